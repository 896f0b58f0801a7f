// The dashboard in a real browser (Debian's chromium driven by playwright-core):
// the empty state, two robots streaming the real TUM clip through the real client,
// live rows, the map and trajectory drawn, disconnected rows after the streams
// end, and a screenshot. Run by tests/tests/dashboard.rs, which starts the server.
//
// node dashboard.mjs <http base> <grpc url> <client binary> <tum dir> <dashboard dir> <screenshot>

import { createRequire } from "node:module";
import { spawn } from "node:child_process";
import { readFileSync, rmSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";

const [base, grpc, clientBin, tumDir, dashboardDir, screenshot] = process.argv.slice(2);
const require = createRequire(join(dashboardDir, "package.json"));
const { chromium } = require("playwright-core");

function fail(message) {
  console.error(`dashboard test: ${message}`);
  process.exit(1);
}

function stream(robot, extra) {
  const summary = join(tmpdir(), `stillmap-dashboard-${process.pid}-${robot}.json`);
  const args = ["stream", "--source", `tum:${tumDir}`, "--server", grpc, "--robot-id", robot, "--quiet", "--summary-json", summary, ...extra];
  return new Promise((resolve, reject) => {
    const child = spawn(clientBin, args, { stdio: ["ignore", "ignore", "inherit"], env: { ...process.env, STILLMAP_LOG: "warn" } });
    child.on("exit", (code) => {
      if (code !== 0) return reject(new Error(`client ${robot} exited with ${code}`));
      const s = JSON.parse(readFileSync(summary, "utf8"));
      rmSync(summary, { force: true });
      resolve(s);
    });
  });
}

const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
  headless: true,
  args: ["--no-sandbox", "--disable-background-networking", "--disable-dev-shm-usage", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
});
try {
  const page = await browser.newPage({ viewport: { width: 1600, height: 1200 } });
  const errors = [];
  page.on("pageerror", (e) => errors.push(e.message));
  await page.goto(base);

  // An empty server says how to start a robot.
  await page.waitForSelector("#empty:not([hidden])", { timeout: 10000 });
  const empty = await page.textContent("#empty");
  if (!empty.includes("No robots yet")) fail(`empty state says ${JSON.stringify(empty)}`);

  // Two robots at once: the full clip, and a short run of 40 frames.
  const [a, b] = await Promise.all([stream("robot-a", ["--rate", "max"]), stream("robot-b", ["--max-frames", "40"])]);
  const rowA = `tr[data-session="${a.session_id}"]`;
  const rowB = `tr[data-session="${b.session_id}"]`;
  await page.waitForFunction(
    ([ra, rb]) => document.querySelector(`${ra} .frames`)?.textContent === "150" && document.querySelector(`${rb} .frames`)?.textContent === "40",
    [rowA, rowB],
    { timeout: 30000 },
  );
  // Streams that ended show as disconnected, not frozen.
  await page.waitForFunction(
    ([ra, rb]) => [ra, rb].every((r) => document.querySelector(`${r} .link`)?.textContent.includes("disconnected")),
    [rowA, rowB],
    { timeout: 15000 },
  );
  // At 1400 px the sessions table fits: no horizontal scrolling, the map column in view.
  await page.setViewportSize({ width: 1400, height: 1000 });
  const fit = await page.evaluate((ra) => {
    const section = document.querySelector("#sessions");
    const map = document.querySelector(`${ra} .map`).getBoundingClientRect();
    return { scroll: section.scrollWidth, client: section.clientWidth, mapRight: map.right, sectionRight: section.getBoundingClientRect().right };
  }, rowA);
  if (fit.scroll > fit.client + 1 || fit.mapRight > fit.sectionRight) fail(`the sessions table overflows at 1400 px: ${JSON.stringify(fit)}`);
  await page.setViewportSize({ width: 1600, height: 1200 });
  // Finished sessions show their last frame's latencies, never an empty sparkline.
  const cell = await page.evaluate((ra) => {
    const td = document.querySelector(`${ra} td.sparks`);
    return { text: td.textContent, empty: [...td.querySelectorAll("svg")].filter((g) => !g.children.length).length };
  }, rowA);
  if (!cell.text.includes("last frame:") || !cell.text.includes("total") || cell.empty) fail(`finished session's latency cell: ${JSON.stringify(cell)}`);

  // The first session is selected: its map tiles, trajectory and cloud get drawn.
  await page.click(rowA);
  await page.waitForFunction(() => window.__stillmap.tilesDrawn > 0 && window.__stillmap.trajectoryPoints >= 100 && window.__stillmap.cloudPoints > 1000, null, { timeout: 30000 });
  // Map pixels that differ from the background (#0c1014). The map lane may still be
  // committing versions after the streams end (its tiles then reload): wait for it.
  const mapPixels = () => {
    const c = document.querySelector("#map2d");
    const px = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
    let n = 0;
    for (let i = 0; i < px.length; i += 4) if (Math.abs(px[i] - 12) + Math.abs(px[i + 1] - 16) + Math.abs(px[i + 2] - 20) > 30) n++;
    return n;
  };
  try {
    await page.waitForFunction(`(${mapPixels.toString()})() >= 2000`, null, { timeout: 15000 });
  } catch {
    fail(`only ${await page.evaluate(mapPixels)} map pixels differ from the background`);
  }
  const drawn = await page.evaluate(mapPixels);
  // The trajectory stays visible at every zoom: fitted, and zoomed all the way out
  // (the clip moves a few centimetres: a ring marks it), then fitted again.
  const trailPixels = () => {
    const c = document.querySelector("#map2d");
    const px = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
    let n = 0;
    for (let i = 0; i < px.length; i += 4) if (Math.abs(px[i] - 255) + Math.abs(px[i + 1] - 176) + px[i + 2] < 60) n++;
    return n;
  };
  const trailFitted = await page.evaluate(trailPixels);
  const box = await page.locator("#map2d").boundingBox();
  await page.mouse.move(box.x + box.width / 2, box.y + box.height / 2);
  for (let k = 0; k < 12; k++) await page.mouse.wheel(0, 400);
  await page.waitForTimeout(300);
  const trailOut = await page.evaluate(trailPixels);
  if (trailFitted < 30 || trailOut < 30) fail(`trajectory pixels: ${trailFitted} fitted, ${trailOut} zoomed out`);
  await page.dblclick("#map2d");
  // The default fleet: its anchor (the first robot) drawn with its whole trajectory
  // over the fleet map's tiles.
  await page.waitForFunction(() => window.__stillmap.fleets >= 1 && window.__stillmap.fleetRobots >= 1 && window.__stillmap.fleetPoints >= 100 && window.__stillmap.fleetTilesDrawn >= 1, null, { timeout: 30000 });
  const fleetText = await page.textContent("#fleets");
  if (!fleetText.includes("default") || !fleetText.includes("(anchor)")) fail(`fleet view says ${JSON.stringify(fleetText)}`);
  const legend = await page.$$eval("#legend label", (ls) => ls.map((l) => l.textContent.trim()));
  if (!legend.some((l) => l.startsWith("unlabelled"))) fail(`legend ${JSON.stringify(legend)}`);
  await page.screenshot({ path: screenshot, fullPage: true });
  if (errors.length) fail(`page errors: ${errors.join("; ")}`);
  const fleet = await page.evaluate(() => ({ robots: window.__stillmap.fleetRobots, points: window.__stillmap.fleetPoints, tiles: window.__stillmap.fleetTilesDrawn }));
  console.log(JSON.stringify({ ok: true, drawn, trail: [trailFitted, trailOut], legend: legend.length, fleet, sessions: [a.session_id, b.session_id], screenshot }));
} finally {
  await browser.close();
}
