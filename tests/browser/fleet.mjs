// Drives a centre's dashboard in Chromium: the fleet panel lists the site with its contact,
// alarm and targets, and the site opens in the page's views from its uploaded copy.
//
//   node fleet.mjs BASE_URL SITE TOKEN ARTIFACT_DIR
//
// The centre must already hold the site's uploads (results, a reference, alarms). Each check
// that fails throws with what it saw; the exit status is 0 only when every check passed. Run
// by tests/suite/fleet.rs, which starts the centre and the site and waits for the upload.
import { mkdirSync } from 'node:fs';
import { join } from 'node:path';
import { check, run, watch } from './lib.mjs';

const [base, site, token, artifacts] = process.argv.slice(2);
if (!base || !site || !token || !artifacts) {
  console.error('usage: node fleet.mjs BASE_URL SITE TOKEN ARTIFACT_DIR');
  process.exit(2);
}
mkdirSync(artifacts, { recursive: true });

await run(async (browser) => {
  const context = await browser.newContext({ viewport: { width: 1440, height: 900 } });
  // The office's read token, as the token dialog would keep it for the tab.
  await context.addInitScript((t) => sessionStorage.setItem('brokenray.token', t), token);
  const page = await context.newPage();
  const problems = watch(page);

  // 1. The centre's page shows the fleet: the site, its last contact, its alarm, its targets.
  await page.goto(base + '/', { waitUntil: 'load' });
  await page.waitForSelector(`#fleet:not([hidden]) #sites tr[data-site="${site}"]`, { timeout: 15000 });
  const row = `#sites tr[data-site="${site}"]`;
  const contact = await page.textContent(`${row} td:nth-of-type(1)`);
  check(/ago$/.test(contact.trim()), `the site's last contact is shown: "${contact.trim()}"`);
  const alarm = await page.textContent(`${row} td:nth-of-type(2) .badge`);
  check(alarm === 'alarm', `the site's worst alarm is shown: "${alarm}"`);
  const targets = await page.textContent(`${row} td:nth-of-type(3)`);
  check(targets.includes('G'), `the site's targets are listed: "${targets.trim()}"`);
  check(await page.isVisible('#cameras-title'), 'the centre\'s own view shows its cameras section');
  await page.screenshot({ path: join(artifacts, 'fleet-centre.png'), fullPage: false });

  // 2. Opening the site: its targets in the same views, from its uploaded copy.
  await page.click(`${row} a[data-open-site="${site}"]`);
  await page.waitForSelector('#site-banner:not([hidden])', { timeout: 15000 });
  check((await page.textContent('#site-name')) === site, 'the banner names the site');
  await page.waitForSelector('article.card[data-target="G"][data-time]:not([data-time=""])', { timeout: 15000 });
  const defX = await page.textContent('[data-target="G"] [data-f="def-r-x"]');
  check(Number.isFinite(Number(defX)), `the site's card shows a deformation: rotation x is "${defX}"`);
  const refVersion = Number(await page.getAttribute('[data-target="G"] [data-f="ref"]', 'data-version'));
  check(refVersion >= 1, `the card shows the site's reference: version ${refVersion}`);
  await page.waitForFunction(() => Number(document.body.dataset.historyLoads || 0) >= 1, null, { timeout: 15000 });
  const info = await page.textContent('#history-info');
  check(/buckets of/.test(info), `the history plots the site's uploaded results: "${info}"`);
  await page.waitForSelector('#alarms tbody tr[data-alarm]:not([data-alarm=""])', { timeout: 15000 });
  const acks = await page.$$('#alarms button[data-ack]');
  check(acks.length === 0, 'a site\'s alarms are not acknowledged at the centre (no button)');
  const refs = await page.$$('#references tbody tr:not(.empty)');
  check(refs.length >= 1, `the site's reference versions are listed: ${refs.length}`);
  for (const id of ['reference-form', 'cameras-title', 'links-title']) {
    check(!(await page.isVisible('#' + id)), `#${id} is hidden on a site's read-only copy`);
  }
  check((await page.textContent('#live')) === 'uploaded copy', 'the live badge says the copy is not live');
  await page.screenshot({ path: join(artifacts, 'fleet-site.png'), fullPage: true });

  // 3. Back to the centre's own view.
  await page.click('#site-banner a[href="#"]');
  await page.waitForSelector('#site-banner[hidden]', { state: 'attached', timeout: 15000 });
  check(await page.isVisible('#cameras-title'), 'back on the centre\'s own view');

  check(problems.length === 0, `no console errors or warnings: ${problems.join(' | ')}`);
});
