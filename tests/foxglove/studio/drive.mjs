// Drives Foxglove Studio 1.48 (tests/foxglove/studio/index.html, served by the test) in
// headless chromium and says what the app shows: its topics with their schemas, the
// problems it reports, and screenshots of its panels paused at a time, after a seek while
// paused, and while playing.  node drive.mjs '{"url": ..., "seek": "...", "out": DIR}'
// Optional: "settingsOf": a panel id (e.g. "3D!arm"): at the end, that panel's settings
// opened, every node expanded, and the errors the panel shows on them (a URDF that does not
// parse, a missing transform, ...) listed in "settingsErrors" as {node, error}.  The app's
// console warnings and errors are in "warnings" (a 3D panel logs each of its layer errors
// once, as "[path > to > node] message", even when it later clears it).
// playwright-core comes from make foxglove-studio's node_modules (STUDIO_NODE_MODULES).
import { createRequire } from "module";
import fs from "fs";

const require = createRequire(`${process.env.STUDIO_NODE_MODULES}/`);
const { chromium } = require("playwright-core");
const args = JSON.parse(process.argv[2]);
fs.mkdirSync(args.out, { recursive: true });
const log = [];
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium", headless: true,
  // software WebGL: the machines this runs on have no GPU
  args: ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"],
});
const result = { topics: [], problems: [], shots: {}, seek: null };
try {
  const page = await browser.newPage({ viewport: { width: 1600, height: 1000 } });
  page.on("console", (m) => log.push(`[${m.type()}] ${m.text()}`));
  page.on("pageerror", (e) => log.push(`[pageerror] ${e}`));
  page.on("response", (r) => { if (r.status() >= 400) log.push(`[http ${r.status()}] ${r.url()}`); });
  await page.goto(args.url, { waitUntil: "load" });
  const panel = (id) => page.locator(`[data-testid="panel-mouseenter-container ${id}"]`);
  const shots = async (tag, panels = [["3d", "3D!arm"], ["plot", "Plot!wrench"], ["phase", "StateTransitions!phase"]]) => {
    for (const [name, id] of panels) {
      const file = `${args.out}/${tag}-${name}.png`;
      await panel(id).screenshot({ path: file });
      result.shots[`${tag}-${name}`] = file;
    }
  };
  const tab = async (name) => {
    if (!(await page.locator('button[data-sidebar-key="connection"][aria-selected="true"]').count()))
      await page.click('button[data-sidebar-key="connection"]');
    await page.locator('[role="tablist"] button[role="tab"]', { hasText: name }).first().click();
    await page.waitForTimeout(300);
  };
  const topics = () => page.$$eval("li.MuiListItem-root", (lis) => lis
    .filter((li) => li.querySelector("[data-topic]"))
    .map((li) => ({ topic: li.querySelector(".MuiListItemText-primary")?.textContent,
                    schema: li.querySelector(".MuiListItemText-secondary")?.textContent })));
  const problems = async () => {
    await tab("Problems");
    result.problemBadge = await page.locator('button[data-sidebar-key="connection"] .MuiBadge-badge')
      .textContent({ timeout: 1000 }).catch(() => "");
    result.problems = await page.$$eval("li .MuiListItemText-primary", (es) => es.map((e) => e.textContent));
    await tab("Topics");
  };

  if (args.live) {
    // a live connection (retried by the app until the run's bridge listens): wait for the
    // visual topics, let the 3D panel draw what arrives, and look while the run goes on
    await page.waitForSelector('[data-testid="panel-mouseenter-container 3D!arm"] canvas', { timeout: 90000 });
    await tab("Topics");
    console.log("LOADED");  // the test starts the run now: the app is up, retrying its connection
    const deadline = Date.now() + args.live.timeout_ms;
    const loaded = Date.now();
    while (Date.now() < deadline && (result.topics = await topics()).length < args.live.topics)
      await page.waitForTimeout(500);
    result.listedAfterMs = Date.now() - loaded;  // how long the app took to connect and list them
    await page.waitForTimeout(args.live.draw_ms);
    await shots("live", [["3d", "3D!arm"]]);
    await page.screenshot({ path: `${args.out}/live-page.png` });
    await problems();
  } else {
    await page.waitForSelector('[data-topic-stat="count"]', { timeout: 90000 });
    await page.waitForSelector('[data-testid="panel-mouseenter-container 3D!arm"] canvas', { timeout: 90000 });
    await page.waitForTimeout(4000);  // the panels draw what the time they opened at has

    await tab("Topics");
    result.topics = await topics();
    await problems();
    result.paused = (await page.locator('button[title="Play"]').count()) > 0;
    await shots("paused");
    await page.screenshot({ path: `${args.out}/paused-page.png` });
    // a seek while paused: the time field pauses playback when focused, Enter moves there
    const time = page.locator('[data-testid="PlaybackTime-text"] input');
    await time.click();
    await time.fill(String(args.seek));
    await time.press("Enter");
    await page.mouse.click(5, 995);
    await page.waitForTimeout(4000);
    result.seek = { requested: String(args.seek), shown: await time.inputValue(),
                    paused: (await page.locator('button[title="Play"]').count()) > 0 };
    await shots("seeked");
    await page.click('button[title="Play"]');
    await page.waitForTimeout(1500);
    await shots("playing");
    // the short recordings play to their end within those 1.5 s: then there is no Pause
    // button, and a click would wait out playwright's 30 s for one
    if (await page.locator('button[title="Pause"]').count()) await page.click('button[title="Pause"]');
  }
  if (args.settingsOf) {
    // the panel's own settings button (its toolbar shows on hover) selects it and opens the
    // "Panel settings" sidebar; an error shows as a red icon on its node, its text in a tooltip
    await page.mouse.click(5, 995);
    await panel(args.settingsOf).hover();
    await panel(args.settingsOf).locator('button[aria-label="Settings"]').first().click();
    await page.waitForSelector('[data-testid="settings-filter-field"]', { timeout: 10000 });
    const tree = page.locator(".MuiPaper-root").filter({ has: page.locator('[data-testid="settings-filter-field"]') }).last();
    for (let i = 0; i < 200; i++) {  // expand every collapsed node, the ones each reveals too
      const collapsed = tree.locator('[data-testid="ArrowRightIcon"]');
      if (!(await collapsed.count())) break;
      await collapsed.first().click();
      await page.waitForTimeout(50);
    }
    await page.waitForTimeout(500);
    result.settingsErrors = [];
    const icons = tree.locator("button.MuiIconButton-colorError");
    for (let i = 0; i < (await icons.count()); i++) {
      const icon = icons.nth(i);
      await icon.scrollIntoViewIfNeeded();
      await icon.hover();
      const tip = page.locator('[role="tooltip"]').last();
      const error = await tip.textContent({ timeout: 3000 }).catch(() => "(no tooltip)");
      const node = await icon.evaluate((b) => b.parentElement?.parentElement?.firstElementChild?.textContent ?? "");
      result.settingsErrors.push({ node, error });
      await page.mouse.move(5, 500);
      await page.waitForTimeout(300);
    }
    await page.screenshot({ path: `${args.out}/settings-page.png` });
    result.shots.settings = `${args.out}/settings-page.png`;
  }
} finally {
  result.warnings = log.filter((l) => /^\[(warning|error|pageerror|http \d+)\]/.test(l)).slice(0, 200).map((l) => l.slice(0, 600));
  fs.writeFileSync(`${args.out}/console.log`, log.join("\n"));
  fs.writeFileSync(`${args.out}/result.json`, JSON.stringify(result, null, 1));
  await browser.close();
}
console.log(JSON.stringify(result));
