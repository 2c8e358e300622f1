// The alarm table: transitions, acknowledgement, and marks on the plots.

import { $, ALARMS_SHOWN, apiBase, clearMessage, el, fmtTime, parseTime, showMessage, state } from './util.js';
import { api } from './api.js';
import { loadCompensation } from './cards.js';
import { windowQuery } from './history.js';

// Who acts, remembered on this computer for the next acknowledgement or reset.
const OPERATOR_KEY = 'brokenray.operator';
export const operator = () => { try { return localStorage.getItem(OPERATOR_KEY) || ''; } catch (_) { return ''; } };
const rememberOperator = (name) => { try { localStorage.setItem(OPERATOR_KEY, name); } catch (_) { /* private mode */ } };

// Acknowledgements being written, by alarm id, with what was typed: the table is drawn again
// on every refresh and new transition, and an open form must survive that.
const drafts = new Map();

// The acknowledgement form of alarm `a` in `cell`, from its draft (a new one: the remembered
// operator, no note). Returns its first field.
function ackForm(a, cell) {
  if (!drafts.has(a.id)) drafts.set(a.id, { by: operator(), note: '' });
  const draft = drafts.get(a.id);
  const by = el('input', { type: 'text', name: 'by', placeholder: 'your name', 'aria-label': 'Acknowledged by', required: '', value: draft.by });
  const note = el('input', { type: 'text', name: 'note', placeholder: 'note (optional)', 'aria-label': 'Note', value: draft.note });
  by.addEventListener('input', () => { draft.by = by.value; });
  note.addEventListener('input', () => { draft.note = note.value; });
  const save = el('button', { type: 'submit', text: 'Save' });
  const said = el('span', { class: 'muted small', role: 'status' });
  const form = el('form', { class: 'ack-form' }, by, note, save, said);
  form.addEventListener('submit', async (e) => {
    e.preventDefault();
    if (!by.value.trim()) { said.textContent = 'Say who acknowledges.'; return; }
    save.disabled = true;
    try {
      const done = await api('/api/v1/alarms/' + a.id + '/ack', {
        method: 'POST',
        json: note.value.trim() ? { by: by.value.trim(), note: note.value.trim() } : { by: by.value.trim() },
      });
      rememberOperator(by.value.trim());
      drafts.delete(a.id);
      const i = state.alarms.findIndex((x) => x.id === a.id);
      if (i >= 0) state.alarms[i] = done;
      renderAlarms();
    } catch (err) {
      said.textContent = err.status === 403 ? 'Refused: this token lacks the admin scope.' : 'Refused: ' + err.message;
      save.disabled = false;
    }
  });
  cell.textContent = '';
  cell.append(form);
  return by;
}

// The acknowledgement cell: who and when once acknowledged; a button on a raised level, or
// the form being written.
function ackCell(a) {
  const cell = el('td', { class: 'ack' });
  if (a.acknowledged_by) {
    drafts.delete(a.id);
    cell.append(el('span', { text: a.acknowledged_by }),
      el('div', { class: 'muted small', text: fmtTime(parseTime(a.acknowledged_at)) }));
    if (a.note) cell.append(el('div', { class: 'muted small', text: a.note }));
    return cell;
  }
  // A site's copy at a centre is read-only: the site's operators acknowledge its alarms.
  if (a.to === 'none' || a.id === undefined || state.site) return cell;
  if (drafts.has(a.id)) {
    ackForm(a, cell);
    return cell;
  }
  const button = el('button', { type: 'button', class: 'ghost', 'data-ack': String(a.id), text: 'Acknowledge' });
  button.addEventListener('click', () => ackForm(a, cell).focus());
  cell.append(button);
  return cell;
}

function alarmRow(a) {
  return el('tr', { 'data-alarm': a.id === undefined ? '' : String(a.id) },
    el('td', { text: fmtTime(parseTime(a.time)) }),
    el('td', { text: a.target }),
    el('td', { text: a.kind }),
    el('td', {}, el('span', { class: 'badge ' + a.from, text: a.from }), ' → ', el('span', { class: 'badge ' + a.to, text: a.to })),
    el('td', { class: 'num', text: Number.isFinite(a.value) ? a.value.toFixed(1) + (a.unit && a.unit !== 'none' ? ' ' + a.unit.replace(/_per_/g, '/') : '') : '' }),
    el('td', { class: 'message', text: a.message }),
    ackCell(a));
}

function renderAlarms() {
  const body = $('alarms').tBodies[0];
  // The field being typed in keeps the focus and the caret across the redraw.
  const active = document.activeElement;
  const row = active && body.contains(active) ? active.closest('tr[data-alarm]') : null;
  const focused = row && active.name
    ? { alarm: row.dataset.alarm, name: active.name, start: active.selectionStart, end: active.selectionEnd }
    : null;
  body.textContent = '';
  if (!state.alarms.length) {
    body.append(el('tr', { class: 'empty' }, el('td', { colspan: '7', text: 'No alarm transitions in the shown range.' })));
    return;
  }
  for (const a of state.alarms) body.append(alarmRow(a));
  const again = focused && body.querySelector(`tr[data-alarm="${focused.alarm}"] input[name="${focused.name}"]`);
  if (again) {
    again.focus();
    again.setSelectionRange(focused.start, focused.end);
  }
}

export async function loadAlarms(win) {
  const answer = await api(`${apiBase()}/alarms?${windowQuery(win)}&limit=${ALARMS_SHOWN}&order=desc`);
  state.alarms = answer.alarms;
  renderAlarms();
  redrawMarks();
}

export function redrawMarks() {
  for (const p of Object.values(state.plots)) if (p) p.redraw(false, false);
}

// An acknowledgement given elsewhere (another dashboard, the API): the transition's row says
// who and when.
export function acceptAcknowledgement(a) {
  const i = state.alarms.findIndex((x) => x.id === a.id);
  if (i < 0) return;
  state.alarms[i] = a;
  renderAlarms();
}

export function acceptAlarm(a) {
  // A transition can change the target's status (a stale link) without a new result.
  loadCompensation(a.target).catch(() => {});
  if (state.range.kind === 'last') {
    state.alarms.unshift(a);
    state.alarms.length = Math.min(state.alarms.length, ALARMS_SHOWN);
    renderAlarms();
    redrawMarks();
  }
  if (a.to === 'alarm') showMessage('alarm-' + a.target, `${fmtTime(parseTime(a.time))}: ${a.target}: ${a.message}`, 'error');
  else if (a.to === 'none') clearMessage('alarm-' + a.target);
}
