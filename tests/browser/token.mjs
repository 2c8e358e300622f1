// The dashboard on a service with tokens: it asks for one, sends it with every call and with
// the event stream, and says so when the token lacks the admin scope. Camera C1's calibration
// report (named by the installation) opens from its link in a new tab, fetched with the token,
// with its style kept under the dashboard's content policy; the shown range's report opens the
// same way, its pictures drawn and laid out for print.
//
//   node token.mjs BASE_URL READ_TOKEN
//
// Run by tests/suite/service/dashboard.rs. The only console errors allowed are the browser's own
// reports of the 401 before the token is given and of the 403 the reference gets.
import { check, run, watch } from './lib.mjs';

const [base, token] = process.argv.slice(2);
if (!base || !token) {
  console.error('usage: node token.mjs BASE_URL READ_TOKEN');
  process.exit(2);
}

await run(async (browser) => {
  const context = await browser.newContext({ viewport: { width: 1280, height: 900 } });
  const page = await context.newPage();
  const problems = watch(page);
  const authorised = [];
  page.on('request', (r) => {
    if (r.url().includes('/api/v1/') && r.headers().authorization === 'Bearer ' + token) authorised.push(new URL(r.url()).pathname);
  });

  await page.goto(base + '/', { waitUntil: 'load' });
  await page.waitForSelector('#token-dialog[open]', { timeout: 10000 });
  const reason = await page.textContent('#token-reason');
  check(reason.includes('Bearer'), `the page asks for a token, saying why: "${reason}"`);

  await page.fill('#token-input', token);
  await page.click('#token-form button[value="save"]');
  await page.waitForSelector('article.card[data-target="G"]:not([data-time=""])[data-time]', { timeout: 10000 });
  await page.waitForFunction(() => document.getElementById('live').dataset.state === 'live', null, { timeout: 10000 });
  for (const path of ['/api/v1/targets', '/api/v1/targets/G/compensation', '/api/v1/links', '/api/v1/events', '/api/v1/targets/G/history']) {
    check(authorised.includes(path), `${path} was asked with the token`);
  }
  const stored = await page.evaluate(() => sessionStorage.getItem('brokenray.token'));
  check(stored === token, 'the token is kept for the tab (sessionStorage)');

  // The calibration report: linked for C1 only, opened in a new tab with the token.
  await page.waitForSelector('article.camera[data-camera="C1"] [data-f="report"]', { timeout: 10000 });
  check(await page.locator('article.camera[data-camera="C2"] [data-f="report"]').count() === 0,
    'camera C2, whose installation names no report, has no report link');
  const [tab] = await Promise.all([
    context.waitForEvent('page', { timeout: 10000 }),
    page.click('article.camera[data-camera="C1"] [data-f="report"]'),
  ]);
  const tabProblems = watch(tab);
  await tab.waitForSelector('h1', { timeout: 10000 });
  const heading = await tab.textContent('h1');
  check(heading.includes('Camera calibration: C1'), `the report opens in a new tab: "${heading}"`);
  check(authorised.includes('/api/v1/cameras/C1/calibration-report'), 'the report was asked with the token');
  const styled = await tab.evaluate(() => ({
    collapse: getComputedStyle(document.querySelector('table')).borderCollapse,
    pictures: document.querySelectorAll('svg').length,
  }));
  check(styled.collapse === 'collapse' && styled.pictures >= 3,
    `the report keeps its style under the dashboard's policy (tables ${styled.collapse}) and its ${styled.pictures} pictures`);
  check(tabProblems.length === 0, `the report's tab reports no problem: ${tabProblems.join(' | ')}`);
  await tab.close();

  // The period's report of the shown range: fetched with the token, opened in a new tab, its
  // pictures drawn, and laid out for print (each picture whole on an A4 page).
  const [reportTab] = await Promise.all([
    context.waitForEvent('page', { timeout: 10000 }),
    page.click('#report-range'),
  ]);
  const reportProblems = watch(reportTab);
  await reportTab.waitForSelector('h1', { timeout: 20000 });
  const reportHeading = await reportTab.textContent('h1');
  check(reportHeading.startsWith('Deformation report'), `the range's report opens in a new tab: "${reportHeading}"`);
  check(authorised.includes('/api/v1/report'), 'the report was asked with the token');
  const drawn = await reportTab.evaluate(() => ({
    target: Boolean([...document.querySelectorAll('h2')].find((h) => h.textContent === 'Target G')),
    pictures: [...document.querySelectorAll('svg')].map((svg) => {
      const box = svg.getBoundingClientRect();
      return { width: box.width, height: box.height, paths: svg.querySelectorAll('path').length };
    }),
  }));
  check(drawn.target, 'the report has target G');
  check(drawn.pictures.length === 6 && drawn.pictures.every((p) => p.width > 300 && p.height > 50 && p.paths > 0),
    `six pictures of G, each drawn with its band and line: ${JSON.stringify(drawn.pictures)}`);
  await reportTab.emulateMedia({ media: 'print' });
  const printed = await reportTab.evaluate(() => ({
    margin: getComputedStyle(document.body).marginTop,
    figures: [...document.querySelectorAll('figure')].map((f) => ({
      whole: getComputedStyle(f).breakInside === 'avoid',
      height: f.getBoundingClientRect().height,
    })),
  }));
  check(printed.margin === '0px', `printed, the page has no margin of its own: ${printed.margin}`);
  // A4 at 96 px an inch, less the browser's default margins: about 1040 px.
  check(printed.figures.length === 6 && printed.figures.every((f) => f.whole && f.height < 1000),
    `printed, each picture is kept whole and fits a page: ${JSON.stringify(printed.figures)}`);
  const pdf = await reportTab.pdf({ format: 'A4' });
  const pages = (pdf.toString('latin1').match(/\/Type\s*\/Page[^s]/g) || []).length;
  check(pdf.subarray(0, 5).toString() === '%PDF-' && pages >= 2, `it prints to a PDF of ${pages} A4 pages`);
  check(reportProblems.length === 0, `the report's tab reports no problem: ${reportProblems.join(' | ')}`);
  await reportTab.close();

  await page.click('#reference-submit');
  await page.waitForFunction(() => document.getElementById('reference-result').textContent.startsWith('Refused'), null, { timeout: 10000 });
  const refused = await page.textContent('#reference-result');
  check(refused.includes('admin scope'), `a read token cannot set the reference, and the page says why: "${refused}"`);

  const unexpected = problems.filter((p) => !/status of 40[13]/.test(p));
  check(unexpected.length === 0, `no console errors but the 401 and 403 answers: ${unexpected.join(' | ')}`);
});
