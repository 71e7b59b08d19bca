// Plots (Chart.js, vendored in /vendor): the per-step plots of a job, shared by the live view
// and the job page, and the history and training charts.

import { fmt, h, table } from './lib.js';

const Chart = window.Chart;
Chart.defaults.animation = false;
Chart.defaults.maintainAspectRatio = false;
Chart.defaults.font.family = getComputedStyle(document.documentElement).fontFamily;

const COLOURS = ['#1f5fbf', '#d9822b', '#1b7f3b', '#b3261e', '#7b3fb0', '#0f8a8a'];
/** Errors reach micrometres: a log axis needs a floor above zero. */
const LOG_FLOOR = 1e-4;

/** A titled card holding one chart's canvas (`id` is the canvas's id). */
export function chartCard(title, id, note) {
  return h('section', { class: 'card' },
    h('h2', { text: title }),
    note ? h('p', { class: 'muted', text: note }) : null,
    h('div', { class: 'chart' }, h('canvas', { id })));
}

function linearAxis(title, extra = {}) {
  return { type: 'linear', title: { display: true, text: title }, ...extra };
}

function lineSet(label, colour, extra = {}) {
  return { label, data: [], borderColor: colour, backgroundColor: colour, pointRadius: 0, borderWidth: 1.5, ...extra };
}

/** A move `[dx, dy, dz, rx, ry, rz]` as text: mm, then deg; a dash for none. */
function moveText(move) {
  if (!move) return '–';
  const part = (values) => values.map((v) => fmt(v, 2)).join(' ');
  return `${part(move.slice(0, 3))} mm · ${part(move.slice(3))}°`;
}

/**
 * The plots of one job's steps: pose errors, leg lengths, the actor and step size at each step,
 * the trajectory of Segment I (top and side views), the supervisor's vetoes, and a table of
 * each step's proposal, the move made and the rules that changed it. `prefix` names the
 * canvases (`chart-<prefix>-errors`, ...) and the table (`<prefix>-steps`). `add(step)` takes a
 * step as the API and the telemetry give it; drawing is batched to one frame.
 */
export class StepPlots {
  constructor(prefix) {
    this.prefix = prefix;
    this.element = h('div', { class: 'stack' },
      h('div', { class: 'grid wide' },
        chartCard('Pose error (measured)', `chart-${prefix}-errors`, 'Position |P| in mm and orientation |O| in deg, and the σ of the sideways estimate in mm, log scale'),
        chartCard('Leg lengths', `chart-${prefix}-legs`, 'The six SPS legs, mm'),
        chartCard('Actor and step size', `chart-${prefix}-actor`, 'The actor the selector chose at each step; bar height is the step scale ω3 (0–1)'),
        h('section', { class: 'card' },
          h('h2', {}, 'Supervisor vetoes ', h('span', { class: 'pill', id: `${prefix}-veto-count`, text: '0' })),
          h('ol', { class: 'vetoes', id: `${prefix}-vetoes` }),
          h('p', { class: 'muted', id: `${prefix}-vetoes-none`, text: 'No move was vetoed.' }))),
      h('div', { class: 'grid wide' },
        chartCard('Segment I trajectory, top view', `chart-${prefix}-trajectory`, 'Measured position of Segment I in the camera frame {W}: x against y, mm'),
        chartCard('Segment I trajectory, side view', `chart-${prefix}-trajectory-side`, 'x against z (along the camera axis), mm')),
      h('section', { class: 'card' },
        h('h2', {}, 'Proposals and rules ', h('span', { class: 'pill', id: `${prefix}-ruled-count`, title: 'steps a rule changed', text: '0' })),
        h('p', { class: 'muted', text: 'What the controller proposed, the move made and the rules that changed it (learned policies; other controllers propose nothing of their own). Rows a rule changed are marked.' }),
        h('div', { class: 'steps-table', id: `${prefix}-steps` }, table(['step', 'proposed', 'made', 'rules'], []))));
    this.pending = false;
    this.charts = [];
    this.lastStep = 0;
    this.ruled = 0;
    this.gap = false;
  }

  /** Creates the charts; call once `element` is in the document. */
  mount() {
    const canvas = (name) => this.element.querySelector(`#chart-${this.prefix}-${name}`);
    const stepAxis = linearAxis('step', { min: 1, ticks: { precision: 0 } });
    this.errors = new Chart(canvas('errors'), {
      type: 'line',
      data: { datasets: [lineSet('position mm', COLOURS[0], { yAxisID: 'mm' }), lineSet('orientation deg', COLOURS[1], { yAxisID: 'deg' }), lineSet('σ sideways mm', COLOURS[3], { yAxisID: 'mm', borderDash: [4, 3] })] },
      options: {
        parsing: false,
        scales: {
          x: stepAxis,
          mm: { type: 'logarithmic', position: 'left', title: { display: true, text: 'mm' } },
          deg: { type: 'logarithmic', position: 'right', title: { display: true, text: 'deg' }, grid: { drawOnChartArea: false } },
        },
      },
    });
    this.legs = new Chart(canvas('legs'), {
      type: 'line',
      data: { datasets: COLOURS.map((colour, i) => lineSet(`leg ${i + 1}`, colour)) },
      options: { parsing: false, scales: { x: stepAxis, y: linearAxis('mm') } },
    });
    const bars = (label, colour) => ({ label, data: [], backgroundColor: colour, barPercentage: 1, categoryPercentage: 1, grouped: false });
    this.actor = new Chart(canvas('actor'), {
      type: 'bar',
      data: { datasets: [bars('position actor', COLOURS[0]), bars('orientation actor', COLOURS[1]), bars('no actor', '#9aa3ae')] },
      options: { parsing: false, scales: { x: { ...stepAxis, offset: true }, y: linearAxis('step scale', { min: 0, max: 1 }) } },
    });
    const path = (label, colour) => ({ label, data: [], showLine: true, borderColor: colour, backgroundColor: colour, pointRadius: 2, borderWidth: 1.5 });
    const endpoints = () => ({ label: 'start / end', data: [], backgroundColor: '#182030', pointRadius: 5, pointStyle: 'rectRot', showLine: false });
    this.top = new Chart(canvas('trajectory'), {
      type: 'scatter',
      data: { datasets: [path('Segment I', COLOURS[2]), endpoints()] },
      options: { parsing: false, scales: { x: linearAxis('x mm'), y: linearAxis('y mm') } },
    });
    this.side = new Chart(canvas('trajectory-side'), {
      type: 'scatter',
      data: { datasets: [path('Segment I', COLOURS[4]), endpoints()] },
      options: { parsing: false, scales: { x: linearAxis('x mm'), y: linearAxis('z mm', { reverse: true }) } },
    });
    this.charts = [this.errors, this.legs, this.actor, this.top, this.side];
    this.vetoes = this.element.querySelector(`#${this.prefix}-vetoes`);
    this.vetoCount = this.element.querySelector(`#${this.prefix}-veto-count`);
    this.vetoesNone = this.element.querySelector(`#${this.prefix}-vetoes-none`);
    this.steps = this.element.querySelector(`#${this.prefix}-steps tbody`);
    this.ruledCount = this.element.querySelector(`#${this.prefix}-ruled-count`);
  }

  /** Empties every plot (a new job). */
  reset() {
    for (const chart of this.charts) for (const set of chart.data.datasets) set.data = [];
    this.vetoes.replaceChildren();
    this.vetoCount.textContent = '0';
    this.vetoesNone.hidden = false;
    this.steps.replaceChildren();
    this.ruledCount.textContent = '0';
    this.ruled = 0;
    this.lastStep = 0;
    this.gap = false;
    this.redraw();
  }

  /**
   * Steps arrive in order; one already shown (a repeat after a refetch) is skipped, and one
   * that skips ahead (events lost to a reconnect) sets `gap` so the caller can reload.
   */
  add(step) {
    if (step.step <= this.lastStep) return;
    if (step.step !== this.lastStep + 1) this.gap = true;
    this.lastStep = step.step;
    const s = step.state;
    const x = step.step;
    const floor = (v) => Math.max(v, LOG_FLOOR);
    this.errors.data.datasets[0].data.push({ x, y: floor(Math.hypot(s[6], s[7], s[8])) });
    this.errors.data.datasets[1].data.push({ x, y: floor(Math.hypot(s[9], s[10], s[11])) });
    if (step.uncertainty) this.errors.data.datasets[2].data.push({ x, y: floor(step.uncertainty.sd_lateral_mm) });
    step.legs_mm.forEach((length, i) => this.legs.data.datasets[i].data.push({ x, y: length }));
    const actor = { position: 0, orientation: 1 }[step.actor] ?? 2;
    this.actor.data.datasets[actor].data.push({ x, y: step.scale ?? 0 });
    for (const [chart, point] of [[this.top, { x: s[0], y: s[1] }], [this.side, { x: s[0], y: s[2] }]]) {
      const [trace, ends] = chart.data.datasets;
      trace.data.push(point);
      ends.data = [trace.data[0], point];
    }
    if (step.detected) {
      this.vetoes.append(h('li', {}, `step ${step.step}: noticed ${step.detected.replaceAll('_', ' ')}`));
      this.vetoCount.textContent = String(this.vetoes.children.length);
      this.vetoesNone.hidden = true;
    }
    const rules = step.rules ?? [];
    this.steps.append(h('tr', { class: rules.length ? 'ruled' : null, 'data-step': step.step },
      h('td', { text: step.step }),
      h('td', { text: moveText(step.proposed) }),
      h('td', { text: moveText(step.action) }),
      h('td', { class: 'wrap' }, rules.map((rule) => h('span', { class: 'tag', text: rule })))));
    if (rules.length) this.ruledCount.textContent = String(++this.ruled);
    if (step.verdict !== 'allowed') {
      this.vetoes.append(h('li', {}, `step ${step.step}: ${step.verdict}`, step.veto_reason ? ` (${step.veto_reason})` : ''));
      this.vetoCount.textContent = String(this.vetoes.children.length);
      this.vetoesNone.hidden = true;
    }
    this.redraw();
  }

  redraw() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      for (const chart of this.charts) chart.update('none');
    });
  }

  destroy() {
    for (const chart of this.charts) chart.destroy();
    this.charts = [];
  }
}

/**
 * Success rate (bars, %) and average steps (line) for each group of GET /api/stats. Returns the
 * chart; the caller destroys it.
 */
export function statsChart(canvas, groups) {
  return new Chart(canvas, {
    type: 'bar',
    data: {
      labels: groups.map((g) => g.key),
      datasets: [
        { label: 'success %', data: groups.map((g) => (g.success_rate === null ? null : 100 * g.success_rate)), backgroundColor: COLOURS[2], yAxisID: 'rate' },
        { type: 'line', label: 'avg steps', data: groups.map((g) => g.avg_steps), borderColor: COLOURS[0], backgroundColor: COLOURS[0], yAxisID: 'steps', pointRadius: 3 },
      ],
    },
    options: {
      scales: {
        rate: { position: 'left', min: 0, max: 100, title: { display: true, text: 'success %' } },
        steps: { position: 'right', min: 0, title: { display: true, text: 'avg steps' }, grid: { drawOnChartArea: false } },
      },
    },
  });
}

/** A training run's learning curve: one line per stage of `points` ({stage, x, value}). */
export function curveChart(canvas, title, points, { log = false } = {}) {
  const stages = [...new Set(points.map((p) => p.stage))];
  return new Chart(canvas, {
    type: 'line',
    data: {
      datasets: stages.map((stage, i) => lineSet(stage, COLOURS[i % COLOURS.length], {
        data: points.filter((p) => p.stage === stage).map((p) => ({ x: p.x, y: log ? Math.max(p.value, 1e-9) : p.value })),
        pointRadius: 1,
      })),
    },
    options: {
      parsing: false,
      scales: { x: linearAxis(title.x, { ticks: { precision: 0 } }), y: { type: log ? 'logarithmic' : 'linear', title: { display: true, text: title.y } } },
    },
  });
}
