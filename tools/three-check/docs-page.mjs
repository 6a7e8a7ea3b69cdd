// Open `lsgan serve`'s /docs in headless Chromium with no network beyond the server, and print what it shows as
// one JSON object.
//
//   node docs-page.mjs --url http://127.0.0.1:8000/docs [--api-key KEY] [--timeout 60] [--chromium PATH]
//
// Every request to another origin is aborted (and listed in "outside_requests"), so a page that needs a CDN stays
// blank. It waits for Swagger UI to render the schema's title and operations, then reports them, whether an
// Authorize button is there and, with --api-key, the status of GET /v1/info sent from the page with the key
// entered through that button ("Try it out" -> "Execute"). The exit status is 0 when "problems" is empty.
import { openPage } from './browser.mjs';

function parseArgs(argv) {
  const opts = { timeout: 60, chromium: process.env.CHROMIUM || '/usr/bin/chromium' };
  const keys = { '--url': 'url', '--api-key': 'apiKey', '--timeout': 'timeout', '--chromium': 'chromium' };
  for (let i = 0; i < argv.length; i += 2) {
    const key = keys[argv[i]];
    if (!key || i + 1 >= argv.length) throw new Error(`bad argument ${argv[i]}`);
    opts[key] = argv[i + 1];
  }
  if (!opts.url) throw new Error('--url is required');
  opts.timeout = Number(opts.timeout);
  opts.origin = new URL(opts.url).origin;
  return opts;
}

async function run(opts, report) {
  const { browser, page } = await openPage(opts, 1280, 900);
  try {
    await page.route('**/*', (route) => {
      const url = route.request().url();
      if (new URL(url).origin === opts.origin) return route.continue();
      report.outside_requests.push(url);
      return route.abort();
    });
    page.on('pageerror', (err) => report.page_errors.push(err.message));
    await page.goto(opts.url, { waitUntil: 'load' });
    await page.waitForSelector('.swagger-ui .info .title');
    report.title = (await page.textContent('.swagger-ui .info .title')).trim();
    report.operations = await page.$$eval('.opblock-summary-path', (els) => els.map((e) => e.textContent.trim()));
    report.authorize = (await page.$('.btn.authorize')) !== null;
    if (opts.apiKey && report.authorize) {
      await page.click('.btn.authorize');
      const field = page.locator('.auth-container input').first();
      await field.fill(opts.apiKey);
      await page.locator('.auth-container .btn.modal-btn.auth').first().click();
      await page.click('.btn-done');
      const info = page.locator('.opblock', { hasText: '/v1/info' }).first();
      await info.locator('.opblock-summary').click();
      await info.locator('.try-out__btn').click();
      const answer = page.waitForResponse((res) => res.url().endsWith('/v1/info'));
      await info.locator('.execute').click();
      report.info_status = (await answer).status();
    }
  } finally {
    await browser.close();
  }
}

const report = { title: null, operations: [], authorize: false, info_status: null, outside_requests: [],
  page_errors: [], problems: [] };
try {
  const opts = parseArgs(process.argv.slice(2));
  await run(opts, report);
  if (!report.title) report.problems.push('no title rendered');
  if (report.outside_requests.length) report.problems.push('requests outside the server');
  if (opts.apiKey && report.info_status !== 200) report.problems.push(`GET /v1/info with the key: ${report.info_status}`);
} catch (err) {
  report.problems.push(err.message.split('\n')[0]);
}
console.log(JSON.stringify(report));
process.exit(report.problems.length ? 1 : 0);
