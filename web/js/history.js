// History plots (uPlot): filtered and raw buckets of the selected target over the chosen range,
// thresholds, alarm and reference marks, zoom, selection and CSV download.

import { $, apiBase, AXES, clearMessage, el, fmtSpan, fmtTime, fromInput, iso, pad, parseTime, showMessage, state, toInput } from './util.js';
import { api, openInTab } from './api.js';
import { loadAlarms } from './alarms.js';

// `from=..&to=..` of a window (ms).
export const windowQuery = (win) => `from=${encodeURIComponent(iso(win[0]))}&to=${encodeURIComponent(iso(win[1]))}`;

// A history request of the selected target over `win`, one bucket a pixel of plot width.
function historyUrl(target, source, win, extra) {
  const maxPoints = Math.min(2000, Math.round(plotWidth()));
  return apiBase() + '/targets/' + encodeURIComponent(target) + `/history?source=${source}&` +
    `${windowQuery(win)}&max_points=${maxPoints}` + (extra ? '&' + extra : '');
}

// The page's colours and font size, read from the style sheet when the plots are built (they
// are rebuilt when the theme or the size changes), not at every draw.
let palette = null;
function readPalette() {
  const v = (name) => getComputedStyle(document.documentElement).getPropertyValue(name).trim();
  palette = {
    x: v('--x'), y: v('--y'), z: v('--z'), mag: v('--mag'), ref: v('--ref'),
    ok: v('--ok'), warn: v('--warn'), alarm: v('--alarm'), muted: v('--muted'), grid: v('--grid'),
    fontPx: parseFloat(getComputedStyle(document.documentElement).fontSize),
  };
}

export function windowMs() {
  if (state.range.kind === 'abs') return [state.range.from, state.range.to];
  // A site's copy ends where its uploads end (a site cut off for days shows its last data).
  const end = state.site && state.newestMs ? state.newestMs : Math.max(Date.now(), state.newestMs);
  return [end - state.range.seconds * 1000, end];
}

function plotWidth() {
  return Math.max(300, $('plot-rot').clientWidth || $('history').clientWidth - 40);
}
function plotHeight() {
  return Math.round(Math.min(460, Math.max(220, window.innerHeight * 0.27)));
}

// Joins the filtered and raw answers on bucket start (equal windows give equal buckets; a
// bucket may be empty in one of them).
function merge(filtered, raw) {
  const index = new Map();
  const times = [];
  for (const t of filtered.time.concat(raw.time)) {
    if (!index.has(t)) {
      index.set(t, 0);
      times.push(t);
    }
  }
  const secs = times.map((t) => parseTime(t) / 1000);
  const order = secs.map((_, i) => i).sort((a, b) => secs[a] - secs[b]);
  order.forEach((k, i) => index.set(times[k], i));
  const n = times.length;
  const pick = (answer, component, which) => {
    const out = new Array(n).fill(null);
    const s = answer.series[component];
    if (!s) return out;
    answer.time.forEach((t, i) => { out[index.get(t)] = s[which][i]; });
    return out;
  };
  const x = order.map((k) => secs[k]);
  const build = (prefix, unit) => {
    const d = { x };
    for (const a of AXES) {
      const c = `def_${prefix}${a}_${unit}`;
      d['f' + a] = pick(filtered, c, 'mean');
      d['lo' + a] = pick(filtered, c, 'min');
      d['hi' + a] = pick(filtered, c, 'max');
      d['r' + a] = pick(raw, c, 'mean');
    }
    d.mag = x.map((_, i) => {
      const v = [d.fx[i], d.fy[i], d.fz[i]];
      return v.some((q) => q === null) ? null : Math.hypot(v[0], v[1], v[2]);
    });
    d.count = n;
    d.defined = d.fx.some((v) => v !== null) || d.rx.some((v) => v !== null);
    return d;
  };
  return { rot: build('r', 'arcsec'), tr: build('t', 'mm') };
}

function thresholdsOf(kind) {
  const t = state.targets.find((q) => q.name === state.selected);
  const a = (t && t.alarms) || {};
  return kind === 'rot'
    ? [{ v: a.warn_rotation_arcsec, label: 'warn', color: palette.warn },
      { v: a.alarm_rotation_arcsec, label: 'alarm', color: palette.alarm }]
    : [{ v: a.warn_translation_mm, label: 'warn', color: palette.warn },
      { v: a.alarm_translation_mm, label: 'alarm', color: palette.alarm }];
}

// Warn and alarm lines of the magnitude; a threshold above the plot is named at its top edge.
function drawThresholds(kind) {
  return (u) => {
    const ctx = u.ctx;
    const { left, top, width, height } = u.bbox;
    const [ymin, ymax] = [u.scales.y.min, u.scales.y.max];
    ctx.save();
    const fontPx = palette.fontPx * 0.75;
    ctx.font = `${Math.round(fontPx * devicePixelRatio)}px system-ui, sans-serif`;
    ctx.textAlign = 'left';
    let above = [];
    for (const t of thresholdsOf(kind)) {
      if (!Number.isFinite(t.v)) continue;
      if (t.v > ymax) {
        above.push(`${t.label} ${t.v}`);
        continue;
      }
      if (t.v < ymin) continue;
      const y = Math.round(u.valToPos(t.v, 'y', true)) + 0.5;
      ctx.strokeStyle = t.color;
      ctx.lineWidth = 1.5 * devicePixelRatio;
      ctx.setLineDash([8 * devicePixelRatio, 5 * devicePixelRatio]);
      ctx.beginPath();
      ctx.moveTo(left, y);
      ctx.lineTo(left + width, y);
      ctx.stroke();
      ctx.fillStyle = t.color;
      ctx.fillText(`${t.label} ${t.v}`, left + 6 * devicePixelRatio, y - 4 * devicePixelRatio);
    }
    drawMarkers(u, fontPx);
    if (above.length) {
      ctx.fillStyle = palette.muted;
      ctx.fillText(`${above.join(', ')} ↑ above`, left + 6 * devicePixelRatio, top + (fontPx + 4) * devicePixelRatio);
    }
    ctx.restore();
    void height;
  };
}

// Vertical marks: alarm transitions (coloured by the level entered) and reference changes.
function drawMarkers(u, fontPx) {
  const ctx = u.ctx;
  const { left, top, width, height } = u.bbox;
  const [xmin, xmax] = [u.scales.x.min, u.scales.x.max];
  const mark = (ms, colour, dash, label) => {
    const x = ms / 1000;
    if (!(x >= xmin && x <= xmax)) return;
    const px = Math.round(u.valToPos(x, 'x', true)) + 0.5;
    ctx.strokeStyle = colour;
    ctx.lineWidth = devicePixelRatio;
    ctx.setLineDash(dash.map((d) => d * devicePixelRatio));
    ctx.beginPath();
    ctx.moveTo(px, top);
    ctx.lineTo(px, top + height);
    ctx.stroke();
    if (label) {
      ctx.fillStyle = colour;
      ctx.fillText(label, Math.min(px + 4 * devicePixelRatio, left + width - 40 * devicePixelRatio),
        top + height - 6 * devicePixelRatio);
    }
  };
  const levelColour = { alarm: palette.alarm, warn: palette.warn, none: palette.ok };
  for (const a of state.alarms) {
    if (a.target === state.selected) mark(parseTime(a.time), levelColour[a.to] || palette.muted, [2, 3], '');
  }
  for (const r of state.references) mark(parseTime(r.since), palette.ref, [], `ref v${r.version}`);
  void fontPx;
}

// The uPlot series and data columns the toggles ask for.
function layout(d, kind) {
  const colors = { x: palette.x, y: palette.y, z: palette.z };
  const unit = kind === 'rot' ? '″' : ' mm';
  const digits = kind === 'rot' ? 1 : 3;
  const series = [{}];
  const data = [d.x];
  const bands = [];
  const keys = [];
  const value = (u, v) => (v === null || v === undefined ? '—' : v.toFixed(digits) + unit);
  for (const a of AXES) {
    if (!state.show[a]) continue;
    series.push({ label: a + ' filtered', stroke: colors[a], width: 1.8, value, points: { show: false } });
    data.push(d['f' + a]);
    keys.push('f' + a);
  }
  if (state.show.mag) {
    series.push({ label: 'magnitude', stroke: palette.mag, width: 1.5, dash: [4, 3], value, points: { show: false } });
    data.push(d.mag);
    keys.push('mag');
  }
  if (state.show.raw) {
    for (const a of AXES) {
      if (!state.show[a]) continue;
      series.push({ label: a + ' raw', stroke: colors[a] + '80', width: 0.8, value, points: { show: false } });
      data.push(d['r' + a]);
      keys.push('r' + a);
    }
  }
  if (state.show.band) {
    for (const a of AXES) {
      if (!state.show[a]) continue;
      series.push({ label: a + ' max', stroke: 'transparent', width: 0, value, points: { show: false } });
      data.push(d['hi' + a]);
      keys.push('hi' + a);
      series.push({ label: a + ' min', stroke: 'transparent', width: 0, value, points: { show: false } });
      data.push(d['lo' + a]);
      keys.push('lo' + a);
      bands.push({ series: [series.length - 2, series.length - 1], fill: colors[a] + '2e' });
    }
  }
  return { series, data, bands, keys, digits, unit };
}

function makePlot(kind, lay) {
  const container = $(kind === 'rot' ? 'plot-rot' : 'plot-tr');
  const old = state.plots[kind];
  if (old) old.destroy();
  container.textContent = '';
  state.layouts[kind] = lay;
  // Tick labels follow the page's font size (larger on a control-room screen).
  const fontPx = Math.round(palette.fontPx * 0.8);
  const axis = {
    stroke: palette.muted,
    grid: { stroke: palette.grid },
    ticks: { stroke: palette.grid },
    font: `${fontPx}px system-ui, sans-serif`,
  };
  const opts = {
    width: plotWidth(),
    height: plotHeight(),
    tzDate: (ts) => uPlot.tzDate(new Date(ts * 1000), 'Etc/UTC'),
    legend: { show: false },
    cursor: {
      drag: { x: true, y: false, setScale: false },
      sync: { key: 'brokenray-history', setSeries: false },
      bind: {
        dblclick: () => () => { zoomOut(); return null; },
      },
    },
    scales: {
      x: { time: true, range: () => { const [a, b] = state.history ? state.history.window : windowMs(); return [a / 1000, b / 1000]; } },
      y: {
        range: (u, min, max) => {
          if (min === null || max === null || !Number.isFinite(min)) return [-1, 1];
          if (min === max) return [min - 1, max + 1];
          const pad = (max - min) * 0.08;
          return [min - pad, max + pad];
        },
      },
    },
    axes: [
      Object.assign({}, axis, { values: timeTicks, space: fontPx * 6, size: fontPx * 4.2 }),
      Object.assign({}, axis, { size: fontPx * 5.5 }),
    ],
    series: lay.series,
    bands: lay.bands,
    hooks: {
      draw: [drawThresholds(kind)],
      setSelect: [(u) => onSelect(u, kind)],
      setCursor: [(u) => readout(u, kind, state.layouts[kind])],
    },
  };
  const plot = new uPlot(opts, lay.data, container);
  plot.brokenrayKeys = lay.keys.join();
  state.plots[kind] = plot;
  return plot;
}

// Tick labels in UTC, 24 h: seconds for short spans, the date where the day changes.
function timeTicks(u, splits, axisIdx, space, incr) {
  let lastDay = '';
  return splits.map((s) => {
    const d = new Date(s * 1000);
    const day = `${pad(d.getUTCMonth() + 1)}-${pad(d.getUTCDate())}`;
    const hm = `${pad(d.getUTCHours())}:${pad(d.getUTCMinutes())}`;
    const text = incr < 60 ? `${hm}:${pad(d.getUTCSeconds())}` : incr < 86400 ? hm : day;
    const showDay = incr < 86400 && day !== lastDay;
    lastDay = day;
    return showDay ? `${text}\n${day}` : text;
  });
}

function readout(u, kind, lay) {
  const out = $(kind === 'rot' ? 'readout-rot' : 'readout-tr');
  const i = u.cursor.idx;
  if (i === null || i === undefined) {
    out.textContent = '';
    return;
  }
  const parts = [fmtTime(u.data[0][i] * 1000)];
  lay.keys.forEach((k, s) => {
    if (!/^(f[xyz]|mag)$/.test(k)) return;
    const v = u.data[s + 1][i];
    parts.push(`${k === 'mag' ? '|·|' : k.slice(1)} ${v === null ? '—' : v.toFixed(lay.digits)}`);
  });
  out.textContent = parts.join('  ');
}

function onSelect(u, kind) {
  if (u.select.width < 3) return;
  const from = u.posToVal(u.select.left, 'x') * 1000;
  const to = u.posToVal(u.select.left + u.select.width, 'x') * 1000;
  state.selection = { from, to };
  const other = state.plots[kind === 'rot' ? 'tr' : 'rot'];
  if (other) other.setSelect({ left: u.select.left, width: u.select.width, top: 0, height: other.bbox.height / devicePixelRatio }, false);
  $('selection-text').textContent = `Selected ${fmtTime(from)} – ${fmtTime(to, false)} UTC (${fmtSpan((to - from) / 1000)})`;
  $('selection').hidden = false;
}

function clearSelection() {
  state.selection = null;
  $('selection').hidden = true;
  for (const p of Object.values(state.plots)) if (p) p.setSelect({ left: 0, width: 0, top: 0, height: 0 }, false);
}

// New data goes into the existing plots (a drag in progress survives a live refresh); the
// plots are rebuilt when the series shown or the page's size change.
export function renderPlots(rebuild) {
  const h = state.history;
  if (!h) return;
  if (rebuild || !palette) readPalette();
  for (const kind of ['rot', 'tr']) {
    const plot = state.plots[kind];
    const lay = layout(h[kind], kind);
    if (!rebuild && plot && plot.brokenrayKeys === lay.keys.join()) {
      state.layouts[kind] = lay;
      plot.setData(lay.data);
    } else {
      makePlot(kind, lay);
    }
    const empty = $(kind === 'rot' ? 'empty-rot' : 'empty-tr');
    if (h[kind].count === 0) {
      empty.textContent = 'No results between ' + fmtTime(h.window[0]) + ' and ' + fmtTime(h.window[1]) + ' UTC' +
        (state.newestMs ? '; the newest result is from ' + fmtTime(state.newestMs) + '.' : '.');
      empty.hidden = false;
    } else if (!h[kind].defined) {
      empty.textContent = 'No deformation in this range: it is measured against a reference, and these results ' +
        'were computed without one. Set a reference below.';
      empty.hidden = false;
    } else {
      empty.hidden = true;
    }
  }
}

export async function loadHistory() {
  const target = state.selected;
  if (!target) return;
  const win = windowMs();
  if (state.historyAbort) state.historyAbort.abort();
  const abort = new AbortController();
  state.historyAbort = abort;
  // Only the deformation: a third of the history's components.
  const components = 'components=' + ['r', 't'].flatMap((k) => AXES.map((a) => `def_${k}${a}_${k === 'r' ? 'arcsec' : 'mm'}`)).join(',');
  try {
    const [filtered, raw] = await Promise.all([
      api(historyUrl(target, 'filtered', win, components), { signal: abort.signal }),
      api(historyUrl(target, 'raw', win, components), { signal: abort.signal }),
    ]);
    if (abort.signal.aborted || target !== state.selected) return;
    const merged = merge(filtered, raw);
    state.history = { window: win, rot: merged.rot, tr: merged.tr, info: filtered };
    const res = filtered.resolution_s ? `${filtered.resolution_s} s rollups` : 'the results';
    $('history-info').textContent = `${fmtTime(win[0])} – ${fmtTime(win[1])} UTC · ` + (merged.rot.count
      ? `${merged.rot.count} buckets of ${fmtSpan(filtered.bucket_s)} from ${res}`
      : 'no results');
    document.body.dataset.historyLoads = String(Number(document.body.dataset.historyLoads || 0) + 1);
    document.body.dataset.historyWindowS = String((win[1] - win[0]) / 1000);
    renderPlots();
    clearMessage('history');
  } catch (e) {
    if (e.name === 'AbortError' || e.status === 401) return;
    showMessage('history', 'History: ' + e.message);
  }
  loadAlarms(win).catch(() => {});
}

export function scheduleRefresh() {
  clearInterval(state.refreshTimer);
  state.refreshTimer = null;
  if (state.range.kind !== 'last') return;
  const everyMs = Math.min(60000, Math.max(2000, state.range.seconds * 1000 / 300));
  state.refreshTimer = setInterval(() => {
    if (!document.hidden && !state.selection) loadHistory();
  }, everyMs);
}

function setRange(range, pushZoom) {
  if (pushZoom) state.zoomStack.push(state.range);
  state.range = range;
  $('zoom-out').disabled = state.zoomStack.length === 0;
  for (const b of document.querySelectorAll('[data-range]')) {
    const pressed = range.kind === 'last' ? b.dataset.range === String(range.seconds) : b.dataset.range === 'custom';
    b.setAttribute('aria-pressed', String(pressed));
  }
  const custom = range.kind === 'abs';
  $('custom-range').hidden = !custom;
  if (custom) {
    $('custom-from').value = toInput(range.from);
    $('custom-to').value = toInput(range.to);
  }
  clearSelection();
  scheduleRefresh();
  loadHistory();
}

function zoomOut() {
  const previous = state.zoomStack.pop();
  if (previous) setRange(previous, false);
}

for (const b of document.querySelectorAll('[data-range]')) {
  b.addEventListener('click', () => {
    if (b.dataset.range === 'custom') {
      const [from, to] = windowMs();
      state.zoomStack = [];
      setRange({ kind: 'abs', from, to }, false);
      $('custom-from').focus();
    } else {
      state.zoomStack = [];
      setRange({ kind: 'last', seconds: Number(b.dataset.range) }, false);
    }
  });
}
$('custom-range').addEventListener('submit', (e) => {
  e.preventDefault();
  const from = fromInput($('custom-from').value);
  const to = fromInput($('custom-to').value);
  if (!(from < to)) {
    showMessage('range', 'The custom range needs a start before its end.');
    return;
  }
  clearMessage('range');
  setRange({ kind: 'abs', from, to }, true);
});
$('zoom-out').addEventListener('click', zoomOut);
$('selection-zoom').addEventListener('click', () => {
  const s = state.selection;
  if (s) setRange({ kind: 'abs', from: s.from, to: s.to }, true);
});
$('selection-reference').addEventListener('click', () => {
  const s = state.selection;
  if (!s) return;
  $('reference-from').value = toInput(Math.floor(s.from / 1000) * 1000);
  $('reference-to').value = toInput(Math.ceil(s.to / 1000) * 1000);
  $('reference-submit').focus();
  $('reference-form').scrollIntoView({ block: 'nearest' });
});
$('selection-clear').addEventListener('click', clearSelection);
document.addEventListener('keydown', (e) => {
  if (e.key === 'Escape' && state.selection) clearSelection();
});
for (const box of document.querySelectorAll('[data-show]')) {
  box.addEventListener('change', () => {
    state.show[box.dataset.show] = box.checked;
    renderPlots(true);
  });
}

async function downloadCsv(source) {
  const target = state.selected;
  if (!target) return;
  const win = state.history ? state.history.window : windowMs();
  const from = win[0];
  const url = historyUrl(target, source, win, 'format=csv');
  try {
    const response = await api(url, { raw: true });
    const blob = await response.blob();
    const link = el('a', { href: URL.createObjectURL(blob), download: `${target}-${source}-${iso(from).replace(/[:.]/g, '')}.csv` });
    document.body.append(link);
    link.click();
    link.remove();
    setTimeout(() => URL.revokeObjectURL(link.href), 10000);
  } catch (e) {
    if (e.status !== 401) showMessage('csv', 'CSV download: ' + e.message);
  }
}
// The period's report of the shown range (every target), opened in a new tab.
async function openRangeReport(tab) {
  const win = state.history ? state.history.window : windowMs();
  try {
    await openInTab('/api/v1/report?' + windowQuery(win), tab);
    clearMessage('report');
  } catch (e) {
    if (e.status !== 401) showMessage('report', 'Report: ' + e.message);
  }
}
$('report-range').addEventListener('click', () => openRangeReport(window.open('', '_blank')));
$('csv-filtered').addEventListener('click', () => downloadCsv('filtered'));
$('csv-raw').addEventListener('click', () => downloadCsv('raw'));
