// The live cell: its PackML state and counters, e-stop state, the running job as it happens
// (from the telemetry stream), and, for operators, starting a job, cancel, stop, e-stop and reset.

import { StepPlots } from './charts.js';
import {
  FINAL_STATUSES, api, facts, fmt, h, may, pill, showBanner, showError,
} from './lib.js';

export async function render(page) {
  const plots = new StepPlots('live');
  const estopState = h('div', { id: 'estop-state', class: 'estop-state', text: '…' });
  const driverState = h('div', { id: 'driver-state', class: 'estop-state', text: '…' });
  const machineState = h('div', { id: 'machine-state', class: 'big', text: '…' });
  const machineFacts = h('div', { id: 'machine-facts' });
  const cellFacts = h('div', { id: 'cell-facts' });
  const jobLine = h('div', { id: 'live-job', class: 'big', text: 'No job yet' });
  const jobFacts = h('div', { id: 'live-job-facts' });
  const controls = may.operate() ? controlsCard() : h('section', { class: 'card', id: 'viewer-note' },
    h('h2', { text: 'Controls' }),
    h('p', { class: 'muted', text: 'Your token may watch the cell. Starting jobs, cancel, e-stop and reset need the operator role.' }));

  page.main.append(
    h('h1', { text: 'Live cell' }),
    h('div', { class: 'grid' },
      h('section', { class: 'card' }, h('h2', { text: 'Cell' }), machineState, machineFacts, estopState, driverState, cellFacts),
      h('section', { class: 'card' }, h('h2', { text: 'Current job' }), jobLine, jobFacts),
      controls),
    h('div', { style: 'height:1rem' }),
    plots.element);
  plots.mount();
  page.onCleanup(() => plots.destroy());

  /** The job on show: its id and last known status. */
  let shown = { id: null, status: null };

  function showJob(job) {
    const changed = job.id !== shown.id;
    if (changed) plots.reset();
    shown = { id: job.id, status: job.status };
    jobLine.dataset.jobId = job.id;
    jobLine.dataset.status = job.status;
    jobLine.replaceChildren(h('a', { href: `#/jobs/${job.id}`, text: `Job ${job.id}` }), ' ', pill(job.status, 'live-job-status'));
    jobFacts.replaceChildren(facts([
      ['controller', job.controller],
      ['seed', job.seed],
      ['initial', job.initial ? `${job.initial.pos_mm} mm, ${job.initial.ori_deg} deg` : null],
      ['steps', job.steps],
      ['reward', job.reward === null || job.reward === undefined ? null : fmt(job.reward, 3)],
      ['failure', job.failure_reason],
      ['final errors', job.final_errors ? `lateral ${fmt(job.final_errors.lateral_mm, 4)} mm, tilt ${fmt(job.final_errors.tilt_deg, 4)} deg` : null],
    ]));
    return changed;
  }

  /** Loads a job and the steps stored so far (on opening the page, or after missing events). */
  async function load(id) {
    const [job, steps] = await Promise.all([api(`/api/jobs/${id}`), api(`/api/jobs/${id}/steps`)]);
    showJob(job);
    for (const step of steps.items) plots.add(step);
  }

  async function refreshCell() {
    const cell = await api('/api/cell');
    estopState.textContent = cell.estop_latched ? 'E-STOP LATCHED: reset to run jobs' : 'E-stop clear';
    estopState.className = `estop-state ${cell.estop_latched ? 'latched' : 'clear'}`;
    estopState.dataset.latched = cell.estop_latched;
    const latch = cell.driver_latch;
    driverState.textContent = latch
      ? `ROBOT DRIVER LATCHED (${latch.code}) since ${new Date(latch.since_unix_ms).toLocaleString()}: ${latch.reason}. Reset once the hardware is ready.`
      : 'Robot driver ready';
    driverState.className = `estop-state ${latch ? 'latched' : 'clear'}`;
    driverState.dataset.latched = Boolean(latch);
    const latched = cell.estop_latched || Boolean(latch);
    const machine = cell.machine;
    const counters = machine.counters;
    machineState.textContent = machine.state;
    machineState.dataset.state = machine.state;
    const mean = counters.good ? counters.total_cycle_time_s / counters.good : null;
    machineFacts.replaceChildren(facts([
      ['stop reason', machine.stop_reason ? `${machine.stop_reason.message} (${machine.stop_reason.code})` : 'none'],
      ['parts', `${counters.processed} processed, ${counters.good} good, ${counters.defective} defective`],
      ['defective by reason', Object.entries(counters.defective_by_reason).map(([k, v]) => `${k} ${v}`).join(', ') || 'none'],
      ['cycle time', mean === null ? '–' : `last ${fmt(counters.last_cycle_time_s, 2)} s, mean ${fmt(mean, 2)} s`],
      ['e-stops', counters.estops],
    ]));
    const stopped = ['Stopped', 'Aborted'].includes(machine.state);
    const pose = cell.last_pose;
    cellFacts.replaceChildren(facts([
      ['cell', cell.cell],
      ['backend', cell.backend],
      ['running', cell.current_job ?? 'none'],
      ['queue', cell.queue.length ? cell.queue.join(', ') : 'empty'],
      ['accepting jobs', cell.accepting_jobs ? 'yes' : `no (${latched ? 'latched' : stopped ? machine.state : 'shutting down'})`],
      ['last pose error', pose ? `(${pose.position_mm.map((v) => fmt(v, 3)).join(', ')}) mm, (${pose.orientation_deg.map((v) => fmt(v, 3)).join(', ')}) deg` : '–'],
    ]));
    page.main.querySelectorAll('[data-needs-clear]').forEach((b) => { b.disabled = latched || stopped; });
    const reset = page.main.querySelector('#reset');
    if (reset) reset.disabled = !latched && !stopped;
    const stop = page.main.querySelector('#stop');
    if (stop) stop.disabled = stopped || ['Stopping', 'Aborting', 'Clearing'].includes(machine.state);
    const cancel = page.main.querySelector('#cancel-job');
    if (cancel) cancel.disabled = cell.current_job === null && cell.queue.length === 0;
    return cell;
  }

  // Events: a new job's first event switches the plots to it.
  page.onCleanup(page.telemetry.subscribe((kind, data) => {
    if (kind === 'step') {
      if (data.job_id !== shown.id) showJob({ id: data.job_id, status: 'running' });
      plots.add(data);
    } else if (kind === 'job') {
      if (data.job_id === shown.id || data.status === 'running') {
        if (data.job_id !== shown.id) showJob({ id: data.job_id, status: data.status });
        jobLine.dataset.status = data.status;
        shown.status = data.status;
        // The final record (reward, errors) is read back from the store.
        api(`/api/jobs/${data.job_id}`).then((job) => { if (job.id === shown.id) showJob(job); }).catch((e) => showError(e, 'Reading the job'));
      }
      refreshCell().catch(() => {});
    } else if (kind === 'cell' || kind === 'machine') {
      refreshCell().catch(() => {});
    } else if (kind === 'lagged' && shown.id !== null) {
      plots.gap = true;
    }
  }));

  // The stream can drop events (a reconnect); a slow poll keeps the page right regardless.
  page.every(2000, async () => {
    const cell = await refreshCell();
    if (plots.gap && shown.id !== null) {
      // Events were lost (a lagging or reconnected stream): redraw from the stored steps.
      plots.reset();
      await load(shown.id);
    }
    if (cell.current_job !== null && cell.current_job !== shown.id) await load(cell.current_job);
    else if (shown.id !== null && !FINAL_STATUSES.includes(shown.status)) await load(shown.id);
  });

  const cell = await refreshCell();
  const latest = cell.current_job ?? (await api('/api/jobs?limit=1')).items[0]?.id;
  if (latest !== undefined && latest !== null) await load(latest);
  if (may.operate()) await fillControllers(page.main.querySelector('#start-controller'), cell.controllers);

  // ---- operator controls

  function controlsCard() {
    const number = (id, label, attrs) => h('label', {}, label, h('input', { id, type: 'number', ...attrs }));
    const form = h('form', { id: 'start-form', class: 'inline stack', onsubmit: startJob },
      h('div', { class: 'row' },
        h('label', {}, 'Controller', h('select', { id: 'start-controller' }, h('option', { value: 'active', text: 'active (the active policy)' }))),
        number('start-seed', 'Seed', { min: 0, step: 1, placeholder: 'random' })),
      h('div', { class: 'row' },
        number('start-pos', 'Initial offset, mm', { min: 0, max: 200, step: 'any', placeholder: 'cell default' }),
        number('start-ori', 'Initial tilt, deg', { min: 0, max: 20, step: 'any', placeholder: 'cell default' }),
        h('label', { class: 'check' }, h('input', { id: 'start-demo', type: 'checkbox' }), 'Record as demonstration')),
      h('div', { class: 'row' }, h('button', { id: 'start-job', type: 'submit', 'data-needs-clear': true, text: 'Start job' })));
    return h('section', { class: 'card stack' },
      h('h2', { text: 'Run' }),
      form,
      h('div', { class: 'row' },
        h('button', { id: 'estop', class: 'estop', type: 'button', onclick: estop, text: 'E-STOP' }),
        h('button', { id: 'cancel-job', class: 'danger', type: 'button', onclick: cancel, text: 'Cancel job' }),
        h('button', { id: 'stop', class: 'danger', type: 'button', onclick: stop, text: 'Stop' }),
        h('button', { id: 'reset', class: 'secondary', type: 'button', onclick: reset, text: 'Reset' })));
  }

  async function startJob(event) {
    event.preventDefault();
    const value = (id) => page.main.querySelector(id).value.trim();
    const body = { controller: value('#start-controller') };
    if (value('#start-seed') !== '') body.seed = Number(value('#start-seed'));
    const [pos, ori] = [value('#start-pos'), value('#start-ori')];
    if ((pos === '') !== (ori === '')) {
      showBanner('Give both the initial offset and the initial tilt, or neither (the cell default).');
      return;
    }
    if (pos !== '') body.initial = { pos_mm: Number(pos), ori_deg: Number(ori) };
    if (page.main.querySelector('#start-demo').checked) body.demonstration = true;
    try {
      const job = await api('/api/jobs', { method: 'POST', json: body });
      // The stream may already have shown this job (a fast twin finishes within milliseconds).
      if (shown.id === null || job.id > shown.id) {
        const busy = (await refreshCell()).current_job;
        if (busy === null || busy === undefined) showJob(job);
      }
      showBanner(`Job ${job.id} created (${job.controller}, seed ${job.seed}).`, 'info');
    } catch (error) {
      showError(error, 'Starting the job');
    }
  }

  // An e-stop asks nobody: it acts at once.
  async function estop() {
    try {
      await api('/api/cell/estop', { method: 'POST' });
      showBanner('E-stop latched: motion stopped, the running job failed with `estop`, the queue was cancelled.');
    } catch (error) {
      showError(error, 'E-stop');
    }
    refreshCell().catch(() => {});
  }

  async function cancel() {
    const cellNow = await refreshCell();
    const id = cellNow.current_job ?? cellNow.queue[0];
    if (id === null || id === undefined) return;
    if (!confirm(`Cancel job ${id}? The robot holds where it is.`)) return;
    try {
      const job = await api(`/api/jobs/${id}/cancel`, { method: 'POST' });
      showBanner(`Job ${job.id} is ${job.status}.`, 'info');
    } catch (error) {
      showError(error, 'Cancelling');
    }
  }

  // PackML Stop: the robot holds, running and queued jobs are cancelled; a reset takes jobs again.
  async function stop() {
    if (!confirm('Stop the cell? The robot holds, the running and queued jobs are cancelled, and the cell takes no jobs until a reset.')) return;
    try {
      await api('/api/cell/stop', { method: 'POST' });
      showBanner('Cell stopped: reset it to take jobs again.', 'info');
    } catch (error) {
      showError(error, 'Stop');
    }
    refreshCell().catch(() => {});
  }

  async function reset() {
    if (!confirm('Reset the cell? This clears the e-stop and the robot driver\'s latch after checking the hardware, and starts no motion. Is the cell safe to run?')) return;
    try {
      await api('/api/cell/reset', { method: 'POST' });
      showBanner('Cell reset: the cell takes jobs again. Nothing was started.', 'info');
    } catch (error) {
      showError(error, 'Reset');
    }
    refreshCell().catch(() => {});
  }
}

/** The controller choices: `active`, the built-in and bundled ones, and registered policies. */
async function fillControllers(select, builtins) {
  for (const name of builtins) select.append(h('option', { value: name, text: name }));
  try {
    const { items } = await api('/api/policies');
    for (const policy of items) {
      select.append(h('option', { value: `policy:${policy.id}`, text: `policy ${policy.id}: ${policy.name} (${policy.status})` }));
    }
  } catch (error) {
    showError(error, 'Listing policies');
  }
}
