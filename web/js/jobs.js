// Jobs view: the caller's jobs with state, stage and live progress (polled every 2 s), and the
// actions that make sense in each state. Rows are updated in place so keyboard focus stays put.

import { $ } from "./dom.js";
import { api } from "./api.js";
import { decimal } from "./format.js";

const POLL_MS = 2000;
const FINISHED = new Set(["succeeded", "failed", "cancelled"]);

export const jobs = new Map(); // id -> the latest JobOut
const sceneNames = new Map(); // scene id -> the name given at upload
const rows = new Map(); // id -> {tr, state}
let actions = {};
let timer = null;

const isFinished = (job) => FINISHED.has(job.state);
export const shortId = (id) => id.slice(0, 8);
export const describeJob = (job) => `${job.type} ${shortId(job.id)}`;

/** What a job continues: its scene (by the name given at upload), or its parent job. */
function origin(job) {
  if (job.scene_id) return `scene ${sceneNames.get(job.scene_id) || shortId(job.scene_id)}`;
  const parent = jobs.get(job.parent_job_id);
  return `after ${parent ? describeJob(parent) : shortId(job.parent_job_id)}`;
}

const num = (x) => decimal(x);
const vector = (v) => `(${v.map(num).join(", ")})`;

/** A job's parameters in a few words, so rows of the same type tell apart. */
function paramSummary(job) {
  const p = job.params || {};
  const parts = [];
  if (job.type === "reconstruct") {
    parts.push(p.quality);
    if (p.frames) parts.push(`frames ${p.frames[0]}–${p.frames[1] - 1}`);
    if (p.source) parts.push(`source ${vector(p.source.center)}${p.source.radius ? ` r ${num(p.source.radius)}` : ""}`);
    if (p.motion === "carrier") parts.push("buoyant air");
    if (p.air_cells) parts.push(`air ${p.air_cells} cells${p.air_vorticity ? `, vorticity ${num(p.air_vorticity)}` : ""}`);
    if (p.entrainment) parts.push("spreading");
  } else if (p.frames) parts.push(`${p.frames} new frames`);
  if (p.from_frame != null) parts.push(`from frame ${p.from_frame}`);
  if (p.wind) parts.push(`wind ${num(p.wind.strength)} ${p.wind.profile || ""} toward ${vector(p.wind.direction)}`.replace("  ", " "));
  if (p.ball) parts.push(`ball r ${num(p.ball.radius)} at ${vector(p.ball.center)}`);
  return parts.filter(Boolean).join(", ");
}

/** The request that created a job, to send again (Retry). */
export function requestOf(job) {
  const body = { type: job.type, params: job.params };
  if (job.scene_id) body.scene_id = job.scene_id; else body.parent_job_id = job.parent_job_id;
  return body;
}

export async function refreshJobs() {
  const page = await api("/v1/jobs?limit=100");
  for (const job of page.items) jobs.set(job.id, job);
  if (page.items.some((job) => job.scene_id && !sceneNames.has(job.scene_id))) {
    for (const scene of (await api("/v1/scenes?limit=100")).items) sceneNames.set(scene.id, scene.name || shortId(scene.id));
  }
  return page.items;
}

function button(label, handler, describedBy) {
  const b = document.createElement("button");
  b.type = "button";
  b.textContent = label;
  b.className = "secondary";
  b.setAttribute("aria-describedby", describedBy);
  b.addEventListener("click", handler);
  return b;
}

function actionButtons(job) {
  const label = `job-${job.id}`;
  const list = [];
  if (job.state === "succeeded") list.push(button("Results", () => actions.results(job.id), label));
  if (job.state !== "failed" && job.state !== "cancelled") {
    list.push(button("What-if", () => actions.whatif(job.id), label));
    list.push(button("Predict", () => actions.predict(job.id), label));
  }
  if (!isFinished(job)) list.push(button("Cancel", () => actions.cancel(job.id), label));
  if (job.state === "failed" || job.state === "cancelled") list.push(button("Retry", () => actions.retry(job.id), label));
  const box = document.createElement("div");
  box.className = "actions";
  box.append(...list);
  return box;
}

function newRow(job) {
  const tr = document.createElement("tr");
  tr.dataset.jobId = job.id;
  tr.innerHTML = `<td><span class="job-title"></span> <span class="job-id"></span><br><span class="help job-origin"></span>
    <br><span class="help job-params"></span>
    <p class="error job-error"></p></td><td class="job-state"></td><td class="job-stage"></td>
    <td><progress max="1"></progress> <span class="job-percent"></span></td><td class="job-actions"></td>`;
  tr.querySelector(".job-title").id = `job-${job.id}`;
  return tr;
}

function updateRow(job) {
  let row = rows.get(job.id);
  if (!row) {
    row = { tr: newRow(job), state: null };
    rows.set(job.id, row);
  }
  const tr = row.tr;
  tr.querySelector(".job-title").textContent = job.type;
  tr.querySelector(".job-id").textContent = shortId(job.id);
  tr.querySelector(".job-origin").textContent = `${origin(job)}, ${new Date(job.timings.created_at).toLocaleString()}`;
  tr.querySelector(".job-params").textContent = paramSummary(job);
  const stateCell = tr.querySelector(".job-state");
  stateCell.textContent = job.cancel_requested && !isFinished(job) ? `${job.state} (cancelling)` : job.state;
  stateCell.className = `job-state state-${job.state}`;
  tr.querySelector(".job-stage").textContent = job.stage.replace(/\b[0-9a-f]{32}\b/g, shortId);
  tr.querySelector("progress").value = job.progress;
  tr.querySelector("progress").setAttribute("aria-label", `progress of ${describeJob(job)}`);
  tr.querySelector(".job-percent").textContent = `${Math.round(job.progress * 100)} %`;
  // A cancelled job has an error only when its parent ended it ("parent job ... failed").
  const ended = job.state === "cancelled" ? "Cancelled" : "Failed";
  tr.querySelector(".job-error").textContent = job.error ? `${ended}: ${job.error}` : "";
  if (row.state !== job.state + job.cancel_requested) { // rebuild buttons only when they change
    row.state = job.state + job.cancel_requested;
    tr.querySelector(".job-actions").replaceChildren(actionButtons(job));
  }
  return tr;
}

function renderTable(items) {
  const body = $("jobs-table").querySelector("tbody");
  const wanted = items.map(updateRow);
  wanted.forEach((tr, i) => { if (body.children[i] !== tr) body.insertBefore(tr, body.children[i] || null); });
  while (body.children.length > wanted.length) body.lastChild.remove();
  $("jobs-empty").hidden = items.length > 0;
}

async function poll() {
  try {
    // a video's render shows in its player, a bundle's job beside the bundle form
    renderTable((await refreshJobs()).filter((job) => !["render", "bundle"].includes(job.type)));
    $("jobs-error").textContent = "";
  } catch (error) {
    $("jobs-error").textContent = `Could not update the job list: ${error.message}`;
  }
}

export function startPolling() {
  stopPolling();
  poll();
  timer = setInterval(poll, POLL_MS);
}

export function stopPolling() {
  if (timer) clearInterval(timer);
  timer = null;
  rows.clear();
  jobs.clear();
  $("jobs-table").querySelector("tbody").replaceChildren();
}

export const pollNow = poll;

/** `handlers`: results(id), whatif(id), predict(id), cancel(id), retry(id). */
export function initJobs(handlers) { actions = handlers; }
