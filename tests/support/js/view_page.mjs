// Looks at pages as a person would: headless Chromium (Debian's, through playwright-core)
// opens each URL given, waits until it has loaded, and prints one JSON object per page:
// every image with whether it loaded (complete, natural size > 0), the text of an element
// (argument --text SELECTOR, e.g. .verdict) with whether it is visible, and a screenshot's
// path (--shot DIR). tests/daemon/worker/test_report_view.py runs it.
import { chromium } from "playwright-core";

const args = process.argv.slice(2);
let selector = null;
let shots = null;
const urls = [];
for (let i = 0; i < args.length; i++) {
  if (args[i] === "--text") selector = args[++i];
  else if (args[i] === "--shot") shots = args[++i];
  else urls.push(args[i]);
}
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
  args: ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync"],
});
try {
  const page = await browser.newPage({ viewport: { width: 1200, height: 900 } });
  for (const [k, url] of urls.entries()) {
    const response = await page.goto(url, { waitUntil: "load" });
    const images = await page.$$eval("img", (imgs) =>
      imgs.map((i) => ({ src: i.getAttribute("src"), loaded: i.complete && i.naturalWidth > 0,
                         width: i.naturalWidth, height: i.naturalHeight })));
    let text = null;
    let visible = null;
    if (selector) {
      const el = await page.$(selector);
      if (el) {
        text = (await el.innerText()).trim();
        visible = await el.isVisible();
      }
    }
    let shot = null;
    if (shots) {
      shot = `${shots}/page-${k}.png`;
      await page.screenshot({ path: shot, fullPage: true });
    }
    console.log(JSON.stringify({ url, ok: response ? response.ok() : true, images, text,
                                 visible, shot }));
  }
} finally {
  await browser.close();
}
