// The coordinator's page: sign in with a client token, list jobs, watch one (stage timeline,
// progress, loss/PSNR plots, contact sheets and animations, a style-blend render), submit a
// job. It talks only to this origin: POST /stylenerf.v1.JobService/<Method> (proto JSON) and
// POST /upload. Text from the server is only ever set as text, never parsed as HTML.
"use strict";

const TOKEN_KEY = "stylenerf-token";
const POLL_MS = 1500;
let timer = null;

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(attrs)) {
    if (name === "class") node.className = value;
    else if (name.startsWith("on")) node.addEventListener(name.slice(2), value);
    else if (value !== false && value !== undefined) node.setAttribute(name, value === true ? "" : value);
  }
  for (const child of children.flat()) {
    if (child !== null && child !== undefined) node.append(child instanceof Node ? child : String(child));
  }
  return node;
}

function svg(tag, attrs = {}) {
  const node = document.createElementNS("http://www.w3.org/2000/svg", tag);
  for (const [name, value] of Object.entries(attrs)) node.setAttribute(name, value);
  return node;
}

const token = () => sessionStorage.getItem(TOKEN_KEY);

class ApiError extends Error {
  constructor(status, body) {
    const fields = (body.violations || []).map((v) => `${v.field}: ${v.description}`);
    super(fields.length ? fields.join("\n") : body.message || `HTTP ${status}`);
    this.status = status;
    this.code = body.code;
  }
}

async function answer(response) {
  const body = await response.json().catch(() => ({ message: `HTTP ${response.status}` }));
  if (response.status === 401) {
    sessionStorage.removeItem(TOKEN_KEY);
  }
  if (!response.ok) throw new ApiError(response.status, body);
  return body;
}

async function rpc(method, request = {}) {
  const response = await fetch(`/stylenerf.v1.JobService/${method}`, {
    method: "POST",
    headers: { "content-type": "application/json", authorization: `Bearer ${token()}` },
    body: JSON.stringify(request),
  });
  return answer(response);
}

async function sha256(file) {
  if (!crypto.subtle) return null; // not a secure context: the server hashes alone
  const digest = await crypto.subtle.digest("SHA-256", await file.arrayBuffer());
  return [...new Uint8Array(digest)].map((b) => b.toString(16).padStart(2, "0")).join("");
}

async function upload(kind, file) {
  const headers = { authorization: `Bearer ${token()}` };
  const sum = await sha256(file);
  if (sum) headers["x-content-sha256"] = sum;
  const query = new URLSearchParams({ kind, filename: file.name });
  return answer(await fetch(`/upload?${query}`, { method: "POST", headers, body: file }));
}

const name = (enumValue, prefix) => String(enumValue || "").replace(prefix, "").toLowerCase();
const jobState = (job) => name(job.state, "JOB_STATE_");
const taskState = (task) => name(task.state, "TASK_STATE_");
const stageName = (stage) => name(stage, "STAGE_");
const ms = (value) => Number(value || 0);

function duration(seconds) {
  seconds = Math.max(0, Math.round(seconds));
  const h = Math.floor(seconds / 3600), m = Math.floor((seconds % 3600) / 60), s = seconds % 60;
  return h ? `${h}h${String(m).padStart(2, "0")}m` : m ? `${m}m${String(s).padStart(2, "0")}s` : `${s}s`;
}

const badge = (state) => el("span", { class: `state ${state}` }, state);
const terminal = (job) => ["succeeded", "failed", "cancelled"].includes(jobState(job));

function show(...nodes) {
  document.getElementById("main").replaceChildren(...nodes.filter(Boolean));
}

function failure(error) {
  return el("p", { class: "error", role: "alert" }, error.message || String(error));
}

// ---- sign in -------------------------------------------------------------------------------

function signIn(message) {
  const input = el("input", { type: "password", id: "token", autocomplete: "off", required: true });
  const status = el("p", { class: "error", role: "alert" }, message || "");
  const form = el("form", {
    onsubmit: async (event) => {
      event.preventDefault();
      sessionStorage.setItem(TOKEN_KEY, input.value.trim());
      try {
        await rpc("ListJobs", { page_size: 1 });
        route();
      } catch (error) {
        sessionStorage.removeItem(TOKEN_KEY);
        status.textContent = error.message;
      }
    },
  }, el("label", { for: "token" }, "Client token"), input,
  el("button", { class: "primary", type: "submit", id: "sign-in" }, "Sign in"), status);
  show(el("section", {}, el("h1", {}, "Sign in"),
    el("p", { class: "muted" }, "The token the coordinator's operator gave you (role client or admin). It is kept in this tab only."),
    form));
}

// ---- the job list --------------------------------------------------------------------------

async function jobList() {
  const rows = el("tbody");
  const status = el("p", { class: "muted" }, "loading…");
  show(el("section", {}, el("h1", {}, "Jobs"),
    el("table", { id: "jobs" }, el("thead", {}, el("tr", {},
      ["Name", "State", "Stages", "Preset", "Created", "Id"].map((h) => el("th", {}, h)))), rows),
    status));
  const refresh = async () => {
    try {
      const page = await rpc("ListJobs", { page_size: 100 });
      const jobs = page.jobs || [];
      rows.replaceChildren(...jobs.map((job) => {
        const done = (job.tasks || []).filter((t) => taskState(t) === "succeeded").length;
        return el("tr", { "data-job": job.id },
          el("td", {}, el("a", { href: `#/jobs/${job.id}` }, job.name || "(unnamed)")),
          el("td", {}, badge(jobState(job))),
          el("td", {}, `${done}/${(job.tasks || []).length}`),
          el("td", {}, job.preset),
          el("td", {}, new Date(ms(job.created_at_ms)).toLocaleString()),
          el("td", { class: "muted" }, job.id));
      }));
      status.textContent = jobs.length ? "" : "No jobs yet: submit one with “New job”.";
    } catch (error) {
      if (error.status === 401) return signIn(error.message);
      status.replaceChildren(failure(error));
    }
  };
  await refresh();
  timer = setInterval(refresh, POLL_MS);
}

// ---- one job -------------------------------------------------------------------------------

function timeline(job) {
  const tasks = job.tasks || [];
  const start = ms(job.created_at_ms);
  const end = Math.max(Date.now() * (terminal(job) ? 0 : 1), ms(job.finished_at_ms), ...tasks.map((t) => ms(t.finished_at_ms)), start + 1);
  const span = end - start;
  return el("table", { class: "timeline", id: "timeline" },
    el("thead", {}, el("tr", {}, ["Stage", "State", "Attempt", "Time", "Progress", ""].map((h) => el("th", {}, h)))),
    el("tbody", {}, tasks.map((task) => {
      const state = taskState(task);
      const begun = ms(task.started_at_ms);
      const ended = ms(task.finished_at_ms) || (begun ? Date.now() : 0);
      const bar = el("div", { class: "bar" });
      if (begun) {
        const piece = el("span", { class: state });
        piece.style.left = `${(100 * (begun - start)) / span}%`;
        piece.style.width = `${Math.max(0.5, (100 * (ended - begun)) / span)}%`;
        bar.append(piece);
      }
      const p = task.progress || {};
      const progress = state === "leased" && p.total
        ? `step ${p.step || 0}/${p.total} · loss ${Number(p.loss || 0).toPrecision(3)}${p.eta_seconds ? ` · ETA ${duration(p.eta_seconds)}` : ""}`
        : task.error || "";
      return el("tr", { "data-stage": stageName(task.stage) },
        el("td", {}, stageName(task.stage)), el("td", {}, badge(state)),
        el("td", {}, `${task.attempt || 0}/${task.max_attempts || 0}`),
        el("td", {}, begun ? duration((ended - begun) / 1000) : ""),
        el("td", { class: task.error ? "error" : "" }, progress), el("td", {}, bar));
    })));
}

/// One line plot of `points` ([step, value]) with its range written beside it.
function plot(title, points) {
  const box = svg("svg", { viewBox: "0 0 300 100", preserveAspectRatio: "none", role: "img", "aria-label": title });
  const xs = points.map((p) => p[0]), ys = points.map((p) => p[1]);
  const [x0, x1] = [Math.min(...xs), Math.max(...xs)], [y0, y1] = [Math.min(...ys), Math.max(...ys)];
  const line = points.map(([x, y]) => `${(300 * (x - x0)) / (x1 - x0 || 1)},${96 - (92 * (y - y0)) / (y1 - y0 || 1)}`);
  box.append(svg("polyline", { points: line.join(" "), "vector-effect": "non-scaling-stroke" }));
  return el("figure", { class: "plot" }, el("h2", {}, title), box,
    el("figcaption", { class: "muted" }, `${points.length} points · ${y0.toPrecision(4)} … ${y1.toPrecision(4)} over steps ${x0}–${x1}`));
}

function plots(events) {
  const series = new Map();
  for (const event of events) {
    const p = event.progress;
    // Before its first step a stage has measured nothing (its loss reads 0).
    if (!p || !Number(p.step)) continue;
    const stage = stageName(event.stage);
    const add = (what, value) => {
      if (!Number.isFinite(value)) return;
      const key = `${stage} ${what}`;
      if (!series.has(key)) series.set(key, []);
      series.get(key).push([Number(p.step), value]);
    };
    if (p.loss !== undefined) add("loss", Number(p.loss));
    if (p.metrics && p.metrics.psnr !== undefined) add("PSNR (dB)", Number(p.metrics.psnr));
  }
  // A curve needs two points; a constant one (a render stage's) says nothing.
  const figures = [...series]
    .filter(([, points]) => points.length >= 2 && points.some(([, y]) => y !== points[0][1]))
    .map(([title, points]) => plot(title, points));
  return el("div", { class: "plots", id: "plots" },
    figures.length ? figures : el("p", { class: "muted" }, "Loss and PSNR appear here as the stages report progress."));
}

async function results(job, urls) {
  const artifacts = (await rpc("ListArtifacts", { job_id: job.id })).artifacts || [];
  const shown = artifacts.filter((a) => /\/(sheet\.png|animation\.gif|animation\.mp4|curves\.png)$/.test(a.key));
  const figures = [];
  for (const artifact of shown) {
    if (!urls.has(artifact.key)) {
      urls.set(artifact.key, (await rpc("GetArtifactUrl", { job_id: job.id, key: artifact.key })).url);
    }
    const url = urls.get(artifact.key);
    const label = artifact.key.replace(`jobs/${job.id}/`, "");
    const media = artifact.key.endsWith(".mp4")
      ? el("video", { src: url, controls: true, loop: true, muted: true })
      : el("img", { src: url, alt: label, class: label.endsWith("curves.png") ? "chart" : "render" });
    figures.push(el("figure", {}, media, el("figcaption", { class: "muted" }, label)));
  }
  return el("div", { class: "results", id: "results" },
    figures.length ? figures : el("p", { class: "muted" }, "Contact sheets and animations appear here when render_stylized has run."));
}

/// The blend slider; `queued` is called once a render is queued (the page then follows the job
/// again until the render's animation is in).
function blendForm(job, queued) {
  const styles = job.style_keys || [];
  const mutual = (job.tasks || []).find((t) => stageName(t.stage) === "mutual_learning");
  if (styles.length < 2 || !mutual || taskState(mutual) !== "succeeded") return null;
  const slider = el("input", { type: "range", min: 0, max: 100, value: 50, id: "blend" });
  const label = el("span", {}, "50 % / 50 %");
  const status = el("p", { class: "muted", role: "status" });
  slider.addEventListener("input", () => { label.textContent = `${100 - slider.value} % / ${slider.value} %`; });
  const button = el("button", {
    class: "primary", type: "button", id: "render-blend",
    onclick: async () => {
      button.disabled = true;
      const t = Number(slider.value) / 100;
      try {
        const task = await rpc("RenderJob", {
          job_id: job.id,
          style_blend: [{ style_index: 0, weight: 1 - t }, { style_index: 1, weight: t }],
        });
        status.textContent = `render task ${task.id} queued; its animation appears below when it is done`;
        queued();
      } catch (error) {
        status.replaceChildren(failure(error));
      } finally {
        button.disabled = false;
      }
    },
  }, "Render this blend");
  return el("section", {}, el("h2", {}, "Blend the first two styles"),
    el("div", { class: "blend" }, el("span", {}, "style 0"), slider, el("span", {}, "style 1"), label), button, status);
}

async function jobView(id) {
  const header = el("div");
  const body = el("div");
  const status = el("p", { class: "muted" });
  show(el("section", {}, header, status), body);
  const urls = new Map();
  // Made once, then kept across redraws (its slider position and status stay).
  let blend = null;
  let events = [];
  let after = 0;
  let finalShown = false;
  const refresh = async () => {
    try {
      const job = await rpc("GetJob", { job_id: id });
      for (;;) {
        const page = (await rpc("ListEvents", { job_id: id, after_seq: after })).events || [];
        events = events.concat(page);
        if (page.length) after = Number(page[page.length - 1].seq);
        if (page.length < 5000) break;
      }
      const elapsed = ((ms(job.finished_at_ms) || Date.now()) - ms(job.created_at_ms)) / 1000;
      const cancel = terminal(job) ? null : el("button", {
        type: "button", id: "cancel",
        onclick: () => rpc("CancelJob", { job_id: id }).catch((e) => status.replaceChildren(failure(e))),
      }, "Cancel");
      header.replaceChildren(...[el("h1", { id: "job-title" }, job.name || job.id, " ", badge(jobState(job))),
        el("p", { class: "muted" }, `${job.id} · preset ${job.preset} · ${(job.style_keys || []).length} styles · ${duration(elapsed)} since submission`),
        job.error ? el("p", { class: "error" }, job.error) : null, cancel].filter(Boolean));
      blend = blend || blendForm(job, () => {
        finalShown = false;
        if (!timer) timer = setInterval(refresh, POLL_MS);
      });
      const parts = [el("section", {}, el("h2", {}, "Stages"), timeline(job)),
        el("section", {}, el("h2", {}, "Training curves"), plots(events)),
        blend,
        el("section", {}, el("h2", {}, "Results"), await results(job, urls))];
      body.replaceChildren(...parts.filter(Boolean));
      status.textContent = "";
      // A finished job is drawn once more (its last artifacts), then no longer polled, unless
      // a render was requested (the job runs again).
      if (terminal(job)) {
        if (finalShown) { clearInterval(timer); timer = null; }
        finalShown = true;
      } else {
        finalShown = false;
      }
    } catch (error) {
      if (error.status === 401) return signIn(error.message);
      status.replaceChildren(failure(error));
    }
  };
  await refresh();
  timer = setInterval(refresh, POLL_MS);
}

// ---- a new job -----------------------------------------------------------------------------

function newJob() {
  const field = (label, input) => [el("label", { for: input.id }, label), input];
  const jobName = el("input", { type: "text", id: "job-name", maxlength: 200 });
  const preset = el("select", { id: "preset" }, ["tiny", "quick", "standard", "paper"].map((p) => el("option", { value: p, selected: p === "quick" }, p)));
  const sceneKind = el("select", { id: "scene-kind" }, [
    el("option", { value: "DATASET_ARCHIVE", selected: true }, "a posed dataset: an uncompressed .tar of a nerfstudio, Blender or LLFF folder"),
    el("option", { value: "PHOTOS" }, "plain photos (an uncompressed .tar of a folder of them) or a video: camera poses are recovered first"),
  ]);
  const scene = el("input", { type: "file", id: "scene", accept: ".tar,application/x-tar,video/*", required: true });
  const styles = el("input", { type: "file", id: "styles", accept: "image/png,image/jpeg,image/gif,image/webp", multiple: true, required: true });
  const overrides = el("textarea", { id: "overrides", rows: 2, placeholder: '{"nerf_pretrain.steps": 500}' });
  const status = el("p", { class: "muted", role: "status" });
  const submit = el("button", { class: "primary", type: "submit", id: "submit" }, "Submit");
  const form = el("form", {
    onsubmit: async (event) => {
      event.preventDefault();
      submit.disabled = true;
      try {
        status.textContent = `uploading ${scene.files[0].name}…`;
        const dataset = await upload(sceneKind.value, scene.files[0]);
        const refs = [];
        for (const file of styles.files) {
          status.textContent = `uploading ${file.name}…`;
          refs.push({ upload_id: (await upload("STYLE_IMAGE", file)).upload_id });
        }
        status.textContent = "creating the job…";
        const created = await rpc("CreateJob", {
          name: jobName.value, preset: preset.value,
          dataset: { upload_id: dataset.upload_id }, styles: refs,
          config_overrides_json: overrides.value.trim(),
        });
        location.hash = `#/jobs/${created.job.id}`;
      } catch (error) {
        if (error.status === 401) return signIn(error.message);
        status.replaceChildren(failure(error));
      } finally {
        submit.disabled = false;
      }
    },
  }, field("Name", jobName), field("Preset", preset),
  field("Scene is", sceneKind), field("Scene file", scene),
  field("Paintings (one or more images)", styles),
  field("Overrides (optional JSON)", overrides), submit, status);
  show(el("section", {}, el("h1", {}, "New job"), form));
}

// ---- routing -------------------------------------------------------------------------------

function route() {
  if (timer) { clearInterval(timer); timer = null; }
  document.getElementById("sign-out").hidden = !token();
  if (!token()) return signIn();
  const hash = location.hash || "#/";
  const job = hash.match(/^#\/jobs\/([\w-]+)$/);
  if (job) return jobView(job[1]);
  if (hash === "#/new") return newJob();
  return jobList();
}

window.addEventListener("hashchange", route);
window.addEventListener("DOMContentLoaded", () => {
  document.getElementById("sign-out").addEventListener("click", () => {
    sessionStorage.removeItem(TOKEN_KEY);
    route();
  });
  route();
});
