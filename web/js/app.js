// brokenray dashboard: compensation cards live from /api/v1/events, history plots (uPlot),
// reference, alarms, relay chain, cameras and links. ES modules, no build step; served by the binary.
// This module chooses the target and starts everything; the others each own one part of the page.
//
// Times are shown in UTC.

import { $, apiBase, clearMessage, el, fmtTime, parseTime, showMessage, state, toInput } from './util.js';
import { api } from './api.js';
import { buildCard, cards, loadCompensation, renderAge } from './cards.js';
import { runEvents } from './events.js';
import { loadHistory, renderPlots, scheduleRefresh, windowMs } from './history.js';
import { loadReferences, renderReferencePanel } from './reference.js';
import { renderTopology } from './chain.js';
import { loadLinks, loadOutputs, loadWebhooks } from './links.js';
import { renderCameraAges, startCameras } from './cameras.js';
import { startFleet } from './fleet.js';
import { startBudgets } from './budget.js';
import { startAcceptance } from './acceptance.js';

export function selectTarget(name, scroll) {
  state.selected = name;
  $('target-select').value = name;
  $('history-target').textContent = name;
  for (const [n, c] of cards) c.root.setAttribute('aria-current', String(n === name));
  state.history = null;
  state.references = [];
  renderReferencePanel();
  loadReferences(name).catch((e) => { if (e.status !== 401) showMessage('references', 'References: ' + e.message); });
  renderTopology();
  if (!$('reference-from').value) {
    const [from, to] = windowMs();
    $('reference-from').value = toInput(Math.floor(Math.max(from, to - 60000) / 1000) * 1000);
    $('reference-to').value = toInput(Math.floor(to / 1000) * 1000);
  }
  loadHistory();
  if (scroll) $('history').scrollIntoView({ behavior: 'smooth', block: 'start' });
}
$('target-select').addEventListener('change', () => selectTarget($('target-select').value, false));

async function loadTargets() {
  state.targets = await api(apiBase() + '/targets');
  const select = $('target-select');
  select.textContent = '';
  $('cards').textContent = '';
  cards.clear();
  for (const t of state.targets) {
    select.append(el('option', { value: t.name, text: `${t.name} from ${t.base}` }));
    const card = buildCard(t);
    cards.set(t.name, card);
    $('cards').append(card.root);
  }
  for (const t of state.targets) {
    if (t.time) state.newestMs = Math.max(state.newestMs, parseTime(t.time));
  }
}

// start

// A site's copy at a centre has no live stream, cameras, links or reference form: what the
// site uploaded is shown, read-only, its compensations asked again every few seconds.
function showSiteMode() {
  document.body.dataset.site = state.site || '';
  for (const node of document.querySelectorAll('.local-only')) node.hidden = Boolean(state.site);
  $('site-banner').hidden = !state.site;
  if (state.site) {
    $('site-name').textContent = state.site;
    $('live').dataset.state = 'copy';
    $('live').textContent = 'uploaded copy';
  }
}

let started = false;
let linksTimer = null;
let siteTimer = null;
export async function start() {
  clearMessage('start');
  showSiteMode();
  startFleet();
  try {
    await loadTargets();
    await Promise.all(state.targets.map((t) => loadCompensation(t.name)));
    if (!state.site) await Promise.all([loadLinks(), loadOutputs()]);
  } catch (e) {
    if (e.status !== 401) showMessage('start', (state.site ? `Site ${state.site}: ` : 'Cannot reach the service: ') + e.message);
    return;
  }
  const keep = state.targets.some((t) => t.name === state.selected);
  if (state.targets.length) selectTarget(keep ? state.selected : state.targets[0].name, false);
  scheduleRefresh();
  if (state.site) {
    if (siteTimer === null) {
      siteTimer = setInterval(() => {
        if (document.hidden) return;
        for (const t of state.targets) {
          loadCompensation(t.name).catch((e) => { if (e.status !== 401) showMessage('site', `Site ${state.site}: ` + e.message); });
        }
      }, 2000);
    }
    return;
  }
  runEvents();
  startCameras();
  startAcceptance();
  startBudgets((e) => { if (e.status !== 401) showMessage('budget', 'Budget: ' + e.message); });
  if (!started) {
    started = true;
    linksTimer = setInterval(() => {
      if (document.hidden) return;
      loadLinks().catch((e) => { if (e.status !== 401) showMessage('links', 'Links: ' + e.message); });
      loadWebhooks().catch((e) => { if (e.status !== 401) showMessage('webhooks', 'Webhooks: ' + e.message); });
      loadOutputs().catch((e) => { if (e.status !== 401) showMessage('outputs', 'Outputs: ' + e.message); });
    }, 2000);
    void linksTimer;
  }
}

function tick() {
  $('clock').textContent = fmtTime(Date.now()) + ' UTC';
  for (const name of cards.keys()) renderAge(name);
  renderCameraAges();
}
setInterval(tick, 500);
tick();

let resizeTimer = 0;
window.addEventListener('resize', () => {
  clearTimeout(resizeTimer);
  // Rebuilt rather than resized: the tick font follows the page's font size.
  resizeTimer = setTimeout(() => renderPlots(true), 150);
});

// The plots take their colours from the style sheet when built: rebuild on a theme change.
window.matchMedia('(prefers-color-scheme: dark)').addEventListener('change', () => renderPlots(true));

// Another site (or this service's own view) chosen: a fresh page, so no stream, timer or plot
// of the previous view lives on.
window.addEventListener('hashchange', () => location.reload());

start();
