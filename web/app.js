// brokenray dashboard: compensation cards live from /api/v1/events, history plots (uPlot),
// reference, alarms, relay chain and links. Plain script, no build step; served by the binary.
//
// Times are shown in UTC. Every API call goes through `api`, which adds the bearer token when one
// was given (kept in sessionStorage for this tab) and asks for one on 401. The event stream is
// read with fetch (EventSource cannot send an Authorization header).
'use strict';

(function () {
  const $ = (id) => document.getElementById(id);
  const AXES = ['x', 'y', 'z'];
  const TOKEN_KEY = 'brokenray.token';
  const ALARMS_SHOWN = 500;
  const LATE_WARN_S = 5; // a result older than this: the age turns amber
  const LATE_ALARM_S = 60; // and red

  const state = {
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
  };

  // ---------------------------------------------------------------- messages

  const messages = new Map();
  function showMessage(key, text, kind) {
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
  function clearMessage(key) {
    const el = messages.get(key);
    if (el) {
      el.remove();
      messages.delete(key);
    }
  }

  // ---------------------------------------------------------------- time and numbers

  // RFC 3339 with up to nanoseconds -> ms since the epoch.
  function parseTime(text) {
    if (!text) return NaN;
    const m = /^(.*T\d\d:\d\d:\d\d)(\.\d+)?(Z|[+-]\d\d:\d\d)$/.exec(text);
    if (!m) return Date.parse(text);
    const frac = m[2] ? m[2].slice(0, 4) : '';
    return Date.parse(m[1] + frac + m[3]);
  }
  const pad = (n, w = 2) => String(n).padStart(w, '0');
  function fmtTime(ms, withDate = true) {
    if (!Number.isFinite(ms)) return '—';
    const d = new Date(ms);
    const t = `${pad(d.getUTCHours())}:${pad(d.getUTCMinutes())}:${pad(d.getUTCSeconds())}`;
    if (!withDate) return t;
    return `${d.getUTCFullYear()}-${pad(d.getUTCMonth() + 1)}-${pad(d.getUTCDate())} ${t}`;
  }
  function toInput(ms) {
    const d = new Date(ms);
    return `${d.getUTCFullYear()}-${pad(d.getUTCMonth() + 1)}-${pad(d.getUTCDate())}T` +
      `${pad(d.getUTCHours())}:${pad(d.getUTCMinutes())}:${pad(d.getUTCSeconds())}`;
  }
  function fromInput(value) {
    if (!value) return NaN;
    return Date.parse(value.length === 16 ? value + ':00Z' : value + 'Z');
  }
  const iso = (ms) => new Date(ms).toISOString();
  function fmtAge(s) {
    if (!Number.isFinite(s)) return '—';
    if (s < 0) s = 0;
    if (s < 10) return s.toFixed(1) + ' s';
    if (s < 120) return Math.round(s) + ' s';
    if (s < 7200) return Math.round(s / 60) + ' min';
    if (s < 172800) return (s / 3600).toFixed(1) + ' h';
    return (s / 86400).toFixed(1) + ' d';
  }
  function fmtSpan(s) {
    if (s < 1) return (s * 1000).toFixed(0) + ' ms';
    if (s < 120) return s.toFixed(s < 10 ? 1 : 0) + ' s';
    if (s < 7200) return (s / 60).toFixed(1) + ' min';
    if (s < 172800) return (s / 3600).toFixed(1) + ' h';
    return (s / 86400).toFixed(1) + ' d';
  }
  const fmt = (v, digits) => (v === null || v === undefined || !Number.isFinite(v) ? '—' : v.toFixed(digits));
  const norm3 = (v) => (v ? Math.hypot(v[0], v[1], v[2]) : NaN);
  function el(tag, attrs, ...children) {
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

  // ---------------------------------------------------------------- API

  class ApiError extends Error {
    constructor(status, message) {
      super(message);
      this.status = status;
    }
  }

  function headers(extra) {
    const h = Object.assign({}, extra || {});
    if (state.token) h.Authorization = 'Bearer ' + state.token;
    return h;
  }

  async function describe(response) {
    try {
      const body = await response.json();
      const e = body.error || {};
      const details = (e.details || []).map((d) => (d.field ? d.field + ': ' : '') + d.message);
      return (e.message || response.statusText) + (details.length ? ' (' + details.join('; ') + ')' : '');
    } catch (_) {
      return response.status + ' ' + response.statusText;
    }
  }

  async function api(path, options) {
    const opts = options || {};
    const init = { method: opts.method || 'GET', headers: headers(opts.headers), signal: opts.signal };
    if (opts.json !== undefined) {
      init.body = JSON.stringify(opts.json);
      init.headers['Content-Type'] = 'application/json';
    }
    const response = await fetch(path, init);
    if (response.status === 401) {
      askToken(await describe(response));
      throw new ApiError(401, 'a token is needed');
    }
    if (!response.ok) throw new ApiError(response.status, await describe(response));
    if (opts.raw) return response;
    return response.json();
  }

  // ---------------------------------------------------------------- token

  let tokenAsked = false;
  function askToken(reason) {
    if (tokenAsked) return;
    tokenAsked = true;
    $('token-reason').textContent = reason
      ? 'The service answered: ' + reason + '. The token is kept for this browser tab only.'
      : 'The token is kept for this browser tab only.';
    $('token-input').value = '';
    if (!$('token-dialog').open) $('token-dialog').showModal();
  }
  $('token-button').addEventListener('click', () => {
    tokenAsked = false;
    askToken('');
  });
  $('token-dialog').addEventListener('close', () => {
    tokenAsked = false;
    const choice = $('token-dialog').returnValue;
    if (choice === 'save' && $('token-input').value.trim()) {
      state.token = $('token-input').value.trim();
      sessionStorage.setItem(TOKEN_KEY, state.token);
    } else if (choice === 'clear') {
      state.token = '';
      sessionStorage.removeItem(TOKEN_KEY);
    } else {
      return;
    }
    start();
  });

  // ---------------------------------------------------------------- compensation cards

  const cards = new Map(); // target -> {root, fields}

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

  function buildCard(target) {
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
    const root = el('article', { class: 'card', 'data-target': name, 'aria-label': 'Target ' + name },
      head, table, noRef, foot);
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

  function renderAge(name) {
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

  function acceptCompensation(c) {
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

  async function loadCompensation(name) {
    const c = await api('/api/v1/targets/' + encodeURIComponent(name) + '/compensation');
    acceptCompensation(c);
  }

  // ---------------------------------------------------------------- live events

  let eventsAbort = null;
  let eventsGeneration = 0;
  function setLive(stateName, text) {
    $('live').dataset.state = stateName;
    $('live').textContent = text;
  }

  async function runEvents() {
    if (eventsAbort) eventsAbort.abort();
    const generation = ++eventsGeneration;
    let delayMs = 1000;
    while (generation === eventsGeneration) {
      eventsAbort = new AbortController();
      try {
        const response = await fetch('/api/v1/events', {
          headers: headers({ Accept: 'text/event-stream' }),
          signal: eventsAbort.signal,
        });
        if (response.status === 401) {
          askToken(await describe(response));
          setLive('offline', 'needs a token');
          return;
        }
        if (!response.ok || !response.body) throw new Error(await describe(response));
        setLive('live', 'live');
        clearMessage('events');
        delayMs = 1000;
        // Results missed while disconnected: ask for the current ones once.
        for (const t of state.targets) loadCompensation(t.name).catch(() => {});
        await readEvents(response.body.getReader());
      } catch (e) {
        if (e.name === 'AbortError') return;
        showMessage('events', 'Live updates interrupted: ' + e.message + '. Reconnecting…');
      }
      if (generation !== eventsGeneration) return;
      setLive('reconnecting', 'reconnecting…');
      await new Promise((r) => setTimeout(r, delayMs));
      delayMs = Math.min(delayMs * 2, 15000);
    }
  }

  async function readEvents(reader) {
    const decoder = new TextDecoder();
    let buffer = '';
    let event = 'message';
    let data = [];
    for (;;) {
      const { value, done } = await reader.read();
      if (done) return;
      buffer += decoder.decode(value, { stream: true });
      let nl;
      while ((nl = buffer.indexOf('\n')) >= 0) {
        let line = buffer.slice(0, nl);
        buffer = buffer.slice(nl + 1);
        if (line.endsWith('\r')) line = line.slice(0, -1);
        if (line === '') {
          if (data.length) dispatch(event, data.join('\n'));
          event = 'message';
          data = [];
        } else if (line.startsWith(':')) {
          // keep-alive comment
        } else {
          const colon = line.indexOf(':');
          const field = colon < 0 ? line : line.slice(0, colon);
          let v = colon < 0 ? '' : line.slice(colon + 1);
          if (v.startsWith(' ')) v = v.slice(1);
          if (field === 'event') event = v;
          else if (field === 'data') data.push(v);
        }
      }
    }
  }

  function dispatch(event, text) {
    let body;
    try {
      body = JSON.parse(text);
    } catch (_) {
      return;
    }
    if (event === 'result') acceptCompensation(body);
    else if (event === 'alarm') acceptAlarm(body);
  }

  // ---------------------------------------------------------------- history

  // `from=..&to=..` of a window (ms).
  const windowQuery = (win) => `from=${encodeURIComponent(iso(win[0]))}&to=${encodeURIComponent(iso(win[1]))}`;

  // A history request of the selected target over `win`, one bucket a pixel of plot width.
  function historyUrl(target, source, win, extra) {
    const maxPoints = Math.min(2000, Math.round(plotWidth()));
    return '/api/v1/targets/' + encodeURIComponent(target) + `/history?source=${source}&` +
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

  function windowMs() {
    if (state.range.kind === 'abs') return [state.range.from, state.range.to];
    const end = Math.max(Date.now(), state.newestMs);
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
  function renderPlots(rebuild) {
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

  async function loadHistory() {
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

  function scheduleRefresh() {
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
  $('csv-filtered').addEventListener('click', () => downloadCsv('filtered'));
  $('csv-raw').addEventListener('click', () => downloadCsv('raw'));

  // ---------------------------------------------------------------- reference

  function renderReferencePanel() {
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

  async function loadReferences(target) {
    const answer = await api('/api/v1/targets/' + encodeURIComponent(target) + '/references');
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

  // ---------------------------------------------------------------- alarms

  // Who acts, remembered on this computer for the next acknowledgement or reset.
  const OPERATOR_KEY = 'brokenray.operator';
  const operator = () => { try { return localStorage.getItem(OPERATOR_KEY) || ''; } catch (_) { return ''; } };
  const rememberOperator = (name) => { try { localStorage.setItem(OPERATOR_KEY, name); } catch (_) { /* private mode */ } };

  // The acknowledgement cell: who and when once acknowledged; a button on a raised level.
  function ackCell(a) {
    const cell = el('td', { class: 'ack' });
    if (a.acknowledged_by) {
      cell.append(el('span', { text: a.acknowledged_by }),
        el('div', { class: 'muted small', text: fmtTime(parseTime(a.acknowledged_at)) }));
      if (a.note) cell.append(el('div', { class: 'muted small', text: a.note }));
      return cell;
    }
    if (a.to === 'none' || a.id === undefined) return cell;
    const button = el('button', { type: 'button', class: 'ghost', 'data-ack': String(a.id), text: 'Acknowledge' });
    button.addEventListener('click', () => {
      const by = el('input', { type: 'text', name: 'by', placeholder: 'your name', 'aria-label': 'Acknowledged by', required: '', value: operator() });
      const note = el('input', { type: 'text', name: 'note', placeholder: 'note (optional)', 'aria-label': 'Note' });
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
      by.focus();
    });
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
    body.textContent = '';
    if (!state.alarms.length) {
      body.append(el('tr', { class: 'empty' }, el('td', { colspan: '7', text: 'No alarm transitions in the shown range.' })));
      return;
    }
    for (const a of state.alarms) body.append(alarmRow(a));
  }

  async function loadAlarms(win) {
    const answer = await api(`/api/v1/alarms?${windowQuery(win)}&limit=${ALARMS_SHOWN}&order=desc`);
    state.alarms = answer.alarms;
    renderAlarms();
    redrawMarks();
  }

  function redrawMarks() {
    for (const p of Object.values(state.plots)) if (p) p.redraw(false, false);
  }

  function acceptAlarm(a) {
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

  // ---------------------------------------------------------------- relay chain

  const SVG = 'http://www.w3.org/2000/svg';
  function svg(tag, attrs, ...children) {
    const e = document.createElementNS(SVG, tag);
    for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
    for (const c of children) e.append(c);
    return e;
  }

  // A path's stations: frames joined by calibrated links are one rigid station; a measured link
  // is a ray between two stations.
  function stationsOf(path, links) {
    const stations = [{ frames: [path.frames[0]], inner: [] }];
    const rays = [];
    path.steps.forEach((step, i) => {
      const link = links.get(step.link);
      if (link && link.kind === 'calibrated') {
        const s = stations[stations.length - 1];
        s.frames.push(path.frames[i + 1]);
        s.inner.push(step.link);
      } else {
        rays.push(step.link);
        stations.push({ frames: [path.frames[i + 1]], inner: [] });
      }
    });
    return { stations, rays };
  }

  function renderTopology() {
    const target = state.targets.find((t) => t.name === state.selected);
    const box = $('topology');
    box.textContent = '';
    if (!target) return;
    $('topology-target').textContent = `${target.name} from ${target.base}`;
    const links = new Map(state.links.map((l) => [l.name, l]));
    const paths = target.paths.map((p) => ({ p, label: 'fused path' }))
      .concat(target.dependent_paths.map((p) => ({ p, label: 'dependent path (not fused)' })));
    for (const { p, label } of paths) {
      const { stations, rays } = stationsOf(p, links);
      const boxW = 170, gap = 190, boxH = 78, top = 24;
      const width = stations.length * boxW + (stations.length - 1) * gap + 20;
      const height = top + boxH + 16;
      const root = svg('svg', { viewBox: `0 0 ${width} ${height}`, role: 'img', 'aria-label': `${label}: ${p.product}` });
      // At its natural size (the same scale for every path), shrunk to fit a narrow screen.
      root.setAttribute('width', String(width));
      root.setAttribute('height', String(height));
      root.append(svg('defs', {}, svg('marker', { id: 'arrow', viewBox: '0 0 10 10', refX: '10', refY: '5', markerWidth: '7', markerHeight: '7', orient: 'auto-start-reverse' },
        svg('path', { d: 'M0,0 L10,5 L0,10 z' }))));
      const title = svg('text', { x: '10', y: '14', class: 'path-label' });
      title.textContent = `${label}: ${p.product}`;
      root.append(title);
      stations.forEach((s, i) => {
        const x = 10 + i * (boxW + gap);
        const end = i === 0 || i === stations.length - 1;
        const role = i === 0 ? 'base' : i === stations.length - 1 ? 'target' : `station ${i}`;
        const g = svg('g', { class: 'station' + (end ? ' end' : '') });
        g.append(svg('rect', { x: String(x), y: String(top), width: String(boxW), height: String(boxH), rx: '8' }));
        const name = svg('text', { x: String(x + boxW / 2), y: String(top + 26), 'text-anchor': 'middle', class: 'name' });
        name.textContent = s.frames.join(' · ');
        const roleText = svg('text', { x: String(x + boxW / 2), y: String(top + 46), 'text-anchor': 'middle', class: 'inner' });
        roleText.textContent = role;
        const inner = svg('text', { x: String(x + boxW / 2), y: String(top + 64), 'text-anchor': 'middle', class: 'inner' });
        inner.textContent = s.inner.length ? 'rigid: ' + s.inner.join(', ') : '';
        g.append(name, roleText, inner);
        root.append(g);
        if (i < rays.length) {
          const link = links.get(rays[i]);
          const status = link ? link.status : 'unknown';
          const cls = status === 'ok' ? 'ok' : status === 'stale' || status === 'no_data' ? 'warn' : 'alarm';
          const x1 = x + boxW, x2 = x + boxW + gap, y = top + boxH / 2;
          const ray = svg('g', { class: 'ray ' + cls, 'data-link': rays[i] });
          ray.append(svg('line', { x1: String(x1 + 4), y1: String(y), x2: String(x2 - 4), y2: String(y) }));
          const t1 = svg('text', { x: String((x1 + x2) / 2), y: String(y - 8), 'text-anchor': 'middle' });
          t1.textContent = rays[i];
          const t2 = svg('text', { x: String((x1 + x2) / 2), y: String(y + 18), 'text-anchor': 'middle', class: 'state' });
          t2.textContent = link ? `${status}${link.rate_hz ? ' · ' + link.rate_hz.toFixed(1) + ' Hz' : ''}` : '';
          ray.append(t1, t2);
          root.append(ray);
        }
      });
      box.append(root);
    }
  }

  // ---------------------------------------------------------------- links

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
  async function loadWebhooks() {
    const hooks = await api('/api/v1/webhooks');
    const failing = hooks.filter((h) => h.failing || h.dropped > 0);
    if (failing.length) {
      showMessage('webhooks', 'Alarm notifications are failing: ' +
        failing.map((h) => `${h.host} (${h.last_error || h.dropped + ' dropped'})`).join('; '));
    } else {
      clearMessage('webhooks');
    }
  }

  async function loadLinks() {
    state.links = await api('/api/v1/links');
    renderLinks();
    renderTopology();
    clearMessage('links');
  }

  // ---------------------------------------------------------------- targets

  function selectTarget(name, scroll) {
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
    state.targets = await api('/api/v1/targets');
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

  // ---------------------------------------------------------------- start

  let started = false;
  let linksTimer = null;
  async function start() {
    clearMessage('start');
    try {
      await loadTargets();
      await Promise.all(state.targets.map((t) => loadCompensation(t.name)));
      await loadLinks();
    } catch (e) {
      if (e.status !== 401) showMessage('start', 'Cannot reach the service: ' + e.message);
      return;
    }
    const keep = state.targets.some((t) => t.name === state.selected);
    if (state.targets.length) selectTarget(keep ? state.selected : state.targets[0].name, false);
    scheduleRefresh();
    runEvents();
    if (!started) {
      started = true;
      linksTimer = setInterval(() => {
        if (document.hidden) return;
        loadLinks().catch((e) => { if (e.status !== 401) showMessage('links', 'Links: ' + e.message); });
        loadWebhooks().catch((e) => { if (e.status !== 401) showMessage('webhooks', 'Webhooks: ' + e.message); });
      }, 2000);
      void linksTimer;
    }
  }

  function tick() {
    $('clock').textContent = fmtTime(Date.now()) + ' UTC';
    for (const name of cards.keys()) renderAge(name);
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

  start();
})();
