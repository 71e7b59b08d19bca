// Training runs: the list with progress; one run's learning curve, redrawn while it runs; for
// admins, starting and cancelling a run.

import { curveChart } from './charts.js';
import {
  api, facts, h, may, pill, showBanner, showError, table, when,
} from './lib.js';

export async function render(page) {
  if (page.args[0]) return renderRun(page, page.args[0]);
  const list = h('div', { id: 'training-list' });
  // h() drops the null a role without the form gets.
  page.main.append(h('div', { class: 'stack' },
    h('h1', { text: 'Training runs' }),
    may.administer() ? await startCard() : null,
    h('section', { class: 'card' }, list)));

  async function refresh() {
    const { items } = await api('/api/training');
    list.replaceChildren(items.length
      ? table(['run', 'status', 'stage', 'progress', 'policy', 'started', 'finished', 'error'], items.map((run) => h('tr', {},
        h('td', {}, h('a', { href: `#/training/${run.id}`, text: run.id })),
        h('td', {}, pill(run.status)),
        h('td', { text: run.stage ?? '–' }),
        h('td', {}, progressBar(run.progress)),
        h('td', {}, run.policy_id ? h('a', { href: '#/policies', text: `policy ${run.policy_id}` }) : '–'),
        h('td', { text: when(run.started_at) }),
        h('td', { text: when(run.finished_at) }),
        h('td', { class: 'wrap', text: run.error ?? '' }))))
      : h('p', { class: 'muted', text: 'No training run yet.' }));
  }

  async function startCard() {
    const { items: demos } = await api('/api/demonstrations');
    const number = (id, label, value, attrs = {}) => h('label', {}, label, h('input', { id, type: 'number', value, ...attrs }));
    const form = h('form', { id: 'training-form', class: 'inline stack', onsubmit: start },
      h('div', { class: 'row' },
        h('label', {}, 'Part', h('select', { id: 'training-part' },
          h('option', { value: 'all', text: 'all: BC, LSTM selector, TD3' }),
          h('option', { value: 'bc', text: 'bc: BC actors and the LSTM selector' }))),
        number('training-seed', 'Seed', 2026, { min: 0 }),
        number('training-episodes', 'TD3 episodes', 500, { min: 1 }),
        number('training-record', 'Expert episodes to record', 400, { min: 10 }),
        number('training-dagger', 'DAgger rounds', 0, { min: 0, max: 5, title: 'After the first pass, the policy drives as many episodes as there are demonstrations, the demonstrator labels them, and they teach the actors; then the stages run again' })),
      h('label', { class: 'row', title: 'Cell-relative inputs (a version 2 policy file); every recorded demonstration and TD3 episode on a cell of its own, drawn around this one' },
        h('input', { id: 'training-any-cell', type: 'checkbox' }),
        'For any cell: train a policy for cells it was not trained on'),
      h('label', {}, 'Demonstrations (none chosen: record expert episodes in the twin)',
        h('select', { id: 'training-demos', multiple: true, size: Math.min(4, Math.max(2, demos.length)) },
          demos.map((d) => h('option', { value: d.id, text: `${d.id}: ${d.name} (${d.episodes} episodes, ${d.inputs} inputs)` })))),
      h('div', { class: 'row' }, h('button', { type: 'submit', id: 'training-start', text: 'Start training' })));
    return h('section', { class: 'card stack' },
      h('h2', { text: 'Start a run' }),
      h('p', { class: 'muted', text: 'One run at a time, on a low-priority thread beside the cell. The result is registered as a candidate policy: evaluate it and activate it on the policies page.' }),
      form);

    async function start(event) {
      event.preventDefault();
      const value = (id) => form.querySelector(id).value;
      const chosen = [...form.querySelector('#training-demos').selectedOptions].map((o) => Number(o.value));
      const body = {
        part: value('#training-part'),
        seed: Number(value('#training-seed')),
        episodes: Number(value('#training-episodes')),
      };
      const settings = {};
      if (form.querySelector('#training-any-cell').checked) settings.for_any_cell = true;
      const rounds = Number(value('#training-dagger'));
      if (rounds > 0) settings.dagger_rounds = rounds;
      if (Object.keys(settings).length) body.settings = settings;
      if (chosen.length) body.demonstrations = chosen;
      else body.record = Number(value('#training-record'));
      try {
        const run = await api('/api/training', { method: 'POST', json: body });
        showBanner(`Training run ${run.id} started.`, 'info');
        location.hash = `#/training/${run.id}`;
      } catch (error) {
        showError(error, 'Starting training');
      }
    }
  }

  await refresh();
  page.every(2000, refresh);
}

function progressBar(progress) {
  const percent = Math.round(100 * (progress || 0));
  return h('div', { class: 'row', title: `${percent} %` },
    h('div', { class: 'progress' }, h('div', { style: `width:${percent}%` })), `${percent} %`);
}

async function renderRun(page, id) {
  const header = h('div');
  const summary = h('div', { id: 'training-summary' });
  const actions = h('div', { class: 'row' });
  const lossCanvas = h('canvas', { id: 'chart-training-loss' });
  const td3Canvas = h('canvas', { id: 'chart-training-td3' });
  const td3Note = h('p', { class: 'muted' });
  page.main.append(header,
    h('section', { class: 'card stack' }, summary, actions),
    h('div', { style: 'height:1rem' }),
    h('div', { class: 'grid wide' },
      h('section', { class: 'card' }, h('h2', { text: 'Supervised losses' }),
        h('p', { class: 'muted', text: 'BC actors (MSE) and the LSTM selector, by epoch, log scale' }),
        h('div', { class: 'chart' }, lossCanvas)),
      h('section', { class: 'card' }, h('h2', { text: 'TD3 return' }),
        td3Note,
        h('div', { class: 'chart' }, td3Canvas))));
  let charts = [];
  page.onCleanup(() => charts.forEach((c) => c.destroy()));

  async function refresh() {
    const run = await api(`/api/training/${id}`);
    header.replaceChildren(h('h1', {}, `Training run ${run.id} `, pill(run.status, 'training-status')));
    summary.replaceChildren(facts([
      ['stage', run.stage ?? '–'],
      ['queue', run.queue_position ? `${run.queue_position} in the work queue (1 = next)` : null],
      ['progress', progressBar(run.progress)],
      ['settings', h('code', { text: JSON.stringify(run.settings) })],
      ['demonstrations', (run.demonstration_ids || []).join(', ') || '–'],
      ['result', run.policy_id ? h('a', { href: '#/policies', text: `policy ${run.policy_id} (candidate)` }) : null],
      ['figures', run.figures ? h('code', { text: JSON.stringify(run.figures) }) : null],
      ['error', run.error ? h('strong', { text: run.error }) : null],
      ['started', `${when(run.started_at)} by ${run.created_by}`],
      ['finished', when(run.finished_at)],
    ]));
    const unfinished = ['queued', 'running'].includes(run.status);
    actions.replaceChildren(...(unfinished && may.administer()
      ? [h('button', {
        type: 'button', class: 'danger', text: 'Cancel run',
        onclick: async () => {
          if (!confirm(`Cancel training run ${run.id}? It stops between stages or TD3 episodes; nothing is registered.`)) return;
          try {
            await api(`/api/training/${run.id}/cancel`, { method: 'POST' });
          } catch (error) {
            showError(error, 'Cancelling');
          }
        },
      })]
      : []));
    const curve = run.curve || [];
    td3Note.textContent = run.settings.part === 'bc'
      ? 'This run has no TD3 stage (part bc).'
      : 'Return of each TD3 episode in the twin';
    charts.forEach((c) => c.destroy());
    charts = [
      curveChart(lossCanvas, { x: 'epoch', y: 'loss' }, curve.filter((p) => p.stage !== 'td3'), { log: true }),
      curveChart(td3Canvas, { x: 'episode', y: 'return' }, curve.filter((p) => p.stage === 'td3')),
    ];
    return !unfinished;
  }

  if (!(await refresh())) {
    page.every(1000, refresh);
  }
}
