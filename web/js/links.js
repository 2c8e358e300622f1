// The links table: status, rates, outliers, filter reset; failing webhooks; the outputs on the
// plant's buses.

import { $, clearMessage, el, fmtAge, fmtTime, parseTime, showMessage, state } from './util.js';
import { api } from './api.js';
import { operator } from './alarms.js';
import { renderTopology } from './chain.js';

function renderLinks() {
  const body = $('links').tBodies[0];
  body.textContent = '';
  const now = Date.now();
  for (const l of state.links) {
    const last = parseTime(l.last_time);
    const rate = l.rate_hz === null ? '—' : l.rate_hz.toFixed(1) + (l.expected_rate_hz ? ' / ' + l.expected_rate_hz.toFixed(0) : '');
    const share = l.n_samples ? ` (${(100 * l.n_outliers / l.n_samples).toFixed(1)} %)` : '';
    body.append(el('tr', { 'data-link': l.name },
      el('th', { scope: 'row', text: l.name }),
      el('td', { text: l.kind }),
      el('td', { text: l.model || '—' }),
      el('td', { class: 'num', text: rate }),
      el('td', { text: Number.isFinite(last) ? `${fmtTime(last)} (${fmtAge((now - last) / 1000)} ago)` : '—' }),
      el('td', { class: 'num', text: String(l.n_samples) }),
      el('td', { class: 'num', text: l.n_outliers + share }),
      el('td', { class: 'num', text: String(l.n_reinitializations) }),
      el('td', {}, el('span', { class: 'badge ' + l.status, text: l.status.replace('_', ' ') })),
      resetCell(l)));
  }
}

// A measured link that is stale or full of outliers can have its filter restarted (after a
// sample stamped far ahead, every correct one is refused as out of order). Two clicks: the
// first asks to confirm.
const OUTLIER_SHARE_FOR_RESET = 0.1;
let resetAsked = { link: null, until: 0 };
function resetCell(l) {
  const cell = el('td', {});
  if (l.last_reset) {
    cell.title = `Last reset ${fmtTime(parseTime(l.last_reset.at))}` + (l.last_reset.by ? ' by ' + l.last_reset.by : '') +
      (l.last_reset.note ? ': ' + l.last_reset.note : '');
  }
  const troubled = l.kind === 'measured' &&
    (l.status === 'stale' || (l.n_samples > 0 && l.n_outliers / l.n_samples >= OUTLIER_SHARE_FOR_RESET));
  if (!troubled) return cell;
  const confirming = resetAsked.link === l.name && Date.now() < resetAsked.until;
  const button = el('button', { type: 'button', class: confirming ? 'danger' : 'ghost', 'data-reset': l.name,
    text: confirming ? 'Confirm reset' : 'Reset filter',
    title: 'Restart this link\'s filter from its next sample' });
  button.addEventListener('click', async () => {
    if (!(resetAsked.link === l.name && Date.now() < resetAsked.until)) {
      resetAsked = { link: l.name, until: Date.now() + 10000 };
      renderLinks();
      return;
    }
    resetAsked = { link: null, until: 0 };
    button.disabled = true;
    try {
      const who = operator();
      await api('/api/v1/links/' + encodeURIComponent(l.name) + '/reset', {
        method: 'POST',
        json: Object.assign({ note: `from the dashboard: the link was ${l.status.replace('_', ' ')}` }, who ? { by: who } : {}),
      });
      clearMessage('reset');
      await loadLinks();
    } catch (err) {
      showMessage('reset', `Resetting ${l.name} was refused: ` + (err.status === 403 ? 'this token lacks the admin scope.' : err.message));
      button.disabled = false;
    }
  });
  cell.append(button);
  return cell;
}

// Webhooks that fail are said on the page: alarms may not be reaching people.
export async function loadWebhooks() {
  const hooks = await api('/api/v1/webhooks');
  const failing = hooks.filter((h) => h.failing || h.dropped > 0);
  if (failing.length) {
    showMessage('webhooks', 'Alarm notifications are failing: ' +
      failing.map((h) => `${h.host} (${h.last_error || h.dropped + ' dropped'})`).join('; '));
  } else {
    clearMessage('webhooks');
  }
}

export async function loadLinks() {
  state.links = await api('/api/v1/links');
  renderLinks();
  renderTopology();
  clearMessage('links');
}

// The outputs on the plant's buses (MQTT, Modbus, NMEA): each one's state and counters; the
// section shows only when the installation has outputs. One that is not connected, or that
// dropped alarm transitions, is said on the page as well.
export async function loadOutputs() {
  const outputs = await api('/api/v1/outputs');
  $('outputs-section').hidden = outputs.length === 0;
  const body = $('outputs').tBodies[0];
  body.textContent = '';
  for (const o of outputs) {
    const label = o.kind === 'modbus' ? (o.connected ? `listening, ${o.clients} client${o.clients === 1 ? '' : 's'}` : 'not listening')
      : (o.connected ? 'connected' : 'not connected');
    body.append(el('tr', { 'data-output': o.kind + ' ' + o.address },
      el('th', { scope: 'row', text: o.kind }),
      el('td', { text: o.address }),
      el('td', {}, el('span', { class: 'badge ' + (o.connected ? 'ok' : 'alarm'), 'data-f': 'output-state', text: label })),
      el('td', { class: 'num', text: String(o.sent) }),
      el('td', { class: 'num', text: String(o.queued) }),
      el('td', { class: 'num', text: String(o.dropped) }),
      el('td', { text: o.last_sent ? fmtTime(parseTime(o.last_sent)) : '—' }),
      el('td', { text: o.last_error ? `${fmtTime(parseTime(o.last_error_at))}: ${o.last_error}` : '—' })));
  }
  const troubled = outputs.filter((o) => !o.connected || o.dropped > 0);
  if (troubled.length) {
    showMessage('outputs', 'Outputs in trouble: ' +
      troubled.map((o) => `${o.kind} ${o.address} (${o.connected ? o.dropped + ' alarm transitions dropped' : o.last_error || 'not connected'})`).join('; '));
  } else {
    clearMessage('outputs');
  }
}
