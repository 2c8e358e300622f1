// Drives the dashboard in Chromium against a running service that already holds history.
//
//   node dashboard.mjs BASE_URL LIVE_JSON ARTIFACT_DIR
//
// LIVE_JSON: groups of observations without times ([[{camera, marker, points_px}, ...], ...]),
// posted here with the current time to play a live measurement. Each check that fails throws
// with what it saw; the exit status is 0 only when every check passed. Run by
// tests/suite/service/dashboard.rs, which starts the service and writes the files.
import { readFileSync, mkdirSync } from 'node:fs';
import { join } from 'node:path';
import { check, run, watch } from './lib.mjs';

const [base, liveFile, artifacts] = process.argv.slice(2);
if (!base || !liveFile || !artifacts) {
  console.error('usage: node dashboard.mjs BASE_URL LIVE_JSON ARTIFACT_DIR');
  process.exit(2);
}
const liveGroups = JSON.parse(readFileSync(liveFile, 'utf8'));
mkdirSync(artifacts, { recursive: true });

await run(async (browser) => {
  const context = await browser.newContext({ viewport: { width: 1440, height: 900 }, acceptDownloads: true });
  const page = await context.newPage();
  const problems = watch(page);
  const historyRequests = [];
  page.on('request', (r) => {
    if (r.url().includes('/history?')) historyRequests.push(new URL(r.url()));
  });

  // 1. The page loads, and the card shows the current compensation.
  await page.goto(base + '/', { waitUntil: 'load' });
  await page.waitForSelector('article.card[data-target="G"]:not([data-time=""])[data-time]', { timeout: 15000 });
  const defX = await page.textContent('[data-target="G"] [data-f="def-r-x"]');
  check(Number.isFinite(Number(defX)), `the card shows a deformation: rotation x is "${defX}"`);
  const refBefore = Number(await page.getAttribute('[data-target="G"] [data-f="ref"]', 'data-version'));
  check(refBefore === 1, `the card shows the reference set before the page opened: version ${refBefore}`);

  // 1b. The uncertainty budget beside the card: every contributor, each axis' shares adding
  // up to the whole variance.
  await page.waitForSelector('[data-target="G"] [data-f="budget"] table tbody tr', { timeout: 15000 });
  const budget = await page.evaluate(() => {
    const rows = [...document.querySelectorAll('[data-target="G"] [data-f="budget"] tbody tr')];
    const sums = [0, 0, 0, 0, 0, 0];
    for (const r of rows) {
      [...r.querySelectorAll('td.share .bar')].forEach((b, i) => { sums[i] += parseFloat(b.style.width); });
    }
    return { n: rows.length, kinds: [...new Set(rows.map((r) => r.dataset.kind))].sort(), sums };
  });
  check(budget.n === 8 && budget.kinds.join() === 'calibration,intrinsics,noise'
    && budget.sums.every((x) => Math.abs(x - 100) <= 5),
  `the budget lists ${budget.n} contributors (${budget.kinds.join(', ')}), each axis' bars adding to 100 %: ${budget.sums.join(', ')}`);

  // 1c. The acceptance panel: the built-in installation states a procedure, and the rig has
  // none recorded yet.
  await page.waitForSelector('#acceptance-section:not([hidden]) #acceptance-status [data-standing]', { timeout: 15000 });
  const standing = await page.getAttribute('#acceptance-status [data-standing]', 'data-standing');
  const standingText = await page.textContent('#acceptance-status');
  check(standing === 'none' && standingText.includes('brokenray acceptance'),
    `the acceptance panel says none is recorded: ${standing}, "${standingText}"`);

  // 2. The plots draw data: pixels of the series colours on both canvases.
  await page.waitForFunction(() => Number(document.body.dataset.historyLoads || 0) >= 1, null, { timeout: 15000 });
  const seriesPixels = (selector) => page.evaluate((sel) => {
    const canvas = document.querySelector(sel + ' canvas');
    if (!canvas) return -1;
    const style = getComputedStyle(document.documentElement);
    const colours = ['--x', '--y', '--z'].map((v) => {
      const hex = style.getPropertyValue(v).trim();
      return [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16));
    });
    // Read through a copy, so the page's own canvas is never read back (Chromium warns when a
    // canvas is read repeatedly).
    const copy = document.createElement('canvas');
    copy.width = canvas.width;
    copy.height = canvas.height;
    const ctx = copy.getContext('2d', { willReadFrequently: true });
    ctx.drawImage(canvas, 0, 0);
    const { data } = ctx.getImageData(0, 0, canvas.width, canvas.height);
    let n = 0;
    for (let i = 0; i < data.length; i += 4) {
      for (const c of colours) {
        if (Math.abs(data[i] - c[0]) + Math.abs(data[i + 1] - c[1]) + Math.abs(data[i + 2] - c[2]) < 60 && data[i + 3] > 200) {
          n++;
          break;
        }
      }
    }
    return n;
  }, selector);
  const rotPixels = await seriesPixels('#plot-rot');
  const trPixels = await seriesPixels('#plot-tr');
  check(rotPixels > 300 && trPixels > 300,
    `the plots draw series: ${rotPixels} and ${trPixels} pixels of the series colours`);
  // The relay chain: base, two stations, target, and the three measured rays between them.
  const stations = await page.$$eval('#topology .station text.name', (t) => t.map((e) => e.textContent));
  const rays = await page.$$eval('#topology .ray', (r) => r.map((e) => e.dataset.link));
  check(stations.join(' | ') === 'B | C1 · C2 | M · C3 | G' && rays.join(' ') === 'C1_from_B C2_from_M C3_from_G',
    `the relay chain is drawn as stations: ${stations.join(' | ')}; rays ${rays.join(' ')}`);
  const linkRows = await page.$$eval('#links tbody tr', (r) => r.map((e) => e.dataset.link));
  check(linkRows.length === 5, `the link table lists the five links: ${linkRows.join(', ')}`);
  const outputRows = await page.$$eval('#outputs tbody tr', (r) => r.map((e) => [e.dataset.output, e.querySelector('[data-f="output-state"]').textContent]));
  check(outputRows.length === 1 && outputRows[0][0].startsWith('modbus 127.0.0.1:') && outputRows[0][1].startsWith('listening'),
    `the outputs table lists the Modbus output, listening: ${JSON.stringify(outputRows)}`);
  check(await page.$eval('#outputs-section', (e) => !e.hidden), 'the outputs section shows when outputs are configured');

  // Cameras: the newest frame of each with its detections drawn over it; a covered marker says
  // why it was not found; a click opens the frame full size.
  await page.waitForSelector('article.camera[data-camera="C1"] svg.overlay circle.detected', { timeout: 15000 });
  const detections = await (await fetch(base + '/api/v1/cameras/C1/detections')).json();
  const seen = await page.evaluate(() => {
    const root = document.querySelector('article.camera[data-camera="C1"]');
    const img = root.querySelector('img');
    const circles = [...root.querySelectorAll('circle.detected')]
      .map((c) => [Number(c.getAttribute('cx')), Number(c.getAttribute('cy'))]);
    // The frame's own pixels under each circle's centre (the overlay must sit on the discs).
    const canvas = document.createElement('canvas');
    canvas.width = img.naturalWidth;
    canvas.height = img.naturalHeight;
    const ctx = canvas.getContext('2d', { willReadFrequently: true });
    ctx.drawImage(img, 0, 0);
    const under = circles.map(([x, y]) => ctx.getImageData(Math.floor(x), Math.floor(y), 1, 1).data[0]);
    const box = img.getBoundingClientRect();
    const overlay = root.querySelector('svg.overlay').getBoundingClientRect();
    return {
      natural: [img.naturalWidth, img.naturalHeight], shown: [box.width, box.height], overlay: [overlay.width, overlay.height],
      circles, under, residuals: root.querySelectorAll('line.residual').length,
      magnification: Number(root.querySelector('svg.overlay').dataset.magnification),
    };
  });
  const points = detections.markers[0].points_px;
  check(seen.natural[0] === 1280 && seen.natural[1] === 1024 && seen.shown[0] > 200 && seen.shown[0] < 1280 &&
    Math.abs(seen.overlay[0] - seen.shown[0]) < 1 && Math.abs(seen.overlay[1] - seen.shown[1]) < 1,
  `C1's frame is shown scaled to the panel with its overlay over it: ${seen.natural.join('x')} shown at ${seen.shown.map(Math.round).join('x')}`);
  check(seen.circles.length === points.length && seen.circles.every(([x, y], i) =>
    Math.abs(x - (points[i][0] + 0.5)) < 1e-6 && Math.abs(y - (points[i][1] + 0.5)) < 1e-6),
  `a circle at each of the ${points.length} detected points (pixel centres at +0.5 in the image's coordinates)`);
  check(seen.under.every((v) => v > 150), `the circles sit on the discs: the frame's values under them ${seen.under.join(', ')}`);
  check(seen.residuals === points.length && seen.magnification > 100,
    `each point's residual is drawn, magnified ${seen.magnification} times`);
  const c3 = await page.textContent('article.camera[data-camera="C3"] li[data-found="false"]');
  check(/G: not found/.test(c3) && /at least 4 needed/.test(c3), `the covered marker of C3 is "not found" with its reason: ${c3.trim()}`);
  check(await page.getAttribute('article.camera[data-camera="C3"]', 'data-state') === 'not-found', 'C3\'s panel is marked as not found');
  // A camera the service takes frames from itself shows its source's state; C2's lost its camera.
  const source = (await page.textContent('article.camera[data-camera="C2"] [data-f="source"]')).trim();
  check(/10\.0\.0\.2: disconnected/.test(source) && /last error .*: no frame for 2\.1 s/.test(source) &&
    await page.getAttribute('article.camera[data-camera="C2"] [data-f="source-status"]', 'class') === 'badge alarm',
  `C2's source is shown lost, with its error: ${source}`);
  check(!(await page.isVisible('article.camera[data-camera="C1"] [data-f="source"]')), 'C1, without a source, shows no source line');
  await page.click('article.camera[data-camera="C1"] button.frame');
  await page.waitForSelector('#camera-dialog[open] #camera-dialog-frame img', { timeout: 5000 });
  const full = await page.evaluate(() => {
    const img = document.querySelector('#camera-dialog-frame img');
    return [img.getBoundingClientRect().width, document.querySelectorAll('#camera-dialog-frame circle.detected').length];
  });
  check(Math.round(full[0]) === 1280 && full[1] === points.length, `a click opens the frame at full size with its overlay: ${full.join(', ')}`);
  await page.click('#camera-dialog button[value="close"]');

  // The alarm list: the transitions of the shown range, newest first.
  await page.waitForSelector('#alarms tbody tr');
  const alarmTimes = await page.$$eval('#alarms tbody tr:not(.empty) td:first-child', (cells) => cells.map((c) => c.textContent));
  const sorted = alarmTimes.every((t, i) => i === 0 || alarmTimes[i - 1] >= t);
  check(alarmTimes.length >= 1 && sorted, `the alarm list shows ${alarmTimes.length} transitions, newest first: ${alarmTimes.slice(0, 3).join(', ')}`);

  // The axis toggles hide and show their series.
  for (const a of ['x', 'y', 'z']) await page.uncheck(`input[data-show="${a}"]`);
  const hiddenPixels = await seriesPixels('#plot-rot');
  for (const a of ['x', 'y', 'z']) await page.check(`input[data-show="${a}"]`);
  const shownPixels = await seriesPixels('#plot-rot');
  check(hiddenPixels < 20 && shownPixels > 300,
    `the x, y, z toggles hide and show the series: ${hiddenPixels} pixels hidden, ${shownPixels} shown`);
  const emptyShown = await page.isVisible('#empty-rot');
  check(!emptyShown, 'the rotation plot has no "no data" notice');

  // 3. Live: a new result changes the card.
  const before = {
    time: await page.getAttribute('[data-target="G"]', 'data-time'),
    pose: await page.textContent('[data-target="G"] [data-f="pose-t-x"]'),
  };
  for (const group of liveGroups) {
    const time = new Date().toISOString();
    const response = await fetch(base + '/api/v1/observations', {
      method: 'POST',
      headers: { 'Content-Type': 'application/json' },
      body: JSON.stringify({ observations: group.map((o) => Object.assign({ time }, o)) }),
    });
    if (!response.ok) throw new Error('posting a live observation: ' + response.status + ' ' + await response.text());
    await new Promise((r) => setTimeout(r, 40));
  }
  await page.waitForFunction((t) => document.querySelector('[data-target="G"]').dataset.time !== t,
    before.time, { timeout: 10000 });
  const after = {
    time: await page.getAttribute('[data-target="G"]', 'data-time'),
    pose: await page.textContent('[data-target="G"] [data-f="pose-t-x"]'),
  };
  // RFC 3339 with up to nanoseconds: milliseconds are enough to order them.
  const ms = (t) => Date.parse(t.replace(/(\.\d{1,3})\d*Z$/, '$1Z'));
  check(ms(after.time) > ms(before.time) && after.pose !== before.pose,
    `the card follows the live results: ${before.time} ${before.pose} mm -> ${after.time} ${after.pose} mm`);

  // 4. The range picker asks for the chosen range. (The 5-minute view refreshes itself every
  // 2 s, so requests for it may still be seen around the click.)
  const span = (u) => (Date.parse(u.searchParams.get('to')) - Date.parse(u.searchParams.get('from'))) / 1000;
  const shownWindow = (lo, hi) => page.waitForFunction(([a, b]) => {
    const s = Number(document.body.dataset.historyWindowS);
    return s > a && s < b;
  }, [lo, hi], { timeout: 10000 });
  let r0 = historyRequests.length;
  await page.click('button[data-range="3600"]');
  await shownWindow(3595, 3605);
  const spans = historyRequests.slice(r0).map(span);
  const hour = historyRequests.slice(r0).filter((u) => Math.abs(span(u) - 3600) < 5);
  check(new Set(hour.map((u) => u.searchParams.get('source'))).size === 2,
    `"1 h" asks for an hour of raw and filtered history: spans ${spans.join(', ')} s`);
  const pressed = await page.getAttribute('button[data-range="3600"]', 'aria-pressed');
  check(pressed === 'true', 'the "1 h" button shows as pressed');

  // 5. Zoom: a drag over the plot selects a window; "Zoom in" asks for it at a finer resolution.
  const hourBucket = await page.evaluate(() => document.getElementById('history-info').textContent);
  const over = await page.locator('#plot-rot .u-over').boundingBox();
  const dragTo = async (fromFrac, toFrac) => {
    await page.mouse.move(over.x + over.width * fromFrac, over.y + over.height / 2);
    await page.mouse.down();
    await page.mouse.move(over.x + over.width * ((fromFrac + toFrac) / 2), over.y + over.height / 2, { steps: 4 });
    await page.mouse.move(over.x + over.width * toFrac, over.y + over.height / 2, { steps: 4 });
    await page.mouse.up();
  };
  await dragTo(0.97, 0.995);
  await page.waitForSelector('#selection:not([hidden])', { timeout: 5000 });
  r0 = historyRequests.length;
  const zoomResponse = page.waitForResponse((r) => r.url().includes('/history?') &&
    r.url().includes('source=filtered') && span(new URL(r.url())) < 200);
  await page.click('#selection-zoom');
  const zoomed = await (await zoomResponse).json();
  await shownWindow(30, 200);
  const zoomSpans = historyRequests.slice(r0).map(span).filter((s) => s < 3000);
  check(zoomSpans.length === 2 && zoomSpans.every((s) => s > 30 && s < 200),
    `zooming in asks for the selected window: spans ${zoomSpans.join(', ')} s`);
  check(zoomed.bucket_s < 0.5 && zoomed.resolution_s === null,
    `the zoomed history is finer: buckets of ${zoomed.bucket_s} s from the results (1 h: ${hourBucket})`);
  check(!(await page.isDisabled('#zoom-out')), 'zoom out is offered');
  const zoomedPixels = await seriesPixels('#plot-rot');
  check(zoomedPixels > 300, `the zoomed plot draws data: ${zoomedPixels} pixels`);

  // 6. The reference, from a window selected on the plot, updates the card.
  await dragTo(0.3, 0.7);
  await page.waitForSelector('#selection:not([hidden])', { timeout: 5000 });
  await page.click('#selection-reference');
  const windowFrom = await page.inputValue('#reference-from');
  const windowTo = await page.inputValue('#reference-to');
  await page.click('#reference-submit');
  await page.waitForFunction((v) => Number(document.querySelector('[data-target="G"] [data-f="ref"]').dataset.version) > v,
    refBefore, { timeout: 10000 });
  const refText = await page.textContent('[data-target="G"] [data-f="ref"]');
  const result = await page.textContent('#reference-result');
  check(refText.startsWith('v2 '), `the card shows the new reference: "${refText}" (${result}; window ${windowFrom} to ${windowTo})`);
  await page.waitForFunction(() => document.querySelectorAll('#references tbody tr').length === 2, null, { timeout: 5000 });
  const versions = await page.$$eval('#references tbody tr td:first-child', (c) => c.map((e) => e.textContent));
  check(versions.join(',') === '2,1', `the reference versions are listed newest first: ${versions.join(', ')}`);

  // 7. CSV of the shown range.
  const downloadEvent = page.waitForEvent('download');
  await page.click('#csv-filtered');
  const download = await downloadEvent;
  const csvPath = join(artifacts, 'dashboard-history.csv');
  await download.saveAs(csvPath);
  const csv = readFileSync(csvPath, 'utf8').split('\n').filter((l) => l);
  check(csv[0].startsWith('time,count,euler_x_deg_min') && csv.length > 10,
    `the CSV download holds the shown range: ${csv.length - 1} rows`);

  // 8. Keyboard: the range buttons, toggles and reference form are reached with Tab.
  await page.click('h1');
  const reached = new Set();
  for (let i = 0; i < 40; i++) {
    await page.keyboard.press('Tab');
    reached.add(await page.evaluate(() => {
      const a = document.activeElement;
      return a.id || a.dataset.range || a.dataset.show || a.textContent.trim();
    }));
  }
  for (const want of ['3600', 'custom', 'x', 'band', 'csv-raw']) {
    check(reached.has(want), `"${want}" is reached with the keyboard: ${[...reached].join(', ')}`);
  }

  // No new result for a while (the live posts stopped): the age counts on and turns amber.
  await page.waitForFunction(() => document.querySelector('[data-target="G"] [data-f="age"]').className === 'over-warn',
    null, { timeout: 15000 });
  const age = await page.textContent('[data-target="G"] [data-f="age"]');
  check(parseFloat(age) >= 5, `the age of the newest result counts on and warns: ${age}`);

  await page.click('button[data-range="300"]');

  // 9. The feed has stopped: by the server's clock the target turns stale and the stale alarm
  // is raised; it is acknowledged from its row, with who and a note, and the service has it.
  await page.waitForFunction(() => document.querySelector('[data-target="G"] [data-f="status"]').textContent === 'stale',
    null, { timeout: 15000 });
  check(true, 'the card says "stale" once the feed has stopped (judged on the server\'s clock)');
  const staleRowId = () => {
    const row = [...document.querySelectorAll('#alarms tbody tr')]
      .find((r) => r.children[2] && r.children[2].textContent === 'stale' && r.querySelector('button[data-ack]'));
    return row ? row.dataset.alarm : null;
  };
  const staleId = await (await page.waitForFunction(staleRowId, null, { timeout: 15000 })).jsonValue();
  check(staleId !== null, `the stale alarm is listed with an "Acknowledge" button: alarm ${staleId}`);
  const row = `#alarms tbody tr[data-alarm="${staleId}"]`;
  await page.click(`${row} button[data-ack]`);
  await page.fill(`${row} input[name="by"]`, 'test operator');
  // The table is drawn again at every refresh (every 2 s here): the form being written stays
  // open with what was typed, and its field keeps the focus and the caret.
  await page.$eval(`${row} input[name="by"]`, (input) => { input.dataset.drawn = 'before'; input.setSelectionRange(4, 4); });
  await page.waitForFunction((sel) => {
    const input = document.querySelector(sel);
    return input && input.dataset.drawn !== 'before';
  }, `${row} input[name="by"]`, { timeout: 10000 });
  const kept = await page.$eval(`${row} input[name="by"]`, (input) => [input.value, document.activeElement === input, input.selectionStart]);
  check(kept[0] === 'test operator' && kept[1] && kept[2] === 4,
    `an acknowledgement being written survives the table's redraw: "${kept[0]}", focused ${kept[1]}, caret at ${kept[2]}`);
  await page.fill(`${row} input[name="note"]`, 'feed stopped on purpose');
  await page.click(`${row} .ack-form button[type="submit"]`);
  await page.waitForFunction((sel) => (document.querySelector(sel)?.textContent || '').includes('test operator'), row, { timeout: 10000 });
  const stored = await (await fetch(base + '/api/v1/alarms?order=desc&limit=100')).json();
  const acked = stored.alarms.find((a) => String(a.id) === staleId);
  check(acked && acked.acknowledged_by === 'test operator' && acked.note === 'feed stopped on purpose' && acked.acknowledged_at,
    `the acknowledgement is stored: ${JSON.stringify(acked && { by: acked.acknowledged_by, at: acked.acknowledged_at, note: acked.note })}`);

  // 10. A stale link offers a reset of its filter; two clicks (ask, confirm) restart it.
  const reset = '#links button[data-reset="C1_from_B"]';
  await page.waitForSelector(reset, { timeout: 10000 });
  await page.click(reset);
  await page.waitForSelector(reset + '.danger', { timeout: 5000 });
  await page.click(reset);
  await page.waitForFunction(() => document.querySelector('#links tr[data-link="C1_from_B"] .badge')?.textContent === 'no data',
    null, { timeout: 10000 });
  const links = await (await fetch(base + '/api/v1/links')).json();
  const c1 = links.find((l) => l.name === 'C1_from_B');
  check(c1.status === 'no_data' && c1.last_reset && c1.last_reset.by === 'test operator' && /dashboard/.test(c1.last_reset.note),
    `the reset is recorded with who asked: ${JSON.stringify(c1.last_reset)}`);
  await page.waitForTimeout(1500);
  await page.screenshot({ path: join(artifacts, 'dashboard.png'), fullPage: true });
  await page.setViewportSize({ width: 1366, height: 768 });
  await page.waitForTimeout(500);
  await page.screenshot({ path: join(artifacts, 'dashboard-laptop.png') });
  await page.setViewportSize({ width: 2560, height: 1440 });
  await page.waitForTimeout(500);
  await page.screenshot({ path: join(artifacts, 'dashboard-control-room.png') });

  // Dark, as a control room's system may ask: the plots are drawn in the dark palette.
  await page.emulateMedia({ colorScheme: 'dark' });
  await page.waitForTimeout(500);
  const darkPixels = await seriesPixels('#plot-rot');
  await page.setViewportSize({ width: 1920, height: 1080 });
  await page.waitForTimeout(500);
  check(darkPixels > 300, `the plots draw in the dark palette: ${darkPixels} pixels of its series colours`);
  await page.screenshot({ path: join(artifacts, 'dashboard-dark.png') });

  check(problems.length === 0, `no console errors or warnings: ${problems.join(' | ')}`);
});
