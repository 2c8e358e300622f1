// The Cameras panel: what each camera sees. Its newest frame (scaled to the panel; a click opens
// it full size) with what was found drawn over it: each detected point and its id, the point
// reprojected with the solved pose, and the residual between them magnified so that a
// hundredth of a pixel can be seen; each marker's found / not found state with the reason, and
// the frame's age.
//
// Frames are fetched with the page's token (as a blob, since an <img> cannot send one) only
// when the newest frame's time changed. A camera whose installation names its calibration
// report links it: the page is fetched with the token too and opened from a blob in a new tab
// (the tab is opened on the click itself, so no popup blocker holds it).

import { $, clearMessage, el, fmtAge, fmtTime, parseTime, showMessage } from './util.js';
import { api, openInTab } from './api.js';

const SVG = 'http://www.w3.org/2000/svg';
// A residual of 0.05 px is drawn this many screen pixels long.
const SCREEN_PX_PER_0_05_PX = 12;

const views = new Map();
let serverOffsetMs = 0;

function svg(tag, attrs, ...children) {
  const e = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k === 'text') e.textContent = v;
    else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c);
  return e;
}

function buildView(camera) {
  const img = el('img', { alt: `Newest frame of camera ${camera.name}`, width: camera.width_px, height: camera.height_px });
  const overlay = svg('svg', { class: 'overlay', viewBox: `0 0 ${camera.width_px} ${camera.height_px}`, 'aria-hidden': 'true' });
  const open = el('button', { type: 'button', class: 'frame', title: 'Open full size', 'aria-label': `Open camera ${camera.name}'s frame full size` },
    img, overlay);
  const view = {
    name: camera.name,
    width: camera.width_px,
    height: camera.height_px,
    root: el('article', { class: 'camera', 'data-camera': camera.name },
      el('div', { class: 'camera-head' },
        el('h3', { text: camera.name }),
        el('span', { class: 'muted small', 'data-f': 'sees', text: camera.markers.length ? 'sees ' + camera.markers.join(', ') : 'sees no marker' }),
        el('span', { class: 'grow' }),
        camera.calibration_report ? reportLink(camera) : null,
        el('span', { 'data-f': 'age', class: 'muted', text: 'no frame yet' })),
      el('p', { class: 'source-state small', 'data-f': 'source', hidden: true }),
      open,
      el('ul', { class: 'marker-states', 'data-f': 'markers' }),
      el('p', { class: 'muted small legend', text: `○ detected point and id · + reprojected · line: residual, magnified` })),
    img,
    overlay,
    time: null,
    timeMs: NaN,
    url: null,
    detections: null,
  };
  open.addEventListener('click', () => openFull(view));
  return view;
}

function reportLink(camera) {
  const a = el('a', { href: camera.calibration_report, 'data-f': 'report', class: 'small', target: '_blank', text: 'calibration report',
    title: `Camera ${camera.name}'s calibration report, as the installation names it` });
  a.addEventListener('click', (event) => {
    event.preventDefault();
    openReport(camera, window.open('', '_blank'));
  });
  return a;
}

async function openReport(camera, tab) {
  try {
    await openInTab(camera.calibration_report, tab);
    clearMessage('cameras');
  } catch (e) {
    if (e.status !== 401) showMessage('cameras', `Camera ${camera.name}'s calibration report: ${e.message}`);
  }
}

// The overlay of one frame, in image pixels (the viewBox is the image; pixel (u, v) covers
// [u, u+1) x [v, v+1) there, so a point at pixel-centre coordinates is drawn at u + 0.5).
function drawOverlay(target, view, screenPxPerImagePx) {
  target.textContent = '';
  const d = view.detections;
  if (!d) return;
  const magnify = SCREEN_PX_PER_0_05_PX / (0.05 * screenPxPerImagePx);
  const r = 6 / screenPxPerImagePx;
  const font = 12 / screenPxPerImagePx;
  const stroke = 1.5 / screenPxPerImagePx;
  for (const m of d.markers) {
    if (!m.found) continue;
    const group = svg('g', { class: 'marker', 'data-marker': m.marker });
    m.points_px.forEach(([u, v], i) => {
      const x = u + 0.5;
      const y = v + 0.5;
      group.append(svg('circle', { class: 'detected', cx: x, cy: y, r, 'stroke-width': stroke, 'data-id': m.ids[i] }));
      group.append(svg('text', { x: x + 1.4 * r, y: y - 1.4 * r, 'font-size': font, text: String(m.ids[i]) }));
      const p = m.reprojected_px && m.reprojected_px[i];
      if (p && Number.isFinite(p[0])) {
        const px = p[0] + 0.5;
        const py = p[1] + 0.5;
        group.append(svg('path', { class: 'reprojected', d: `M${px - r} ${py}H${px + r}M${px} ${py - r}V${py + r}`, 'stroke-width': stroke }));
        group.append(svg('line', { class: 'residual', x1: px, y1: py, x2: px + magnify * (u - p[0]), y2: py + magnify * (v - p[1]), 'stroke-width': 2 * stroke }));
      }
    });
    target.append(group);
  }
  target.dataset.magnification = magnify.toFixed(0);
}

function scaleOf(view) {
  const shown = view.img.getBoundingClientRect().width;
  return shown > 0 ? shown / view.width : 1;
}

// A camera the service takes frames from itself: its connection, counters and last error.
function renderSource(view, source) {
  const p = view.root.querySelector('[data-f="source"]');
  p.hidden = !source;
  if (!source) return;
  p.textContent = '';
  const ok = source.status === 'streaming';
  const counts = [
    `${source.frames_received} received`,
    `${source.frames_dropped} dropped`,
    `${source.incomplete_buffers} incomplete`,
    `${source.frames_refused_time} refused for their time`,
    `${source.reconnects} reconnects`,
  ];
  let clock = source.timestamp;
  if (source.ptp_status) clock += ` (PTP ${source.ptp_status})`;
  else if (source.clock_fit) clock += ` (${source.clock_fit.drift_ppm.toFixed(1)} ppm)`;
  p.append(
    el('span', { class: 'badge ' + (ok ? 'ok' : 'alarm'), 'data-f': 'source-status', text: `${source.address}: ${source.status}` }),
    el('span', { class: 'muted', text: ` ${clock} · ${counts.join(' · ')}` }));
  if (source.last_error) {
    p.append(el('span', { class: 'reason', 'data-f': 'source-error', text: ` last error ${fmtTime(parseTime(source.last_error_at))}: ${source.last_error}` }));
  }
}

function render(view, camera) {
  renderSource(view, camera.source);
  const list = view.root.querySelector('[data-f="markers"]');
  list.textContent = '';
  const frame = camera.frame;
  if (!frame) {
    view.root.dataset.state = 'none';
    return;
  }
  const missing = frame.markers.filter((m) => !m.found);
  view.root.dataset.state = missing.length ? 'not-found' : 'found';
  for (const m of frame.markers) {
    const state = m.found ? 'found' : 'not found';
    const detail = m.found ? `rms ${m.reprojection_rms_px.toFixed(3)} px` : m.reason;
    list.append(el('li', { 'data-marker': m.marker, 'data-found': String(m.found) },
      el('span', { class: 'badge ' + (m.found ? 'ok' : 'alarm'), text: `${m.marker}: ${state}` }),
      el('span', { class: m.found ? 'muted small' : 'reason small', text: ' ' + detail })));
  }
  drawOverlay(view.overlay, view, scaleOf(view));
}

export function renderCameraAges() {
  const now = Date.now() + serverOffsetMs;
  for (const view of views.values()) {
    if (!Number.isFinite(view.timeMs)) continue;
    const age = view.root.querySelector('[data-f="age"]');
    age.textContent = `${fmtTime(view.timeMs)} (${fmtAge((now - view.timeMs) / 1000)} ago)`;
  }
}

// The frame and its detections come from two requests; a newer frame may land between them.
// They are taken only when they are of the same frame (`X-Frame-Time` against the detections'
// time); otherwise asked again, at most three times.
async function refreshFrame(view, camera) {
  const name = encodeURIComponent(camera.name);
  let response = null;
  let detections = null;
  for (let attempt = 0; attempt < 3; attempt++) {
    [response, detections] = await Promise.all([
      api(`/api/v1/cameras/${name}/frame`, { raw: true }),
      api(`/api/v1/cameras/${name}/detections`),
    ]);
    if (parseTime(response.headers.get('X-Frame-Time')) === parseTime(detections.time)) break;
  }
  const url = URL.createObjectURL(await response.blob());
  await new Promise((resolve) => {
    view.img.onload = resolve;
    view.img.onerror = resolve;
    view.img.src = url;
  });
  if (view.url) URL.revokeObjectURL(view.url);
  view.url = url;
  view.detections = detections;
  view.time = camera.frame.time;
  view.timeMs = parseTime(detections.time);
}

export async function loadCameras() {
  const { cameras } = await api('/api/v1/cameras');
  const grid = $('cameras');
  if (views.size !== cameras.length || cameras.some((c) => !views.has(c.name))) {
    grid.textContent = '';
    views.clear();
    for (const c of cameras) {
      const view = buildView(c);
      views.set(c.name, view);
      grid.append(view.root);
    }
  }
  $('cameras-empty').hidden = cameras.length > 0;
  for (const c of cameras) {
    const view = views.get(c.name);
    if (c.frame) {
      // The age is judged on the server's clock: the offset from its answer.
      serverOffsetMs = parseTime(c.frame.time) + c.frame.age_s * 1000 - Date.now();
      if (c.frame.time !== view.time) await refreshFrame(view, c);
    }
    render(view, c);
  }
  renderCameraAges();
  clearMessage('cameras');
}

// Full size: the frame at one image pixel per screen pixel, scrollable, with its overlay.
function openFull(view) {
  if (!view.url) return;
  const dialog = $('camera-dialog');
  $('camera-dialog-title').textContent = `Camera ${view.name}, ${fmtTime(view.timeMs)} UTC`;
  const holder = $('camera-dialog-frame');
  holder.textContent = '';
  const img = el('img', { src: view.url, width: view.width, height: view.height, alt: `Frame of camera ${view.name}` });
  const overlay = svg('svg', { class: 'overlay', viewBox: `0 0 ${view.width} ${view.height}`, width: view.width, height: view.height });
  drawOverlay(overlay, view, 1);
  holder.append(el('div', { class: 'frame full' }, img, overlay));
  dialog.showModal();
}

let timer = null;
export function startCameras() {
  const tick = () => {
    if (document.hidden) return;
    loadCameras().catch((e) => { if (e.status !== 401) showMessage('cameras', 'Cameras: ' + e.message); });
  };
  tick();
  if (timer === null) timer = setInterval(tick, 1000);
}

// The overlay's marks keep their screen size when the panel is resized.
window.addEventListener('resize', () => {
  for (const view of views.values()) drawOverlay(view.overlay, view, scaleOf(view));
});
