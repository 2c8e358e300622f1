// Shared by every part of the dashboard: the page state, messages, time and number formats,
// element construction.

export const $ = (id) => document.getElementById(id);
export const AXES = ['x', 'y', 'z'];
export const TOKEN_KEY = 'brokenray.token';
export const ALARMS_SHOWN = 500;
export const LATE_WARN_S = 5; // a result older than this: the age turns amber
export const LATE_ALARM_S = 60; // and red

export const state = {
  targets: [],
  links: [],
  selected: null,
  comp: new Map(), // target -> {data, receivedAt (ms, performance clock)}
  newestMs: 0, // newest result time seen (ms since the epoch)
  range: { kind: 'last', seconds: 300 },
  zoomStack: [],
  selection: null, // {from, to} in ms
  alarms: [],
  references: [], // every reference version of the selected target, newest first
  show: { x: true, y: true, z: true, mag: true, raw: true, band: true },
  history: null, // {window: [from, to] ms, rot: data, tr: data, info}
  plots: { rot: null, tr: null },
  layouts: { rot: null, tr: null },
  historyAbort: null,
  refreshTimer: null,
  token: sessionStorage.getItem(TOKEN_KEY) || '',
  // On a centre, the site whose uploaded copy is shown (`#site=NAME`); null: this service's own.
  site: siteOfHash(),
};

// The site named by the page's address (`#site=ship-1`), or null.
function siteOfHash() {
  const m = /^#site=([a-z0-9_-]+)$/.exec(location.hash);
  return m ? m[1] : null;
}

// Where the per-target endpoints are: this service's own, or a site's copy at a centre.
export function apiBase() {
  return state.site ? '/api/v1/sites/' + encodeURIComponent(state.site) : '/api/v1';
}

// messages

const messages = new Map();
export function showMessage(key, text, kind) {
  let el = messages.get(key);
  if (!el) {
    el = document.createElement('div');
    const span = document.createElement('span');
    const close = document.createElement('button');
    close.type = 'button';
    close.className = 'ghost';
    close.textContent = 'Dismiss';
    close.addEventListener('click', () => clearMessage(key));
    el.append(span, close);
    $('messages').append(el);
    messages.set(key, el);
  }
  el.className = 'message ' + (kind || 'error');
  el.firstChild.textContent = text;
}
export function clearMessage(key) {
  const el = messages.get(key);
  if (el) {
    el.remove();
    messages.delete(key);
  }
}

// time and numbers

// RFC 3339 with up to nanoseconds -> ms since the epoch.
export function parseTime(text) {
  if (!text) return NaN;
  const m = /^(.*T\d\d:\d\d:\d\d)(\.\d+)?(Z|[+-]\d\d:\d\d)$/.exec(text);
  if (!m) return Date.parse(text);
  const frac = m[2] ? m[2].slice(0, 4) : '';
  return Date.parse(m[1] + frac + m[3]);
}
export const pad = (n, w = 2) => String(n).padStart(w, '0');
export function fmtTime(ms, withDate = true) {
  if (!Number.isFinite(ms)) return '—';
  const d = new Date(ms);
  const t = `${pad(d.getUTCHours())}:${pad(d.getUTCMinutes())}:${pad(d.getUTCSeconds())}`;
  if (!withDate) return t;
  return `${d.getUTCFullYear()}-${pad(d.getUTCMonth() + 1)}-${pad(d.getUTCDate())} ${t}`;
}
export function toInput(ms) {
  const d = new Date(ms);
  return `${d.getUTCFullYear()}-${pad(d.getUTCMonth() + 1)}-${pad(d.getUTCDate())}T` +
    `${pad(d.getUTCHours())}:${pad(d.getUTCMinutes())}:${pad(d.getUTCSeconds())}`;
}
export function fromInput(value) {
  if (!value) return NaN;
  return Date.parse(value.length === 16 ? value + ':00Z' : value + 'Z');
}
export const iso = (ms) => new Date(ms).toISOString();
export function fmtAge(s) {
  if (!Number.isFinite(s)) return '—';
  if (s < 0) s = 0;
  if (s < 10) return s.toFixed(1) + ' s';
  if (s < 120) return Math.round(s) + ' s';
  if (s < 7200) return Math.round(s / 60) + ' min';
  if (s < 172800) return (s / 3600).toFixed(1) + ' h';
  return (s / 86400).toFixed(1) + ' d';
}
export function fmtSpan(s) {
  if (s < 1) return (s * 1000).toFixed(0) + ' ms';
  if (s < 120) return s.toFixed(s < 10 ? 1 : 0) + ' s';
  if (s < 7200) return (s / 60).toFixed(1) + ' min';
  if (s < 172800) return (s / 3600).toFixed(1) + ' h';
  return (s / 86400).toFixed(1) + ' d';
}
export const fmt = (v, digits) => (v === null || v === undefined || !Number.isFinite(v) ? '—' : v.toFixed(digits));
export const norm3 = (v) => (v ? Math.hypot(v[0], v[1], v[2]) : NaN);
export function el(tag, attrs, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined) continue;
    if (k === 'class') e.className = v;
    else if (k === 'text') e.textContent = v;
    else e.setAttribute(k, v);
  }
  for (const c of children) if (c !== null && c !== undefined) e.append(c);
  return e;
}
