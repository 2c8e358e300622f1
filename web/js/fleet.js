// The fleet panel, on a centre: every site with its last contact, backlog, targets and worst
// alarm, from /api/v1/sites; a site opens in the page's views (`#site=NAME`), answered from
// its uploaded copy. Hidden on a service that is no centre (only a centre's `/healthz` says
// `centre`). On any service, what `/healthz` reports wrong of the uploads or the disk budget
// is shown as a message, checked every ten seconds.

import { $, clearMessage, el, fmtAge, fmtTime, parseTime, showMessage, state } from './util.js';
import { api } from './api.js';

// A site not heard from for this long is marked late (its link or the site is down).
const LATE_CONTACT_S = 120;

function badge(value) {
  return el('span', { class: 'badge ' + value, text: value });
}

function siteRow(s) {
  const age = (Date.now() - parseTime(s.last_contact)) / 1000;
  const backlog = Object.entries(s.backlog || {})
    .map(([tier, rows]) => `${tier} ${rows}`).join(' · ') || '—';
  const targets = el('td', {});
  for (const t of s.targets || []) {
    targets.append(el('span', { class: 'site-target' }, t.name + ' ', badge(t.status)), ' ');
  }
  if (!(s.targets || []).length) targets.textContent = '—';
  for (const p of s.problems || []) targets.append(el('div', { class: 'site-problem', text: p }));
  const open = el('a', { href: '#site=' + encodeURIComponent(s.site), text: 'Open', 'data-open-site': s.site });
  if (state.site === s.site) open.setAttribute('aria-current', 'page');
  return el('tr', { 'data-site': s.site },
    el('th', { scope: 'row', text: s.site }),
    el('td', { class: age > LATE_CONTACT_S ? 'late' : '', title: fmtTime(parseTime(s.last_contact)) + ' UTC' },
      fmtAge(age) + ' ago'),
    el('td', {}, badge(s.alarm)),
    targets,
    el('td', { class: 'num', text: backlog }),
    el('td', {}, open));
}

async function loadSites() {
  const answer = await api('/api/v1/sites');
  $('fleet').hidden = false;
  const body = $('sites').tBodies[0];
  body.textContent = '';
  for (const s of answer.sites) body.append(siteRow(s));
  if (!answer.sites.length) {
    body.append(el('tr', { class: 'empty' }, el('td', { colspan: '6', text: 'No site has uploaded yet.' })));
  }
  document.body.dataset.sitesLoads = String(Number(document.body.dataset.sitesLoads || 0) + 1);
  clearMessage('fleet');
}

// `/healthz` (open, no token): whether this service is a centre, and what it reports wrong
// that the page must show (a stopped upload stream, rows the disk budget removed, samples that
// make no measurement group, a target filter that no longer fits its data).
async function health() {
  const response = await fetch('/healthz');
  const h = await response.json();
  for (const [key, text] of [
    ['upstream', h.upstream_problem],
    ['storage', h.storage_problem],
    ['grouping', h.grouping_problem],
    ['filter', h.filter_problem],
  ]) {
    if (text) showMessage('health-' + key, text);
    else clearMessage('health-' + key);
  }
  return h;
}

let healthTimer = null;
function watchHealth() {
  if (healthTimer !== null) return;
  healthTimer = setInterval(() => {
    if (!document.hidden) health().catch(() => {});
  }, 10000);
}

let timer = null;
export async function startFleet() {
  if (timer !== null) return;
  let centre = false;
  watchHealth();
  try {
    centre = (await health()).centre === true;
  } catch (e) {
    showMessage('fleet', 'Cannot ask the service whether it is a centre: ' + e.message);
    return;
  }
  if (!centre) return;
  const tick = () => {
    if (document.hidden) return;
    loadSites().catch((e) => { if (e.status !== 401) showMessage('fleet', 'Fleet: ' + e.message); });
  };
  tick();
  timer = setInterval(tick, 5000);
}
