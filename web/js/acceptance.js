// The rig's acceptance: where the newest stands (valid, due, no longer holds, failed, or none
// recorded), the run while one measures, the recorded acceptances, and the report of the last
// 30 days. Read from GET /acceptance every few seconds; not for a site's uploaded copy.

import { $, clearMessage, el, fmtTime, parseTime, showMessage } from './util.js';
import { api, openInTab } from './api.js';

const REFRESH_MS = 5000;
const STANDING_TEXT = {
  valid: 'valid',
  due: 'due for reverification',
  no_longer_holds: 'no longer holds',
  failed: 'failed',
};
const STANDING_CLASS = { valid: 'ok', due: 'warn', no_longer_holds: 'alarm', failed: 'alarm' };

function render(list) {
  $('acceptance-section').hidden = !list.configured && list.acceptances.length === 0;
  const newest = list.acceptances[0];
  const status = $('acceptance-status');
  status.textContent = '';
  if (!newest) {
    status.append(el('span', { class: 'badge warn', 'data-standing': 'none', text: 'none recorded' }),
      ' The rig has no acceptance: run ', el('code', { text: 'brokenray acceptance' }), '.');
  } else {
    status.append(
      el('span', { class: 'badge ' + STANDING_CLASS[newest.standing], 'data-standing': newest.standing,
        text: STANDING_TEXT[newest.standing] || newest.standing }),
      ` Acceptance ${newest.id} by ${newest.by}, ${fmtTime(parseTime(newest.at))} UTC; `
        + (newest.passed ? `reverify by ${fmtTime(parseTime(newest.due))} UTC.` : 'it did not pass.'));
  }
  const run = $('acceptance-run');
  run.hidden = !list.run || list.run.phase === 'finished';
  if (list.run && list.run.phase !== 'finished') {
    const k = list.run.step;
    run.textContent = `Running (by ${list.run.by}): step ${k + 1} of ${list.run.steps.length}, `
      + `${list.run.steps[k].name}: ${list.run.instruction}`;
  }
  const body = $('acceptances').tBodies[0];
  body.textContent = '';
  for (const a of list.acceptances.slice(0, 10)) {
    const why = [...(a.failed || []).map((f) => 'failed: ' + f), ...(a.changed || [])].join('; ');
    body.append(el('tr', { 'data-acceptance': String(a.id) },
      el('th', { scope: 'row', class: 'num', text: String(a.id) }),
      el('td', { text: fmtTime(parseTime(a.at)) }),
      el('td', { text: a.by }),
      el('td', {}, el('span', { class: 'badge ' + (a.passed ? 'ok' : 'alarm'), text: a.passed ? 'passed' : 'failed' })),
      el('td', {}, el('span', { class: 'badge ' + STANDING_CLASS[a.standing], text: STANDING_TEXT[a.standing] || a.standing })),
      el('td', { text: why || '—' })));
  }
}

async function load() {
  try {
    render(await api('/api/v1/acceptance'));
    clearMessage('acceptance');
  } catch (e) {
    if (e.status !== 401) showMessage('acceptance', 'Acceptance: ' + e.message);
  }
}

let timer = null;
export function startAcceptance() {
  load();
  if (timer === null) {
    timer = setInterval(() => { if (!document.hidden) load(); }, REFRESH_MS);
  }
}

// The report of the last 30 days (the service's default period), the latest acceptance in it.
$('acceptance-report').addEventListener('click', async () => {
  const tab = window.open('', '_blank');
  try {
    await openInTab('/api/v1/report', tab);
    clearMessage('report');
  } catch (e) {
    if (e.status !== 401) showMessage('report', 'Report: ' + e.message);
  }
});
