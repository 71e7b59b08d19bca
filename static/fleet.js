// The fleet: every cell that replicates to the same PostgreSQL, as that database shows them:
// each cell's heartbeat (state, stop reason, e-stop, active policy, counters, replication
// backlog), the fleet's jobs and stats for one cell or all, and the fleet's policy registry
// with, for admins, "activate where it passed".

import {
  api, fmt, h, may, percent, pill, showError, table, when,
} from './lib.js';

/** How often the view re-reads the fleet, ms. */
const REFRESH_MS = 3000;
/** How long the view follows an activation request's results, ms (each cell answers on its own). */
const FOLLOW_ACTIVATION_MS = 20000;
const JOB_LIMIT = 50;
/** A cell whose last heartbeat is older than this (s) is marked stale; cells beat about every second. */
const STALE_S = 10;

function navLink() {
  return document.querySelector('#nav a[data-page=fleet]');
}

/**
 * Shows the Fleet nav entry only when this cell is in a fleet. `state`: `member`, `unavailable`
 * (PostgreSQL unreachable: the entry stays, the view says why) or `none`; kept on the link as
 * `data-fleet`.
 */
function markNav(state) {
  const link = navLink();
  if (!link) return;
  link.dataset.fleet = state;
  link.hidden = state === 'none';
}

/**
 * Asks the server whether this cell is in a fleet and shows or hides the nav entry. A 404
 * (`no_fleet`, or a server without the fleet API) hides it; a 503 (`fleet_unavailable`) keeps
 * it; an unreachable server changes nothing (the heartbeat signs in again, which asks again).
 */
export async function probe() {
  try {
    await api('/api/fleet/cells');
    markNav('member');
  } catch (error) {
    if (error.status === 404) markNav('none');
    else if (error.status === 503) markNav('unavailable');
  }
}

/** `counters` and the like may come as objects or as the JSON text PostgreSQL keeps. */
function parsed(value) {
  if (typeof value !== 'string') return value ?? null;
  try {
    return JSON.parse(value);
  } catch (_) {
    return value;
  }
}

/** "3 s ago", "4 min ago", "2 h ago", or the time itself after a day. */
export function ago(iso, nowMs) {
  if (!iso) return 'never';
  const seconds = Math.max(0, Math.round((nowMs - Date.parse(iso)) / 1000));
  if (Number.isNaN(seconds)) return iso;
  if (seconds < 60) return `${seconds} s ago`;
  if (seconds < 3600) return `${Math.floor(seconds / 60)} min ago`;
  if (seconds < 86400) return `${Math.floor(seconds / 3600)} h ago`;
  return when(iso);
}

function stopText(cell) {
  const reason = parsed(cell.stop_reason);
  const parts = [];
  if (cell.estop_latched) parts.push(h('strong', { class: 'latched-text', text: 'E-STOP latched' }));
  if (reason && typeof reason === 'object') parts.push(`${reason.message} (${reason.code})`);
  else if (reason) parts.push(String(reason));
  if (!parts.length) return 'none';
  return parts.flatMap((part, i) => (i ? [', ', part] : [part]));
}

function policyText(active) {
  const policy = parsed(active);
  if (!policy) return 'none';
  return h('span', { title: policy.sha256 }, `${policy.name} · ${String(policy.sha256).slice(0, 12)}`);
}

function defectiveText(counters) {
  const reasons = Object.entries(counters.defective_by_reason || {}).map(([why, n]) => `${why} ${n}`);
  return reasons.length ? `${counters.defective} (${reasons.join(', ')})` : String(counters.defective ?? '–');
}

function cellRow(cell, nowMs) {
  const counters = parsed(cell.counters) || {};
  const heardS = cell.last_heard_at ? (nowMs - Date.parse(cell.last_heard_at)) / 1000 : Infinity;
  const stale = heardS > STALE_S;
  return h('tr', {
    'data-cell': cell.cell_id,
    'data-this-cell': String(Boolean(cell.this_cell)),
    'data-state': cell.state ?? '',
    'data-estop-latched': String(Boolean(cell.estop_latched)),
    'data-stale': String(stale),
    class: cell.this_cell ? 'this-cell' : null,
  },
  h('td', {}, cell.cell_id, cell.this_cell ? [' ', h('span', { class: 'tag', text: 'this cell' })] : null),
  h('td', { text: cell.state ?? '–' }),
  h('td', { class: 'wrap' }, stopText(cell)),
  h('td', {}, policyText(cell.active_policy)),
  h('td', { 'data-counter': 'processed', text: counters.processed ?? '–' }),
  h('td', { 'data-counter': 'good', text: counters.good ?? '–' }),
  h('td', { 'data-counter': 'defective', class: 'wrap', text: defectiveText(counters) }),
  h('td', { class: stale ? 'stale' : null, title: when(cell.last_heard_at), text: ago(cell.last_heard_at, nowMs) }),
  h('td', { 'data-backlog': cell.backlog ?? '', text: cell.backlog ?? '–' }),
  h('td', { text: cell.lag_s === null || cell.lag_s === undefined ? '–' : `${fmt(cell.lag_s, 1)} s` }));
}

function jobRow(job, thisCell) {
  // Only this cell's jobs have a page here; another cell's job is shown on that cell's dashboard.
  const id = job.cell_id === thisCell ? h('a', { href: `#/jobs/${job.id}`, text: job.id }) : String(job.id);
  return h('tr', { 'data-cell': job.cell_id, 'data-job-id': job.id },
    h('td', { text: job.cell_id }),
    h('td', {}, id),
    h('td', {}, pill(job.status)),
    h('td', { text: job.controller }),
    h('td', { text: job.policy_id ?? '–' }),
    h('td', { text: when(job.created_at) }),
    h('td', { 'data-steps': job.steps, text: job.steps }),
    h('td', { text: fmt(job.reward, 2) }),
    h('td', { class: 'wrap', text: job.failure_reason ?? '' }));
}

function evaluationText(evaluation) {
  if (!evaluation) return 'not evaluated';
  if (evaluation.status !== 'done') return evaluation.status;
  return `success ${percent(evaluation.success_rate)}`;
}

export async function render(page) {
  const chosen = page.query.get('cell') || '';
  const status = h('div', { id: 'fleet-status', class: 'answer refused', hidden: true });
  const body = h('div', { class: 'stack', hidden: true });
  const cells = h('div', { id: 'fleet-cells' });
  const picker = h('select', {
    id: 'fleet-cell',
    onchange: () => {
      // The pick lives in the address, as the history's filters do.
      location.hash = picker.value ? `#/fleet?cell=${encodeURIComponent(picker.value)}` : '#/fleet';
    },
  }, h('option', { value: '', text: 'all cells' }));
  const stats = h('p', { id: 'fleet-stats', class: 'muted', text: '…' });
  const jobCount = h('p', { id: 'fleet-job-count', class: 'muted' });
  const jobs = h('div', { id: 'fleet-jobs' });
  const activation = h('div', { id: 'fleet-activation', class: 'answer', hidden: true });
  const policies = h('div', { id: 'fleet-policies' });

  body.append(
    h('section', { class: 'card stack' }, h('h2', { text: 'Cells' }), cells),
    h('section', { class: 'card stack' },
      h('h2', { text: 'Jobs' }),
      h('div', { class: 'row' }, h('label', {}, 'Cell', picker)),
      stats, jobCount, jobs),
    h('section', { class: 'card stack' },
      h('h2', { text: 'Policies' }),
      h('p', { class: 'muted', text: 'The fleet\'s registry: each policy, and on each cell its status there and its latest evaluation on that cell.' }),
      activation, policies));
  page.main.append(h('h1', { text: 'Fleet' }), status, body);

  /** What was last drawn, as JSON: a table is redrawn only when it changed. */
  const drawn = { cellIds: null, jobs: null, policies: null };
  /** The fleet's cell ids as last read, and this cell's. */
  let cellIds = [];
  let thisCell = null;

  function say(text) {
    status.textContent = text;
    status.hidden = false;
  }

  function drawCells(items) {
    const nowMs = Date.now();
    cells.replaceChildren(items.length
      ? table(['cell', 'state', 'stop reason', 'active policy', 'processed', 'good', 'defective', 'last heard', 'backlog (rows)', 'lag'],
        items.map((cell) => cellRow(cell, nowMs)))
      : h('p', { class: 'muted', text: 'No cell has reported to the fleet yet.' }));
    // The picker is rebuilt only when the cells change, so an open list is not disturbed.
    const ids = items.map((cell) => cell.cell_id);
    if (chosen && !ids.includes(chosen)) ids.push(chosen);
    const key = JSON.stringify(ids);
    if (key !== drawn.cellIds) {
      drawn.cellIds = key;
      picker.replaceChildren(h('option', { value: '', text: 'all cells' }),
        ...ids.map((id) => h('option', { value: id, text: id, selected: id === chosen })));
      picker.value = chosen;
    }
  }

  function drawJobs(list, figures) {
    const total = figures.total;
    stats.dataset.jobs = total.jobs;
    stats.textContent = `${chosen || 'All cells'}: ${total.jobs} jobs, ${total.finished} finished, success ${percent(total.success_rate)}, ${fmt(total.avg_steps, 1)} steps on average.`;
    const key = JSON.stringify([list, thisCell]);
    if (key === drawn.jobs) return;
    drawn.jobs = key;
    jobCount.dataset.total = list.total;
    jobCount.textContent = list.total
      ? `The ${list.items.length} newest of ${list.total} jobs${chosen ? ` on ${chosen}` : ' in the fleet'}.`
      : `No job${chosen ? ` on ${chosen}` : ' in the fleet'} yet.`;
    jobs.replaceChildren(table(['cell', 'job', 'status', 'controller', 'policy', 'created', 'steps', 'reward', 'failure'],
      list.items.map((job) => jobRow(job, thisCell))));
  }

  function drawPolicies(items) {
    const key = JSON.stringify([items, cellIds]);
    if (key === drawn.policies) return;
    drawn.policies = key;
    // A column per cell: those heard from, then any other a policy names.
    const columns = [...cellIds];
    for (const policy of items) {
      for (const entry of policy.cells) if (!columns.includes(entry.cell_id)) columns.push(entry.cell_id);
    }
    const rows = items.map((policy) => h('tr', { 'data-sha256': policy.sha256 },
      h('td', { text: policy.name }),
      h('td', { title: policy.sha256, text: policy.sha256.slice(0, 12) }),
      columns.map((id) => {
        const entry = policy.cells.find((c) => c.cell_id === id);
        if (!entry) return h('td', { 'data-cell': id, class: 'muted', text: 'not here' });
        return h('td', { 'data-cell': id, 'data-status': entry.status },
          pill(entry.status), ' ', evaluationText(entry.evaluation));
      }),
      may.administer() ? h('td', {}, h('button', {
        type: 'button', class: 'secondary', 'data-action': 'activate', text: 'Activate where it passed',
        onclick: () => activate(policy),
      })) : null));
    policies.replaceChildren(items.length
      ? table(['name', 'sha256', ...columns, ...(may.administer() ? [''] : [])], rows)
      : h('p', { class: 'muted', text: 'No policy is in the fleet\'s registry yet.' }));
  }

  function drawActivation(request, name, following) {
    activation.hidden = false;
    activation.className = 'answer';
    activation.dataset.activationId = request.id;
    const answered = new Set(request.results.map((r) => r.cell_id));
    const waiting = cellIds.filter((id) => !answered.has(id));
    activation.replaceChildren(
      h('div', { text: `Activation ${request.id} of ${name} (${request.sha256.slice(0, 12)}), requested by ${request.requested_by} ${when(request.requested_at)}:` }),
      h('ul', { id: 'fleet-activation-results', class: 'results' },
        request.results.map((r) => h('li', { 'data-cell': r.cell_id, 'data-outcome': r.outcome },
          `${r.cell_id}: `, pill(r.outcome), r.detail ? ` ${r.detail}` : ''))),
      // The DOM's replaceChildren writes a null as the text "null": an empty note instead.
      h('div', { class: 'muted', text: waiting.length ? `${following ? 'Waiting for' : 'No answer yet from'} ${waiting.join(', ')}.` : '' }));
  }

  async function activate(policy) {
    if (!confirm(`Activate ${policy.name} (${policy.sha256.slice(0, 12)}) on every cell of the fleet where it passed the gate on that cell?`)) return;
    let request;
    try {
      request = await api(`/api/fleet/policies/${policy.sha256}/activate`, { method: 'POST' });
    } catch (error) {
      activation.hidden = false;
      activation.className = 'answer refused';
      activation.textContent = `Activation refused (${error.status} ${error.code}): ${error.message}`;
      return;
    }
    drawActivation(request, policy.name, true);
    // Each cell answers when it next polls the fleet: follow the request for a while.
    const started = Date.now();
    page.every(1000, async () => {
      const latest = await api(`/api/fleet/activations/${request.id}`);
      const answered = new Set(latest.results.map((r) => r.cell_id));
      const done = cellIds.every((id) => answered.has(id)) || Date.now() - started > FOLLOW_ACTIVATION_MS;
      drawActivation(latest, policy.name, !done);
      if (done) drawn.policies = null;
      return done;
    });
  }

  /**
   * Reads the whole view; true once there is nothing to follow (this cell is in no fleet). An
   * unreachable fleet database is said in the view and tried again at the next refresh.
   */
  async function refresh() {
    const only = new URLSearchParams(chosen ? { cell: chosen } : {});
    const jobQuery = new URLSearchParams(only);
    jobQuery.set('limit', JOB_LIMIT);
    try {
      const { items } = await api('/api/fleet/cells');
      cellIds = items.map((c) => c.cell_id);
      thisCell = (items.find((c) => c.this_cell) || {}).cell_id ?? null;
      const [list, figures, registry] = await Promise.all([
        api(`/api/fleet/jobs?${jobQuery}`),
        api(chosen ? `/api/fleet/stats?${only}` : '/api/fleet/stats'),
        api('/api/fleet/policies'),
      ]);
      if (page.closed) return true;
      markNav('member');
      status.hidden = true;
      body.hidden = false;
      drawCells(items);
      drawJobs(list, figures);
      drawPolicies(registry.items);
      return false;
    } catch (error) {
      // `no_fleet`, or a server without the fleet API.
      if (error.status === 404) {
        markNav('none');
        say(`This cell is not in a fleet: ${error.message}`);
        body.hidden = true;
        return true;
      }
      if (error.status === 503) {
        markNav('unavailable');
        say(`The fleet's database does not answer (${error.code}): ${error.message}. This cell keeps working on its own and catches up when it is back; retrying every ${REFRESH_MS / 1000} s.`);
        body.hidden = true;
        return false;
      }
      throw error;
    }
  }

  let stop;
  try {
    stop = await refresh();
  } catch (error) {
    showError(error, 'Reading the fleet');
    stop = false;
  }
  if (!stop) page.every(REFRESH_MS, refresh);
}
