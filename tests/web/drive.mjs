// Drives the coordinator's page in headless Chromium as a person would (run by
// tests/web_page.rs): sign in, submit a job from the form (a scene archive and two paintings),
// watch it finish, check that the animations and plots show, request a style-blend render.
// Saves a screenshot of each step into SHOTS and prints a JSON summary on stdout.
//
// Environment: BASE (the page's URL), TOKEN, SCENE (a .tar), STYLES (paths joined by ":"),
// OVERRIDES (JSON), SHOTS (a folder), CHROMIUM (the browser), PLAYWRIGHT (its node_modules
// folder holding playwright-core), TIMEOUT_MS (for the job to finish).
import { createRequire } from "node:module";
import path from "node:path";

const env = (name) => {
  const value = process.env[name];
  if (!value) throw new Error(`${name} is not set`);
  return value;
};
const require = createRequire(path.join(env("PLAYWRIGHT"), "noop.js"));
const { chromium } = require("playwright-core");

const shots = env("SHOTS");
const timeout = Number(env("TIMEOUT_MS"));
const browser = await chromium.launch({
  executablePath: env("CHROMIUM"),
  headless: true,
  // A sandbox needs privileges CI containers lack; these flags keep Chromium off the network.
  args: ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync"],
});
const summary = {};
try {
  const page = await browser.newPage({ viewport: { width: 1200, height: 900 } });
  const errors = [];
  page.on("pageerror", (error) => errors.push(String(error)));
  await page.goto(env("BASE"));

  // A wrong token is refused on the page, the right one signs in.
  await page.fill("#token", "not-the-token-0123456789");
  await page.click("#sign-in");
  await page.waitForSelector("text=unknown token");
  await page.fill("#token", env("TOKEN"));
  await page.click("#sign-in");
  await page.waitForSelector("#jobs");
  await page.screenshot({ path: path.join(shots, "1-jobs.png") });

  await page.click("#nav-new");
  await page.fill("#job-name", "from the browser");
  await page.selectOption("#preset", "tiny");
  await page.setInputFiles("#scene", env("SCENE"));
  await page.setInputFiles("#styles", env("STYLES").split(":"));
  await page.fill("#overrides", env("OVERRIDES"));
  await page.screenshot({ path: path.join(shots, "2-new-job.png") });
  await page.click("#submit");
  await page.waitForURL(/#\/jobs\/j-/);
  summary.jobId = page.url().split("#/jobs/")[1];

  // The job page follows the job live until it succeeds.
  await page.waitForSelector("#timeline tr[data-stage=nerf_pretrain]");
  await page.waitForSelector("#job-title .state.succeeded", { timeout });
  // Every result image loaded (the list is redrawn while polling: wait for all of them).
  await page.waitForFunction(() => {
    const imgs = [...document.querySelectorAll("#results img")];
    return imgs.length > 0 && imgs.every((img) => img.complete && img.naturalWidth > 0);
  }, null, { timeout: 30000 });
  summary.images = await page.$$eval("#results img", (imgs) =>
    imgs.filter((img) => img.complete && img.naturalWidth > 0).map((img) => img.alt));
  summary.plots = await page.$$eval("#plots svg polyline", (lines) => lines.length);
  summary.stages = await page.$$eval("#timeline tbody tr", (rows) =>
    rows.map((row) => [row.dataset.stage, row.querySelector(".state").textContent]));
  await page.screenshot({ path: path.join(shots, "3-job-finished.png"), fullPage: true });

  // A blend of the two paintings is requested from the slider.
  await page.$eval("#blend", (slider) => {
    slider.value = "30";
    slider.dispatchEvent(new Event("input"));
  });
  await page.click("#render-blend");
  await page.waitForSelector("text=/render task \\d+ queued/");
  summary.blendRequested = true;
  // The page follows the job again and shows the blend's animation when it is done.
  await page.waitForFunction(() => document.querySelectorAll("#results img[alt$='animation.gif']").length >= 3,
    null, { timeout });
  await page.waitForSelector("#job-title .state.succeeded", { timeout });
  summary.animationsAfterBlend = await page.$$eval("#results img[alt$='animation.gif']", (imgs) => imgs.map((img) => img.alt));
  await page.screenshot({ path: path.join(shots, "4-blend-requested.png"), fullPage: true });
  summary.pageErrors = errors;
} finally {
  await browser.close();
}
console.log(JSON.stringify(summary));
