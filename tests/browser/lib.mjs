// What the browser scripts share: Chromium started headless for this machine's closed network,
// a check that logs and throws, and the console problems a page reports.
import { chromium } from 'playwright-core';

export async function launch() {
  return chromium.launch({
    executablePath: process.env.BROKENRAY_CHROMIUM || '/usr/bin/chromium',
    args: ['--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run',
      '--disable-background-networking', '--disable-component-update', '--disable-sync'],
  });
}

export function check(ok, what) {
  if (!ok) throw new Error(what);
  console.log('browser: ok -', what);
}

// Collects console errors and warnings and uncaught exceptions of a page.
export function watch(page) {
  const problems = [];
  page.on('console', (m) => {
    if (m.type() === 'error' || m.type() === 'warning') problems.push(`console ${m.type()}: ${m.text()}`);
  });
  page.on('pageerror', (e) => problems.push('page error: ' + e.message));
  return problems;
}

// Runs `body(browser)`, closes the browser, and sets the exit status.
export async function run(body) {
  const browser = await launch();
  try {
    await body(browser);
    console.log('browser: all checks passed');
  } catch (e) {
    console.error('browser: FAILED -', e.message);
    process.exitCode = 1;
  } finally {
    await browser.close();
  }
}
