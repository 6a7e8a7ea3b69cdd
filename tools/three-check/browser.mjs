// Debian's Chromium started headless by playwright-core, as check.mjs and serve-page.mjs both need it.
import fs from 'node:fs';
import { chromium } from 'playwright-core';

// Headless without GPU or network: no sandbox (root in CI), software WebGL (SwiftShader), and none of the
// background services that would try connections the CI network refuses.
const CHROMIUM_ARGS = [
  '--headless', '--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run',
  '--disable-background-networking', '--disable-component-update', '--disable-sync',
  '--use-angle=swiftshader', '--enable-unsafe-swiftshader',
];

// A browser (closed by the caller's cleanup) and one page of width x height with the run's timeout.
export async function openPage(opts, width, height) {
  if (!fs.existsSync(opts.chromium)) {
    throw new Error(`no Chromium at ${opts.chromium}: install it with \`apt-get install -y chromium chromium-driver\``);
  }
  let browser;
  try {
    browser = await chromium.launch({ executablePath: opts.chromium, headless: true, args: CHROMIUM_ARGS,
      timeout: opts.timeout * 1000 });
  } catch (err) {
    throw new Error(`could not start Chromium (${opts.chromium}): ${err.message}`);
  }
  const page = await browser.newPage({ viewport: { width, height } });
  page.setDefaultTimeout(opts.timeout * 1000);
  return { browser, page };
}
