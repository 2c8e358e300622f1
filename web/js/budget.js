// The uncertainty budget beside each target: how much of each axis' variance of the newest
// filtered G_from_B comes from each contributor (a link's noise, a camera's intrinsics, a
// station's calibration), the largest first, so the operator sees what to calibrate better.
// Read from GET /targets/{name}/budget every few seconds; not for a site's uploaded copy.

import { apiBase, el, fmt, state } from './util.js';
import { api } from './api.js';
import { cards } from './cards.js';

const AXIS_KEYS = [['rotation', 0, 'rx'], ['rotation', 1, 'ry'], ['rotation', 2, 'rz'],
  ['translation', 0, 'tx'], ['translation', 1, 'ty'], ['translation', 2, 'tz']];
const KIND_LABEL = { noise: 'noise', intrinsics: 'camera intrinsics', calibration: 'calibration' };
const REFRESH_MS = 5000;

function render(card, b) {
  const figure = card.fields.budget;
  // The same result: nothing to draw again (and nothing on the page moves).
  if (figure.dataset.time === b.time) return;
  figure.textContent = '';
  figure.append(el('figcaption', {},
    'Uncertainty budget ',
    el('span', { class: 'muted small', text: 'share of each axis’ variance; σ random '
      + `${fmt(b.sigma_random.rotation[2], 1)}″, systematic ${fmt(b.sigma_systematic.rotation[2], 1)}″ about z` })));
  const head = el('tr', {}, el('th', { scope: 'col', text: 'contributor' }));
  for (const [, , label] of AXIS_KEYS) head.append(el('th', { scope: 'col', text: label }));
  const body = el('tbody');
  for (const c of b.contributions) {
    const row = el('tr', { 'data-kind': c.kind, 'data-name': c.name, 'data-part': c.part },
      el('th', { scope: 'row' }, c.name + ' ', el('span', { class: 'muted small', text: KIND_LABEL[c.kind] || c.kind })));
    for (const [axes, i, label] of AXIS_KEYS) {
      const share = c.share[axes][i];
      const sigma = c.sigma[axes][i];
      const unit = axes === 'rotation' ? '″' : ' mm';
      // Set through the CSSOM: the page's content policy refuses style attributes.
      const bar = el('span', { class: 'bar ' + c.part });
      bar.style.width = `${Math.round(100 * share)}%`;
      row.append(el('td', { class: 'share', title: `${label}: σ ${fmt(sigma, axes === 'rotation' ? 2 : 4)}${unit}, ${fmt(100 * share, 1)} % of the variance` },
        bar, el('span', { class: 'pct', text: fmt(100 * share, 0) })));
    }
    body.append(row);
  }
  figure.append(el('table', { class: 'budget-table' }, el('thead', {}, head), body));
  figure.dataset.time = b.time;
}

export async function loadBudget(name) {
  const card = cards.get(name);
  if (!card) return;
  try {
    const b = await api(apiBase() + '/targets/' + encodeURIComponent(name) + '/budget');
    render(card, b);
  } catch (e) {
    if (e.status === 404) {
      card.fields.budget.textContent = '';
      card.fields.budget.append(el('figcaption', { text: 'Uncertainty budget: no result yet' }));
    } else {
      throw e;
    }
  }
}

let timer = null;
export function startBudgets(onError) {
  if (state.site) return;
  const all = () => {
    if (document.hidden) return;
    for (const name of cards.keys()) {
      // A target without a result has no budget yet.
      const c = state.comp.get(name);
      if (c && c.data.time) loadBudget(name).catch(onError);
    }
  };
  all();
  if (timer === null) timer = setInterval(all, REFRESH_MS);
}
