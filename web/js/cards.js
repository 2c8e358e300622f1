// The compensation cards: one per target, updated live.

import { $, AXES, LATE_ALARM_S, LATE_WARN_S, apiBase, el, fmt, fmtAge, fmtTime, norm3, parseTime, state } from './util.js';
import { api } from './api.js';
import { renderReferencePanel } from './reference.js';
import { selectTarget } from './app.js';

export const cards = new Map(); // target -> {root, fields}

function valueRow(label, key, digits, withMag) {
  const tr = el('tr', {}, el('th', { scope: 'row', text: label }));
  for (const a of AXES) tr.append(el('td', { 'data-f': key + '-' + a }));
  tr.append(el('td', withMag ? { class: 'big', 'data-f': key + '-mag' } : {}));
  return tr;
}
function sigmaRow(key) {
  const tr = el('tr', { class: 'sigma' }, el('th', { scope: 'row', class: 'sigma', text: '± 1σ' }));
  for (const a of AXES) tr.append(el('td', { class: 'sigma', 'data-f': key + '-' + a }));
  tr.append(el('td'));
  return tr;
}

export function buildCard(target) {
  const name = target.name;
  const plot = el('button', { type: 'button', text: 'Show history' });
  plot.addEventListener('click', () => selectTarget(name, true));
  const head = el('div', { class: 'card-head' },
    el('h3', {}, name + ' ', el('span', { class: 'muted small', text: 'from ' + target.base })),
    el('span', { class: 'badge', 'data-f': 'status', title: 'Status of the result' }),
    el('span', { class: 'badge', 'data-f': 'alarm', title: 'Alarm level' }),
    plot);
  const table = el('table', { class: 'values' },
    el('thead', {}, el('tr', {}, el('th'), el('th', { scope: 'col', text: 'x' }),
      el('th', { scope: 'col', text: 'y' }), el('th', { scope: 'col', text: 'z' }),
      el('th', { scope: 'col', text: 'magnitude' }))),
    el('tbody', {},
      valueRow('Deformation rotation (″)', 'def-r', 1, true),
      sigmaRow('def-sr'),
      valueRow('Deformation translation (mm)', 'def-t', 3, true),
      sigmaRow('def-st'),
      (() => { const r = valueRow('Pose translation (mm)', 'pose-t', 3, false); r.className = 'sep'; return r; })(),
      valueRow('Pose Euler angles (°)', 'pose-e', 5, false),
      (() => { const r = valueRow('σ rotation (″)', 'pose-sr', 1, false); r.className = 'sigma'; return r; })(),
      (() => { const r = valueRow('σ translation (mm)', 'pose-st', 3, false); r.className = 'sigma'; return r; })()));
  const noRef = el('p', { class: 'no-reference', 'data-f': 'no-ref', hidden: '',
    text: 'No reference set: the deformation is measured against one. Set it in the Reference panel.' });
  const foot = el('div', { class: 'card-foot' },
    el('span', {}, 'Result ', el('b', { 'data-f': 'time' })),
    el('span', {}, 'Age ', el('b', { 'data-f': 'age' })),
    el('span', {}, 'Reference ', el('b', { 'data-f': 'ref' })),
    el('span', {}, 'Thresholds ', el('b', { 'data-f': 'thresholds' })));
  // A site's uploaded copy has no live filters to split: no budget there.
  const budget = el('figure', { class: 'budget', 'data-f': 'budget', hidden: state.site ? '' : null });
  const root = el('article', { class: 'card', 'data-target': name, 'aria-label': 'Target ' + name },
    head, table, noRef, foot, budget);
  const fields = {};
  for (const f of root.querySelectorAll('[data-f]')) fields[f.dataset.f] = f;
  const a = target.alarms || {};
  const level = (name, r, t) => {
    const parts = [];
    if (Number.isFinite(r)) parts.push(`${fmt(r, 0)}″`);
    if (Number.isFinite(t)) parts.push(`${fmt(t, 2)} mm`);
    return parts.length ? `${name} ${parts.join(' / ')}` : '';
  };
  fields.thresholds.textContent = [
    level('warn', a.warn_rotation_arcsec, a.warn_translation_mm),
    level('alarm', a.alarm_rotation_arcsec, a.alarm_translation_mm),
  ].filter((x) => x).join(', ') || 'none';
  return { root, fields, target };
}

function setBadge(node, value) {
  node.textContent = value;
  node.className = 'badge ' + value;
}

function levelClass(value, warn, alarm) {
  if (Number.isFinite(alarm) && value >= alarm) return 'big over-alarm';
  if (Number.isFinite(warn) && value >= warn) return 'big over-warn';
  return 'big';
}

function renderCard(name) {
  const card = cards.get(name);
  const entry = state.comp.get(name);
  if (!card || !entry) return;
  const c = entry.data;
  const f = card.fields;
  setBadge(f.status, c.status);
  setBadge(f.alarm, c.alarm);
  card.root.dataset.alarm = c.alarm;
  card.root.dataset.time = c.time || '';
  const put = (key, values, digits) => {
    AXES.forEach((a, i) => { f[key + '-' + a].textContent = values ? fmt(values[i], digits) : '—'; });
  };
  const d = c.deformation;
  const thresholds = card.target.alarms || {};
  put('def-r', d && d.rotation_arcsec, 1);
  put('def-t', d && d.translation_mm, 3);
  put('def-sr', d && d.sigma.rotation_arcsec, 1);
  put('def-st', d && d.sigma.translation_mm, 3);
  const rmag = d ? norm3(d.rotation_arcsec) : NaN;
  const tmag = d ? norm3(d.translation_mm) : NaN;
  f['def-r-mag'].textContent = fmt(rmag, 1);
  f['def-t-mag'].textContent = fmt(tmag, 3);
  f['def-r-mag'].className = levelClass(rmag, thresholds.warn_rotation_arcsec, thresholds.alarm_rotation_arcsec);
  f['def-t-mag'].className = levelClass(tmag, thresholds.warn_translation_mm, thresholds.alarm_translation_mm);
  put('pose-t', c.pose && c.pose.t_mm, 3);
  put('pose-e', c.pose && c.pose.euler_deg, 5);
  put('pose-sr', c.sigma && c.sigma.rotation_arcsec, 1);
  put('pose-st', c.sigma && c.sigma.translation_mm, 3);
  f['no-ref'].hidden = !!c.reference;
  f.time.textContent = c.time ? fmtTime(parseTime(c.time)) : 'none yet';
  f.ref.textContent = c.reference
    ? `v${c.reference.version} since ${fmtTime(parseTime(c.reference.since))}`
    : 'none';
  f.ref.dataset.version = c.reference ? String(c.reference.version) : '0';
  renderAge(name);
  if (name === state.selected) renderReferencePanel();
}

export function renderAge(name) {
  const card = cards.get(name);
  const entry = state.comp.get(name);
  if (!card || !entry) return;
  const c = entry.data;
  // The service works in measurement time: when every link stops, no new result says so.
  // The age keeps counting here, and turns amber, then red, as results stop arriving.
  const age = c.age_s + (performance.now() - entry.receivedAt) / 1000;
  card.fields.age.textContent = c.time ? fmtAge(age) : '—';
  card.fields.age.className = !c.time ? '' : age > LATE_ALARM_S ? 'over-alarm' : age > LATE_WARN_S ? 'over-warn' : '';
}

export function acceptCompensation(c) {
  state.comp.set(c.target, { data: c, receivedAt: performance.now() });
  const t = parseTime(c.time);
  if (Number.isFinite(t) && t > state.newestMs) state.newestMs = t;
  scheduleCard(c.target);
}

const pendingCards = new Set();
let cardFrame = 0;
function scheduleCard(name) {
  pendingCards.add(name);
  if (cardFrame) return;
  cardFrame = requestAnimationFrame(() => {
    cardFrame = 0;
    for (const n of pendingCards) renderCard(n);
    pendingCards.clear();
  });
}

export async function loadCompensation(name) {
  const c = await api(apiBase() + '/targets/' + encodeURIComponent(name) + '/compensation');
  acceptCompensation(c);
}
