// Expert demonstrations: list and export for everyone; import and delete for admins. Recording
// one is a job started with "Record as demonstration" on the live page.

import {
  api, download, h, may, showBanner, showError, table, uploadCard, when,
} from './lib.js';

export async function render(page) {
  const list = h('div', { id: 'demonstration-list' });
  // h() drops the null a role without the form gets.
  page.main.append(h('div', { class: 'stack' },
    h('h1', { text: 'Demonstrations' }),
    h('p', { class: 'muted', text: 'Expert trajectories the learning pipeline imitates. To record one in the cell, start a job with "Record as demonstration" on the live page; its steps are stored here when it succeeds.' }),
    may.administer() ? importCard() : null,
    h('section', { class: 'card' }, list)));

  async function refresh() {
    const { items } = await api('/api/demonstrations');
    const rows = items.map((demo) => h('tr', {},
      h('td', { text: demo.id }),
      h('td', { text: demo.name }),
      h('td', { text: demo.source }),
      h('td', {}, demo.job_id ? h('a', { href: `#/jobs/${demo.job_id}`, text: `job ${demo.job_id}` }) : '–'),
      h('td', { text: demo.episodes }),
      h('td', { text: demo.steps }),
      h('td', { text: demo.inputs }),
      h('td', { text: demo.cell_hash }),
      h('td', { text: `${when(demo.created_at)}${demo.created_by ? ` by ${demo.created_by}` : ''}` }),
      h('td', {}, h('div', { class: 'row' },
        h('button', { type: 'button', class: 'secondary', text: 'Export', onclick: () => download(`/api/demonstrations/${demo.id}`, `${demo.name}.jsonl`).catch((e) => showError(e, 'Exporting')) }),
        may.administer() ? h('button', { type: 'button', class: 'danger', text: 'Delete', onclick: () => remove(demo) }) : null))));
    list.replaceChildren(items.length
      ? table(['id', 'name', 'source', 'job', 'episodes', 'steps', 'inputs', 'cell', 'created', ''], rows)
      : h('p', { class: 'muted', text: 'No demonstration is stored yet.' }));
  }

  async function remove(demo) {
    if (!confirm(`Delete demonstration ${demo.id} (${demo.name}, ${demo.steps} steps)? Export it first if it may be needed again.`)) return;
    try {
      await api(`/api/demonstrations/${demo.id}`, { method: 'DELETE' });
      showBanner(`Demonstration ${demo.id} deleted.`, 'info');
    } catch (error) {
      showError(error, 'Deleting');
    }
    refresh().catch((e) => showError(e, 'Listing demonstrations'));
  }

  function importCard() {
    return uploadCard({
      id: 'demonstration',
      title: 'Import',
      action: 'Import',
      note: 'JSON Lines, one step a line: {"episode", "step", "state": [12], "action": [6], "actor", "scale"} (the export format). A bad line is refused with its number and nothing is stored.',
      accept: '.jsonl,.ndjson,application/x-ndjson',
      extension: /\.(jsonl|ndjson)$/,
      path: '/api/demonstrations',
      type: 'application/x-ndjson',
      done: (demo) => {
        showBanner(`Imported demonstration ${demo.id}: ${demo.episodes} episodes, ${demo.steps} steps.`, 'info');
        refresh().catch(() => {});
      },
      failed: (error) => showError(error, 'Import'),
    });
  }

  await refresh();
}
