// celld dashboard: sign-in, the page router, the live telemetry stream and the heartbeat.
// Each page is a module whose `render(page)` fills `page.main` and registers its cleanups.

import {
  api, forgetToken, h, hideBanner, linkState, saveToken, session, showBanner, showError,
} from './lib.js';
import * as live from './live.js';
import * as jobs from './jobs.js';
import * as policies from './policies.js';
import * as demonstrations from './demonstrations.js';
import * as training from './training.js';
import * as fleet from './fleet.js';

const PAGES = {
  live: live.render,
  jobs: jobs.render,
  policies: policies.render,
  demonstrations: demonstrations.render,
  training: training.render,
  fleet: fleet.render,
};

// ---- live telemetry: one EventSource for the whole page, fanned out to the current page.

const telemetry = {
  source: null,
  listeners: new Set(),
  /** `listener(kind, data)` for `step`, `job`, `cell`, `lagged`; returns the unsubscribe. */
  subscribe(listener) {
    this.listeners.add(listener);
    return () => this.listeners.delete(listener);
  },
  open() {
    this.close();
    // EventSource cannot send headers: the stream alone takes the token as a query parameter.
    this.source = new EventSource(`/api/telemetry?access_token=${encodeURIComponent(session.token)}`);
    this.source.onopen = () => linkState(true, 'live');
    this.source.onerror = () => {
      const pill = document.getElementById('link-state');
      pill.textContent = 'stream reconnecting';
      pill.className = 'pill';
    };
    for (const kind of ['step', 'job', 'cell', 'lagged']) {
      this.source.addEventListener(kind, (event) => {
        const data = JSON.parse(event.data);
        for (const listener of this.listeners) listener(kind, data);
      });
    }
  },
  close() {
    if (this.source) this.source.close();
    this.source = null;
  },
};

// ---- routing: #/page/arg?query

/** The page on show; leaving it runs its cleanups. */
let current = { close() {} };

function route() {
  const [path, query = ''] = location.hash.replace(/^#\/?/, '').split('?');
  const [name, ...args] = path.split('/').filter(Boolean);
  return { name: name || 'live', args, query: new URLSearchParams(query) };
}

async function show() {
  current.close();
  const view = document.getElementById('view');
  if (!session.token || !session.me) {
    renderSignIn(view);
    return;
  }
  const { name, args, query } = route();
  const render = PAGES[name];
  for (const link of document.querySelectorAll('#nav a')) {
    link.classList.toggle('current', link.dataset.page === name);
  }
  // Each page draws into its own element: a render still awaiting the server when the user
  // moves on fills a detached element, and what it registers afterwards is cleaned up at once.
  const page = {
    main: h('div'),
    args,
    query,
    telemetry,
    cleanups: [],
    closed: false,
    close() {
      this.closed = true;
      for (const cleanup of this.cleanups.splice(0)) cleanup();
    },
    onCleanup(fn) {
      if (this.closed) fn();
      else this.cleanups.push(fn);
    },
    /**
     * Runs `fn` every `ms` while the page is shown, until it returns (or resolves to) `true`.
     * A failed run is left to the next one (the heartbeat reports an unreachable server).
     */
    every(ms, fn) {
      const timer = setInterval(async () => {
        try {
          if ((await fn()) === true) clearInterval(timer);
        } catch (_) { /* the next run retries */ }
      }, ms);
      this.onCleanup(() => clearInterval(timer));
    },
  };
  current = page;
  view.replaceChildren(page.main);
  if (!render) {
    page.main.append(h('section', { class: 'card' }, h('h1', { text: 'No such page' }), h('a', { href: '#/live', text: 'Back to the live cell' })));
    return;
  }
  try {
    await render(page);
  } catch (error) {
    if (!page.closed) showError(error, `Opening ${name}`);
  }
}

// ---- sign-in

/** Checks the token with the server; on success shows the pages the role may use. */
async function signIn(token) {
  saveToken(token);
  try {
    session.me = await api('/api/me');
  } catch (error) {
    // A refused token is forgotten; an unreachable server is retried by the heartbeat.
    if (error.status === 401) forgetToken();
    throw error;
  }
  document.getElementById('whoami').textContent = `${session.me.name} · ${session.me.role}`;
  document.getElementById('nav').hidden = false;
  document.getElementById('signout').hidden = false;
  telemetry.open();
  hideBanner();
  // The Fleet entry shows only on a cell in a fleet; the answer does not hold up signing in.
  fleet.probe();
}

function signOut(message) {
  telemetry.close();
  forgetToken();
  document.getElementById('whoami').textContent = '';
  document.getElementById('nav').hidden = true;
  document.getElementById('signout').hidden = true;
  if (message) showBanner(`Signed out: ${message}`);
  show();
}

function renderSignIn(main) {
  const input = h('input', { id: 'token', type: 'password', autocomplete: 'current-password', placeholder: 'celld_…', required: true });
  const form = h('form', {
    class: 'card signin stack',
    id: 'signin',
    onsubmit: async (event) => {
      event.preventDefault();
      try {
        await signIn(input.value.trim());
        show();
      } catch (error) {
        showError(error, 'Signing in');
      }
    },
  },
  h('h1', { text: 'Sign in' }),
  h('p', { class: 'muted' }, 'Paste a token. The first start of ', h('code', { text: 'celld serve' }),
    ' prints a sign-in link and writes the admin token to ', h('code', { text: 'admin.token' }),
    ' beside the database; ', h('code', { text: 'celld token create --role viewer|operator|admin --name NAME' }), ' makes more.'),
  h('label', {}, 'Token', input),
  h('button', { id: 'signin-submit', type: 'submit', text: 'Sign in' }));
  main.replaceChildren(form);
  input.focus();
}

// ---- the heartbeat: says when the server is unreachable, and clears that when it is back.

async function heartbeat() {
  try {
    const response = await fetch('/api/health', { cache: 'no-store' });
    linkState(response.ok, telemetry.source && telemetry.source.readyState === 1 ? 'live' : 'online');
    if (response.ok && session.token && !session.me) {
      await signIn(session.token);
      show();
    }
  } catch (_) {
    linkState(false);
  }
}

async function start() {
  session.onRefused = (message) => signOut(`the server refused the token (${message})`);
  document.getElementById('signout').addEventListener('click', () => signOut());
  document.getElementById('banner-close').addEventListener('click', hideBanner);
  window.addEventListener('hashchange', show);
  // The link `celld serve` prints: #token=SECRET signs in and is then removed from the address.
  const fromLink = location.hash.match(/^#token=([^&]+)/);
  if (fromLink) {
    history.replaceState(null, '', `${location.pathname}#/live`);
    saveToken(decodeURIComponent(fromLink[1]));
  }
  if (session.token) {
    try {
      await signIn(session.token);
    } catch (error) {
      showError(error, 'Signing in');
    }
  }
  setInterval(heartbeat, 5000);
  heartbeat();
  show();
}

start();
