// The dashboard on a service with tokens: it asks for one, sends it with every call and with
// the event stream, and says so when the token lacks the admin scope.
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
  const page = await browser.newPage({ viewport: { width: 1280, height: 900 } });
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

  await page.click('#reference-submit');
  await page.waitForFunction(() => document.getElementById('reference-result').textContent.startsWith('Refused'), null, { timeout: 10000 });
  const refused = await page.textContent('#reference-result');
  check(refused.includes('admin scope'), `a read token cannot set the reference, and the page says why: "${refused}"`);

  const unexpected = problems.filter((p) => !/status of 40[13]/.test(p));
  check(unexpected.length === 0, `no console errors but the 401 and 403 answers: ${unexpected.join(' | ')}`);
});
