// The policy registry: list with evaluation results; for admins upload, evaluate and activate
// (the activation gate's answer is shown as the server gives it).

import {
  api, download, fmt, h, may, percent, pill, showError, table, uploadCard, when,
} from './lib.js';

export async function render(page) {
  const answer = h('div', { id: 'policy-answer', class: 'answer', hidden: true });
  const list = h('div', { id: 'policy-list' });
  /** True while an evaluation is in progress: the list is then refreshed every 2 s. */
  let following = false;
  // h() drops the null a role without the form gets.
  page.main.append(h('div', { class: 'stack' },
    h('h1', { text: 'Policies' }),
    may.administer() ? policyUploadCard() : null,
    h('section', { class: 'card stack' }, answer, list)));

  function say(text, kind) {
    answer.hidden = false;
    answer.className = `answer ${kind}`;
    answer.textContent = text;
  }

  async function refresh() {
    const { items } = await api('/api/policies');
    const rows = items.map((policy) => h('tr', { 'data-policy-id': policy.id },
      h('td', { text: policy.id }),
      h('td', { text: policy.name }),
      h('td', {}, pill(policy.status)),
      h('td', { title: policy.sha256, text: policy.sha256.slice(0, 12) }),
      h('td', { text: `${(policy.size_bytes / 1024).toFixed(0)} KiB` }),
      h('td', { text: when(policy.created_at) }),
      h('td', {}, policy.training_run_id ? h('a', { href: `#/training/${policy.training_run_id}`, text: `run ${policy.training_run_id}` }) : (policy.uploaded_by ?? '–')),
      h('td', { class: 'wrap' }, evaluationText(policy.evaluation)),
      h('td', {}, actions(policy))));
    list.replaceChildren(items.length
      ? table(['id', 'name', 'status', 'sha256', 'size', 'registered', 'from', 'latest evaluation (Table 5 protocol)', ''], rows)
      : h('p', { class: 'muted', text: 'No policy is registered yet.' }));
    return items.some((p) => p.evaluation && ['queued', 'running'].includes(p.evaluation.status));
  }

  function actions(policy) {
    const cell = h('div', { class: 'row' },
      h('button', { type: 'button', class: 'secondary', text: 'Download', onclick: () => download(`/api/policies/${policy.id}/file`, `${policy.name}.safetensors`).catch((e) => showError(e, 'Downloading')) }),
      h('a', { href: `#/jobs?policy_id=${policy.id}`, text: 'jobs' }));
    if (!may.administer()) return cell;
    const episodes = h('input', { type: 'number', min: 1, max: 10000, value: 1000, title: 'episodes', style: 'width:6rem' });
    cell.append(
      episodes,
      h('button', {
        type: 'button', class: 'secondary', text: 'Evaluate',
        onclick: async () => {
          try {
            await api(`/api/policies/${policy.id}/evaluate`, { method: 'POST', json: { episodes: Number(episodes.value) } });
            say(`Evaluating policy ${policy.id} over ${episodes.value} episodes in the background.`, 'accepted');
            following = true;
            refresh().catch(() => {});
          } catch (error) {
            say(`Evaluation refused (${error.status}): ${error.message}`, 'refused');
          }
        },
      }),
    );
    // The DOM's append writes a null as the text "null": the active policy has no Activate.
    if (policy.status !== 'active') {
      cell.append(h('button', { type: 'button', text: 'Activate', onclick: () => activate(policy) }));
    }
    return cell;
  }

  async function activate(policy, force) {
    const body = force ? { force: true, reason: force } : {};
    try {
      const result = await api(`/api/policies/${policy.id}/activate`, { method: 'POST', json: body });
      say(`Policy ${policy.id} is active${result.forced ? ' (forced past the gate, audited)' : ': it passed the gate'}${result.retired ? `; policy ${result.retired} retired (activate it again to roll back)` : ''}.`, 'accepted');
    } catch (error) {
      if (error.status !== 409) {
        say(`Activation refused (${error.status}): ${error.message}`, 'refused');
        return;
      }
      say(`The gate refused: ${error.message}`, 'refused');
      const reason = prompt(`The gate refused policy ${policy.id}:\n${error.message}\n\nTo activate it anyway, give a reason (it is audited). Cancel keeps the current policy.`);
      if (reason && reason.trim()) return activate(policy, reason.trim());
    }
    refresh().catch((e) => showError(e, 'Listing policies'));
  }

  function policyUploadCard() {
    return uploadCard({
      id: 'policy',
      title: 'Upload a policy',
      action: 'Upload',
      note: 'A safetensors file in the layout of docs/design.md §6, or a flat TD3 policy (docs/learning-reference.md) (PyTorch state_dict names, f32). It is checked before anything is stored, and registered as a candidate: evaluate it, then activate it.',
      accept: '.safetensors',
      extension: /\.safetensors$/,
      path: '/api/policies',
      type: 'application/octet-stream',
      done: (policy) => {
        say(`Registered policy ${policy.id} (${policy.name}), status ${policy.status}.`, 'accepted');
        refresh().catch(() => {});
      },
      failed: (error) => say(`Upload refused (${error.status} ${error.code}): ${error.message}`, 'refused'),
    });
  }

  // Evaluations run in the background: follow them while any is in progress.
  following = await refresh();
  page.every(2000, async () => {
    if (following) following = await refresh().catch(() => true);
  });
}

function evaluationText(evaluation) {
  if (!evaluation) return 'not evaluated';
  if (evaluation.status !== 'done') {
    const place = evaluation.queue_position ? ` ${evaluation.queue_position} in the work queue` : '';
    return `${evaluation.status}${place}${evaluation.error ? `: ${evaluation.error}` : ''} (${evaluation.episodes} episodes)`;
  }
  const failures = Object.entries(evaluation.failures || {}).map(([why, n]) => `${why} ${n}`).join(', ');
  return `success ${percent(evaluation.success_rate)}, ${fmt(evaluation.avg_steps, 1)} steps on average, ${evaluation.episodes} episodes (seed ${evaluation.seed}, ${conditions(evaluation)})${failures ? `; failures: ${failures}` : ''}`;
}

/** What an evaluation ran on: this cell (and any mismatch), or cells drawn around it. */
function conditions(evaluation) {
  const parts = [evaluation.randomise_cells ? `cells drawn around cell ${evaluation.cell_hash}` : `cell ${evaluation.cell_hash}`];
  if (!evaluation.randomise_cells && evaluation.noise_scale !== 1) parts.push(`camera noise ×${evaluation.noise_scale}`);
  if (!evaluation.randomise_cells && evaluation.calibration_scale !== 1) parts.push(`calibration error ×${evaluation.calibration_scale}`);
  if (evaluation.fault) parts.push(`fault ${evaluation.fault}`);
  return parts.join(', ');
}
