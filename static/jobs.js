// Run history: jobs with filters and paging, success rate and steps by day and by controller,
// and one job's page with its plots and a CSV download.

import { StepPlots, statsChart } from './charts.js';
import {
  FINAL_STATUSES, JOB_STATUSES, api, download, facts, fmt, h, may, percent, pill, showBanner,
  showError, table, toLocalInput, toUtc, when,
} from './lib.js';

const PAGE_SIZE = 25;

export async function render(page) {
  if (page.args[0]) return renderJob(page, page.args[0]);
  return renderHistory(page);
}

async function renderHistory(page) {
  const query = page.query;
  const filters = {
    status: query.get('status') || '',
    controller: query.get('controller') || '',
    policy_id: query.get('policy_id') || '',
    since: query.get('since') || '',
    until: query.get('until') || '',
  };
  const offset = Math.max(0, Number(query.get('offset')) || 0);
  const input = (id, label, attrs) => h('label', {}, label, h('input', { id, ...attrs }));
  const form = h('form', { id: 'job-filters', class: 'inline row', onsubmit: apply },
    h('label', {}, 'Status', h('select', { id: 'filter-status' },
      h('option', { value: '', text: 'any' }),
      JOB_STATUSES.map((s) => h('option', { value: s, text: s, selected: s === filters.status })))),
    input('filter-controller', 'Controller', { value: filters.controller, placeholder: 'any', size: 12 }),
    input('filter-policy', 'Policy id', { type: 'number', min: 1, value: filters.policy_id, placeholder: 'any' }),
    input('filter-since', 'Created from', { type: 'datetime-local', value: toLocalInput(filters.since) }),
    input('filter-until', 'until', { type: 'datetime-local', value: toLocalInput(filters.until) }),
    h('button', { type: 'submit', text: 'Apply' }),
    h('button', { type: 'button', class: 'secondary', text: 'Clear', onclick: () => { location.hash = '#/jobs'; } }));

  function apply(event) {
    event.preventDefault();
    const next = new URLSearchParams();
    const set = (key, value) => { if (value) next.set(key, value); };
    set('status', form.querySelector('#filter-status').value);
    set('controller', form.querySelector('#filter-controller').value.trim());
    set('policy_id', form.querySelector('#filter-policy').value);
    set('since', toUtc(form.querySelector('#filter-since').value));
    set('until', toUtc(form.querySelector('#filter-until').value));
    location.hash = `#/jobs?${next}`;
  }

  const params = new URLSearchParams({ limit: PAGE_SIZE, offset });
  for (const [key, value] of Object.entries(filters)) if (value) params.set(key, value);
  const range = new URLSearchParams();
  if (filters.since) range.set('since', filters.since);
  if (filters.until) range.set('until', filters.until);
  const [list, byDay, byController] = await Promise.all([
    api(`/api/jobs?${params}`),
    api(`/api/stats?by=day&${range}`),
    api(`/api/stats?by=controller&${range}`),
  ]);

  const rows = list.items.map((job) => h('tr', {},
    h('td', {}, h('a', { href: `#/jobs/${job.id}`, text: job.id })),
    h('td', {}, pill(job.status)),
    h('td', { text: job.controller }),
    h('td', { text: job.policy_id ?? '–' }),
    h('td', { text: when(job.created_at) }),
    h('td', { text: job.steps }),
    h('td', { text: fmt(job.reward, 2) }),
    h('td', { class: 'wrap', text: job.failure_reason ?? '' })));
  const pageLink = (label, to, disabled) => h('button', {
    class: 'secondary', type: 'button', disabled, text: label,
    onclick: () => { query.set('offset', to); location.hash = `#/jobs?${query}`; },
  });
  const last = Math.min(offset + list.items.length, list.total);
  const total = byDay.total;

  page.main.append(
    h('h1', { text: 'Run history' }),
    h('section', { class: 'card stack' },
      form,
      h('p', { class: 'muted', id: 'job-count' }, list.total ? `Jobs ${offset + 1}–${last} of ${list.total}` : 'No job matches these filters.'),
      table(['job', 'status', 'controller', 'policy', 'created', 'steps', 'reward', 'failure'], rows),
      h('div', { class: 'pager' },
        pageLink('‹ Newer', Math.max(0, offset - PAGE_SIZE), offset === 0),
        pageLink('Older ›', offset + PAGE_SIZE, offset + PAGE_SIZE >= list.total))),
    h('div', { style: 'height:1rem' }),
    h('div', { class: 'grid wide' },
      h('section', { class: 'card' },
        h('h2', { text: 'Success and steps by day' }),
        h('p', { class: 'muted', text: `In this range: ${total.jobs} jobs, ${total.finished} finished, success ${percent(total.success_rate)}, ${fmt(total.avg_steps, 1)} steps on average.` }),
        h('div', { class: 'chart' }, h('canvas', { id: 'chart-stats-day' }))),
      h('section', { class: 'card' },
        h('h2', { text: 'Success and steps by controller' }),
        h('p', { class: 'muted' }, failureText(total.failure_reasons)),
        h('div', { class: 'chart' }, h('canvas', { id: 'chart-stats-controller' })))));
  for (const [id, stats] of [['chart-stats-day', byDay], ['chart-stats-controller', byController]]) {
    const chart = statsChart(page.main.querySelector(`#${id}`), stats.groups);
    page.onCleanup(() => chart.destroy());
  }
}

function failureText(reasons) {
  const entries = Object.entries(reasons || {});
  if (!entries.length) return 'No failures in this range.';
  return `Failure reasons: ${entries.map(([reason, n]) => `${reason} ${n}`).join(', ')}.`;
}

async function renderJob(page, id) {
  const plots = new StepPlots('job');
  const header = h('div');
  const summary = h('div', { id: 'job-summary' });
  const actions = h('div', { class: 'row' },
    h('button', { id: 'job-csv', type: 'button', class: 'secondary', text: 'Download steps (CSV)', onclick: () => download(`/api/jobs/${id}/steps?format=csv`, `job-${id}-steps.csv`).catch((e) => showError(e, 'Downloading')) }));
  page.main.append(header, h('section', { class: 'card stack' }, summary, actions), h('div', { style: 'height:1rem' }), plots.element);
  plots.mount();
  page.onCleanup(() => plots.destroy());

  let job = null;
  async function refresh() {
    const [latest, steps] = await Promise.all([api(`/api/jobs/${id}`), api(`/api/jobs/${id}/steps`)]);
    job = latest;
    header.replaceChildren(h('h1', {}, `Job ${job.id} `, pill(job.status, 'job-status')));
    summary.replaceChildren(facts([
      ['controller', job.policy_id ? h('span', {}, `${job.controller} (`, h('a', { href: '#/policies', text: `policy ${job.policy_id}` }), ')') : job.controller],
      ['seed', job.seed],
      ['initial', `${job.initial.pos_mm} mm, ${job.initial.ori_deg} deg`],
      ['demonstration', job.demonstration ? 'recorded' : null],
      ['created', `${when(job.created_at)} by ${job.created_by ?? '–'}`],
      ['started', when(job.started_at)],
      ['finished', when(job.finished_at)],
      ['steps', job.steps],
      ['reward', fmt(job.reward, 3)],
      ['failure reason', job.failure_reason ? h('strong', { id: 'job-failure', text: job.failure_reason }) : null],
      ['final errors', job.final_errors ? `lateral ${fmt(job.final_errors.lateral_mm, 4)} mm, depth ${fmt(job.final_errors.depth_error_mm, 4)} mm, tilt ${fmt(job.final_errors.tilt_deg, 4)} deg, hole arc ${fmt(job.final_errors.hole_arc_mm, 4)} mm` : null],
    ]));
    for (const step of steps.items) plots.add(step);
    return FINAL_STATUSES.includes(job.status);
  }

  if (!(await refresh())) {
    // Still running or queued: follow it until it ends.
    page.every(1000, refresh);
  }
  if (may.operate()) {
    actions.append(h('button', {
      id: 'job-rerun', type: 'button', class: 'secondary', text: 'Run again (same seed)',
      onclick: async () => {
        try {
          const again = await api('/api/jobs', { method: 'POST', json: { controller: job.controller, seed: job.seed, initial: job.initial } });
          showBanner(`Job ${again.id} created with seed ${again.seed}.`, 'info');
          location.hash = '#/live';
        } catch (error) {
          showError(error, 'Starting the job');
        }
      },
    }));
  }
}
