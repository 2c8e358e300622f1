// The relay chain drawn as SVG: stations and the rays between them, for the selected target.

import { $, state } from './util.js';

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

export function renderTopology() {
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
