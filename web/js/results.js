// Results view: MP4 players side by side and in sync (input view, any camera, the orbit; for a
// what-if, next to the factual prediction from the same frame), per-frame plots from the run
// manifest, and downloads of everything the job published (videos, exports, states, manifest).

import { $ } from "./dom.js";
import { api } from "./api.js";
import { describeJob, jobs, refreshJobs } from "./jobs.js";

const SYNC_TOLERANCE_S = 0.08;
let syncLoop = null;
let plots = [];

/** Video choices of one job: [{label, url, camera}] with the orbit last. */
function videoChoices(artifacts, prefix) {
  const name = (a) => (a.kind === "video" ? `camera ${a.camera}` : a.kind.replaceAll("_", " "));
  return artifacts.filter((a) => a.kind === "video" || a.kind === "orbit" || a.kind === "side_by_side")
    .map((a) => ({ label: `${prefix}${name(a)}`, url: a.presigned_url, camera: a.kind === "video" ? a.camera : null, kind: a.kind }))
    .sort((a, b) => (a.camera === null) - (b.camera === null));
}

/** The players to show: [{title, choices, initial}]. */
function playerPlan(job, manifest, own, factual) {
  const input = (manifest.input_views || [])[0];
  const mine = videoChoices(own, job.type === "interact" ? "what-if: " : "");
  const pick = (choices, camera) => Math.max(0, choices.findIndex((c) => c.camera === camera));
  const orbit = (choices) => Math.max(0, choices.findIndex((c) => c.kind === "orbit"));
  if (factual) {
    const theirs = videoChoices(factual, "factual: ");
    return [
      { title: "What-if, input view", choices: mine, initial: pick(mine, input) },
      { title: "Factual prediction, input view", choices: theirs, initial: pick(theirs, input) },
      { title: "What-if, orbit", choices: mine, initial: orbit(mine) },
      { title: "Factual prediction, orbit", choices: theirs, initial: orbit(theirs) },
    ];
  }
  const other = mine.findIndex((c) => c.camera !== null && c.camera !== input);
  const sideBySide = mine.findIndex((c) => c.kind === "side_by_side"); // a what-if without its factual twin
  return [
    { title: "Input view", choices: mine, initial: pick(mine, input) },
    { title: sideBySide >= 0 ? "Factual | what-if" : "Another camera", choices: mine,
      initial: sideBySide >= 0 ? sideBySide : other >= 0 ? other : pick(mine, input) },
    { title: "Orbit", choices: mine, initial: orbit(mine) },
  ];
}

function player({ title, choices, initial }, index) {
  const figure = document.createElement("figure");
  const video = document.createElement("video");
  video.muted = true;
  video.playsInline = true;
  video.preload = "auto";
  video.setAttribute("aria-label", title);
  const select = document.createElement("select");
  select.id = `player-${index}`;
  choices.forEach((choice, i) => select.append(new Option(choice.label, String(i))));
  select.value = String(initial);
  const label = Object.assign(document.createElement("label"), { htmlFor: select.id, textContent: title });
  video.loop = true; // a shorter video starts again rather than stopping while the others play
  const show = () => {
    const leader = document.querySelector("#players video");
    const time = leader && leader !== video ? leader.currentTime : 0;
    video.src = choices[Number(select.value)].url;
    video.currentTime = time;
  };
  video.addEventListener("loadedmetadata", () => { // portrait videos get a taller frame than landscape ones
    figure.classList.toggle("portrait", video.videoHeight > video.videoWidth);
  });
  select.addEventListener("change", show);
  if (choices.length) show();
  const caption = document.createElement("figcaption");
  caption.append(label, select);
  figure.append(video, caption);
  return figure;
}

const videos = () => [...document.querySelectorAll("#players video")];

/** One clock for all players: the first video leads; the others are nudged when they drift. */
function startSync() {
  stopSync();
  const seek = $("seek-all"), time = $("time-all");
  const tick = () => {
    const [leader, ...followers] = videos();
    if (leader) {
      for (const video of followers) {
        const target = video.duration ? leader.currentTime % video.duration : leader.currentTime; // shorter ones loop
        if (Math.abs(video.currentTime - target) > SYNC_TOLERANCE_S && video.readyState >= 1) video.currentTime = target;
        if (leader.paused !== video.paused) leader.paused ? video.pause() : video.play().catch(() => {});
      }
      if (leader.duration) seek.value = String(leader.currentTime / leader.duration);
      time.textContent = `${leader.currentTime.toFixed(2)} s`;
      $("play-all").textContent = leader.paused ? "Play" : "Pause";
    }
    syncLoop = requestAnimationFrame(tick);
  };
  syncLoop = requestAnimationFrame(tick);
}

export function stopSync() {
  if (syncLoop) cancelAnimationFrame(syncLoop);
  syncLoop = null;
  videos().forEach((video) => video.pause());
}

function plot(title, frames, series, unit) {
  const figure = document.createElement("figure");
  figure.setAttribute("aria-label", title);
  $("plots").append(figure);
  const opts = {
    title, width: 380, height: 220,
    scales: { x: { time: false } },
    axes: [{ label: "frame", incrs: FRAME_STEPS }, { label: unit, size: 60 }],
    series: [{ label: "frame" }, ...series.map(([name], i) => ({ label: name, stroke: PALETTE[i % PALETTE.length], width: 2 }))],
  };
  plots.push(new uPlot(opts, [frames, ...series.map(([, values]) => values)], figure));
}

const FRAME_STEPS = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000]; // whole frames on the x axis
const PALETTE = ["#1d5fa8", "#c0392b", "#17692a", "#8e44ad", "#d35400", "#2c3e50"];
const PSNRS = ["input_psnr", "forecast_psnr"]; // dB, tens: on the loss axis they would flatten the losses to zero
const NOT_LOSSES = new Set([...PSNRS, "particles", "gaussians"]);

/** Loss terms, PSNR of the input view, seconds per frame, from the manifest's frame log. */
function drawPlots(manifest) {
  plots.forEach((p) => p.destroy());
  plots = [];
  $("plots").replaceChildren();
  const frames = manifest.frames || [];
  if (!frames.length) {
    $("plots").textContent = "The run has no frames yet.";
    return;
  }
  const t = frames.map((f) => f.t);
  const keys = [...new Set(frames.flatMap((f) => Object.keys(f.losses || {})))];
  const column = (key) => frames.map((f) => (f.losses && key in f.losses ? f.losses[key] : null));
  const losses = keys.filter((k) => !NOT_LOSSES.has(k));
  if (losses.length) plot("Loss per frame", t, losses.map((k) => [k, column(k)]), "loss");
  const psnrs = PSNRS.filter((k) => keys.includes(k));
  if (psnrs.length) plot("PSNR of the input view", t, psnrs.map((k) => [k.replace("_psnr", ""), column(k)]), "dB");
  plot("Time per frame", t, [["seconds", frames.map((f) => f.seconds)]], "s");
  if (keys.includes("particles")) plot("Particles", t, [["particles", column("particles")], ["gaussians", column("gaussians")]], "count");
}

/** Every file the artifacts API lists, in its order: videos, exports, states, the manifest. */
function downloads(artifacts) {
  $("downloads").replaceChildren(...artifacts.map((a) => {
    const li = document.createElement("li");
    const link = Object.assign(document.createElement("a"), { href: a.presigned_url, textContent: a.name });
    link.download = a.name.split("/").pop();
    li.append(link, ` (${(a.size / 1024).toFixed(1)} KiB)`);
    return li;
  }));
}

/** The factual prediction beside a what-if: a succeeded predict job on the same parent, same frame count. */
async function factualFor(job) {
  if (job.type !== "interact") return null;
  await refreshJobs();
  if (job.params.from_frame != null) return null; // branched inside the run: its side-by-side shows the factual
  const twin = [...jobs.values()].find((j) => j.type === "predict" && j.parent_job_id === job.parent_job_id
    && j.params.frames === job.params.frames && j.state === "succeeded");
  return twin || null;
}

export async function showResults(jobId) {
  $("results-error").textContent = "";
  $("results-title").textContent = "Results";
  $("results-summary").textContent = "Loading…";
  $("players").replaceChildren();
  try {
    const job = await api(`/v1/jobs/${jobId}`);
    const own = (await api(`/v1/jobs/${jobId}/artifacts`)).items;
    const manifestItem = own.find((a) => a.kind === "manifest");
    const manifest = manifestItem ? await api(manifestItem.url) : { frames: [] };
    const twin = await factualFor(job);
    const factual = twin ? (await api(`/v1/jobs/${twin.id}/artifacts`)).items : null;
    $("results-title").textContent = `Results of ${describeJob(job)}`;
    const range = manifest.frame_range ? `frames ${manifest.frame_range[0]}–${manifest.frame_range[1] - 1}` : "";
    $("results-summary").textContent = `${job.state}; ${range}; input views ${(manifest.input_views || []).join(", ")}`
      + (job.type !== "interact" ? "."
        : job.params.from_frame != null ? `; branched at frame ${job.params.from_frame}: the factual | what-if player shows the run without the intervention.`
          : twin ? `; shown next to the factual prediction (${describeJob(twin)}) from the same frame.`
            : "; no succeeded factual prediction with the same frames yet.");
    $("players").replaceChildren(...playerPlan(job, manifest, own, factual).map(player));
    drawPlots(manifest);
    downloads(own);
    startSync();
  } catch (error) {
    $("results-error").textContent = `Could not load the results: ${error.message}`;
  }
}

export function initResults() {
  $("play-all").addEventListener("click", () => {
    const [leader] = videos();
    if (!leader) return;
    if (leader.paused) videos().forEach((v) => v.play().catch(() => {}));
    else videos().forEach((v) => v.pause());
  });
  $("seek-all").addEventListener("input", (event) => {
    const [leader] = videos();
    if (leader && leader.duration) videos().forEach((v) => { v.currentTime = Number(event.target.value) * leader.duration; });
  });
}
