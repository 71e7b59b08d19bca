// Shared by every page: the signed-in caller, the API client, the error banner, DOM building
// and number formatting. Plain ES modules, no build step.

const TOKEN_KEY = 'celld.token';

/** The signed-in caller: `token`, and `me` (GET /api/me: name, role, may.{operate,administer}). */
export const session = {
  token: localStorage.getItem(TOKEN_KEY),
  me: null,
  /** Called when the server refuses the token (401): back to the sign-in page. */
  onRefused: () => {},
};

export function saveToken(token) {
  session.token = token;
  localStorage.setItem(TOKEN_KEY, token);
}

export function forgetToken() {
  session.token = null;
  session.me = null;
  localStorage.removeItem(TOKEN_KEY);
}

export const may = {
  operate: () => Boolean(session.me && session.me.may.operate),
  administer: () => Boolean(session.me && session.me.may.administer),
};

/** A refused or failed request, with the server's error code and message. */
export class RequestError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
  }
}

/**
 * Calls the API with the session's token. `json` sends a JSON body; `body` and `type` send raw
 * bytes; `raw` returns the Response. Throws a RequestError naming the problem; an unreachable
 * server is status 0.
 */
export async function api(path, { method = 'GET', json, body, type, raw = false } = {}) {
  const headers = {};
  if (session.token) headers.Authorization = `Bearer ${session.token}`;
  if (json !== undefined) {
    headers['Content-Type'] = 'application/json';
    body = JSON.stringify(json);
  } else if (type) {
    headers['Content-Type'] = type;
  }
  let response;
  try {
    response = await fetch(path, { method, headers, body });
  } catch (error) {
    linkState(false);
    throw new RequestError(0, 'unreachable', `cannot reach the server at ${location.host} (${error.message})`);
  }
  linkState(true);
  if (!response.ok) {
    let code = `http_${response.status}`;
    let message = `${method} ${path} answered ${response.status} ${response.statusText}`;
    try {
      const answer = await response.json();
      if (answer && answer.error) {
        code = answer.error.code;
        message = answer.error.message;
      }
    } catch (_) { /* not JSON: keep the status line */ }
    if (response.status === 401 && path !== '/api/me') session.onRefused(message);
    throw new RequestError(response.status, code, message);
  }
  if (raw) return response;
  const contentType = response.headers.get('Content-Type') || '';
  return contentType.includes('json') ? response.json() : response.text();
}

/** Fetches `path` with the token and saves the answer as `filename`. */
export async function download(path, filename) {
  const response = await api(path, { raw: true });
  const url = URL.createObjectURL(await response.blob());
  const link = h('a', { href: url, download: filename });
  document.body.append(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

// ---- the banner and the connection pill

let unreachableSince = null;

let bannerTimer = null;

/** Shows `text` above the page; an `info` banner goes away by itself after 8 s. */
export function showBanner(text, kind = 'error') {
  const banner = document.getElementById('banner');
  banner.className = kind === 'error' ? '' : kind;
  document.getElementById('banner-text').textContent = text;
  banner.hidden = false;
  clearTimeout(bannerTimer);
  if (kind === 'info') bannerTimer = setTimeout(hideBanner, 8000);
}

export function hideBanner() {
  document.getElementById('banner').hidden = true;
}

/** Shows what went wrong with a request: the server's refusal, or that it is unreachable. */
export function showError(error, doing) {
  const prefix = doing ? `${doing}: ` : '';
  if (error instanceof RequestError && error.status === 0) {
    showBanner(`${prefix}${error.message}. Retrying; nothing stored on the server is lost.`);
  } else if (error instanceof RequestError) {
    showBanner(`${prefix}refused (${error.status} ${error.code}): ${error.message}`);
  } else {
    showBanner(`${prefix}${error.message || error}`);
  }
}

/** Marks the connection up or down; coming back clears an "unreachable" banner. */
export function linkState(up, detail) {
  const pill = document.getElementById('link-state');
  if (up) {
    pill.textContent = detail || 'online';
    pill.className = 'pill ok';
    if (unreachableSince) {
      unreachableSince = null;
      hideBanner();
    }
  } else {
    if (!unreachableSince) unreachableSince = new Date();
    pill.textContent = 'unreachable';
    pill.className = 'pill bad';
    showBanner(`The server at ${location.host} does not answer (since ${unreachableSince.toLocaleTimeString()}). ` +
      'Retrying every few seconds; the cell keeps its own state and nothing stored is lost.');
  }
}

// ---- DOM

/**
 * Builds an element: `attrs` are properties and attributes (`class`, `text`, `onclick`...,
 * `data-*`, anything else as an attribute); children are nodes, strings, arrays or null.
 */
export function h(tag, attrs = {}, ...children) {
  const element = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs || {})) {
    if (value === null || value === undefined || value === false) continue;
    if (key === 'class') element.className = value;
    else if (key === 'text') element.textContent = value;
    else if (key.startsWith('on')) element.addEventListener(key.slice(2), value);
    else if (key === 'value') element.value = value;
    // Through the CSSOM: the page's Content-Security-Policy refuses inline style attributes.
    else if (key === 'style') element.style.cssText = value;
    else if (value === true) element.setAttribute(key, '');
    else element.setAttribute(key, value);
  }
  for (const child of children.flat(Infinity)) {
    if (child === null || child === undefined || child === false) continue;
    element.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return element;
}

/** A status badge: `<span class="pill status-succeeded">succeeded</span>`. */
export function pill(status, id) {
  return h('span', { class: `pill status-${status}`, id, 'data-status': status, text: status });
}

/** A term/definition list from [label, value] pairs (null values are skipped). */
export function facts(pairs) {
  return h('dl', { class: 'facts' },
    pairs.filter(([, value]) => value !== null && value !== undefined)
      .map(([label, value]) => [h('dt', { text: label }), h('dd', {}, value)]));
}

export function table(headings, rows) {
  return h('div', { class: 'table-wrap' },
    h('table', {},
      h('thead', {}, h('tr', {}, headings.map((text) => h('th', { text })))),
      h('tbody', {}, rows)));
}

/**
 * A card whose form sends one chosen file as the body of `POST path?name=NAME` (content type
 * `type`); the name defaults to the file's name less `extension`. `done(answer)` or
 * `failed(error)` follows.
 */
export function uploadCard({ id, title, action, note, accept, extension, path, type, done, failed }) {
  const file = h('input', { id: `${id}-file`, type: 'file', accept, required: true });
  const name = h('input', { id: `${id}-name`, placeholder: 'name (default: the file name)' });
  const send = async (event) => {
    event.preventDefault();
    const chosen = file.files[0];
    if (!chosen) return;
    const label = name.value.trim() || chosen.name.replace(extension, '');
    try {
      done(await api(`${path}?name=${encodeURIComponent(label)}`, { method: 'POST', body: chosen, type }));
    } catch (error) {
      failed(error);
    }
  };
  return h('section', { class: 'card stack' },
    h('h2', { text: title }),
    h('p', { class: 'muted', text: note }),
    h('form', { class: 'inline row', onsubmit: send },
      h('label', {}, 'File', file), h('label', {}, 'Name', name), h('button', { type: 'submit', text: action })));
}

// ---- numbers and times

export function fmt(value, digits = 2) {
  if (value === null || value === undefined || Number.isNaN(value)) return '–';
  return Number(value).toFixed(digits);
}

export function percent(rate) {
  return rate === null || rate === undefined ? '–' : `${(100 * rate).toFixed(1)} %`;
}

/** Stored times are UTC ISO 8601; show them in the browser's time zone. */
export function when(iso) {
  return iso ? new Date(iso).toLocaleString() : '–';
}

/** A `datetime-local` input's value as the UTC ISO time the API filters take. */
export function toUtc(localValue) {
  return localValue ? new Date(localValue).toISOString() : '';
}

/** A UTC ISO time as a `datetime-local` input's value. */
export function toLocalInput(iso) {
  if (!iso) return '';
  const date = new Date(iso);
  const pad = (n) => String(n).padStart(2, '0');
  return `${date.getFullYear()}-${pad(date.getMonth() + 1)}-${pad(date.getDate())}T${pad(date.getHours())}:${pad(date.getMinutes())}`;
}

export const FINAL_STATUSES = ['succeeded', 'failed', 'cancelled', 'interrupted'];
export const JOB_STATUSES = ['queued', 'running', ...FINAL_STATUSES];
