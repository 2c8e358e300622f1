// The reference panel: the current reference, its versions, and setting one from a window.

import { $, apiBase, el, fmtTime, fromInput, iso, parseTime, state } from './util.js';
import { api } from './api.js';
import { loadCompensation } from './cards.js';
import { loadHistory } from './history.js';
import { redrawMarks } from './alarms.js';

export function renderReferencePanel() {
  const entry = state.comp.get(state.selected);
  const box = $('reference-current');
  box.textContent = '';
  if (!entry || !entry.data.reference) {
    box.append(el('p', { class: 'no-reference', text: `No reference for ${state.selected || 'this target'} yet.` }));
    return;
  }
  const r = entry.data.reference;
  const w = r.window;
  box.append(el('p', {},
    el('b', { text: `Version ${r.version}` }), ` since ${fmtTime(parseTime(r.since))} UTC, `,
    w ? `mean of ${w.count} filtered results from ${fmtTime(parseTime(w.from))} to ${fmtTime(parseTime(w.to), false)}`
      : `a given pose (${r.origin})`,
    el('br'),
    `t ${r.t_mm.map((v) => v.toFixed(3)).join(', ')} mm · Euler ${r.euler_deg.map((v) => v.toFixed(5)).join(', ')} °`));
}

export async function loadReferences(target) {
  const answer = await api(apiBase() + '/targets/' + encodeURIComponent(target) + '/references');
  if (target !== state.selected) return;
  state.references = answer.references.slice().reverse();
  const body = $('references').tBodies[0];
  body.textContent = '';
  for (const r of state.references.slice(0, 20)) {
    const w = r.window;
    body.append(el('tr', {},
      el('td', { class: 'num', text: String(r.version) }),
      el('td', { text: fmtTime(parseTime(r.since)) }),
      el('td', { text: w ? `mean of ${w.count} from ${fmtTime(parseTime(w.from))} to ${fmtTime(parseTime(w.to), false)}` : r.origin })));
  }
  if (!state.references.length) {
    body.append(el('tr', { class: 'empty' }, el('td', { colspan: '3', text: 'None yet.' })));
  }
  redrawMarks();
}

$('reference-form').addEventListener('submit', async (e) => {
  e.preventDefault();
  const target = state.selected;
  const from = fromInput($('reference-from').value);
  const to = fromInput($('reference-to').value);
  const result = $('reference-result');
  if (!(from < to)) {
    result.textContent = 'The window needs a start before its end.';
    return;
  }
  $('reference-submit').disabled = true;
  result.textContent = 'Setting…';
  try {
    const r = await api('/api/v1/targets/' + encodeURIComponent(target) + '/reference', {
      method: 'POST',
      json: { from: iso(from), to: iso(to) },
    });
    result.textContent = `Reference version ${r.version} set for ${target}` +
      (r.window ? ` from ${r.window.count} results.` : '.');
    await loadCompensation(target);
    loadReferences(target).catch(() => {});
    loadHistory();
  } catch (err) {
    result.textContent = err.status === 403
      ? 'Refused: this token lacks the admin scope. ' + err.message
      : 'Refused: ' + err.message;
  } finally {
    $('reference-submit').disabled = false;
  }
});
