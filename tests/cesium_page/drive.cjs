// Headless Chromium (Debian's, software WebGL) opens the page at argv[2], waits for window.splatResult and
// writes a screenshot of the page to argv[3]; prints the result as JSON. Every request that does not go to a
// loopback address is refused, so nothing leaves the machine. Run with NODE_PATH pointing at .ci/node/node_modules.
"use strict";
const fs = require("fs");
const os = require("os");
const path = require("path");
const { chromium } = require("playwright-core");

async function main() {
  const [url, out, size = "640x480", executable = "/usr/bin/chromium"] = process.argv.slice(2);
  const [width, height] = size.split("x").map(Number);
  const profile = fs.mkdtempSync(path.join(os.tmpdir(), "splat-chromium-"));
  const logs = [];
  const fetched = [];  // the paths of every loopback request (which tileset JSONs and contents were read)
  let context;
  try {
    context = await chromium.launchPersistentContext(profile, {
      executablePath: executable, headless: true, viewport: { width, height }, deviceScaleFactor: 1,
      args: ["--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
             "--disable-background-networking", "--disable-component-update", "--no-first-run",
             "--disable-default-apps", "--disable-sync", "--mute-audio"],
    });
    const page = context.pages()[0] || await context.newPage();
    await page.route("**/*", (route) => {
      const host = new URL(route.request().url()).hostname;
      if (host === "127.0.0.1" || host === "localhost" || host === "[::1]") {
        fetched.push(new URL(route.request().url()).pathname);
        return route.continue();
      }
      logs.push(`refused ${route.request().url()}`);
      return route.abort();
    });
    page.on("console", (m) => logs.push(`console.${m.type()}: ${m.text()}`));
    page.on("pageerror", (e) => logs.push(`pageerror: ${e}`));
    // No step has a clock of its own (timeout 0): under load a software-rendered page once took over Playwright's
    // default 30 s for one screenshot (the suite beside a CPU burner, issue 34). Each step waits for its event; the
    // test's guard on the whole driver (tests/browser.py shoot) is what ends a page that hangs.
    page.setDefaultTimeout(0);
    await page.goto(url, { waitUntil: "load", timeout: 0 });
    await page.waitForFunction(() => window.splatResult !== undefined, null, { timeout: 0, polling: 250 });
    const result = await page.evaluate(() => window.splatResult);
    await page.screenshot({ path: out, timeout: 0 });
    const gl = await page.evaluate(() => {
      const c = document.createElement("canvas").getContext("webgl2");
      const ext = c && c.getExtension("WEBGL_debug_renderer_info");
      return c ? String(ext ? c.getParameter(ext.UNMASKED_RENDERER_WEBGL) : c.getParameter(c.RENDERER)) : "none";
    });
    console.log(JSON.stringify({ result, gl, logs, fetched }));
  } catch (e) {
    console.log(JSON.stringify({ result: { status: "driver-error", error: String(e) }, logs }));
    process.exitCode = 1;
  } finally {
    if (context) await context.close();
    fs.rmSync(profile, { recursive: true, force: true });
  }
}

main();
