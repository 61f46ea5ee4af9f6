// Results view: MP4 players side by side and in sync (input view, any camera, the orbit; for a
// what-if, next to the factual prediction from the same frame), per-frame plots from the run
// manifest, and downloads of everything the job published (videos, exports, states, manifest).
// A reconstruction publishes its input views, a prediction or what-if no video; any other video
// (a camera, the orbit, a what-if's side-by-side) is rendered when a player or a download asks for
// it (POST /v1/jobs/{id}/videos/{name}):
// the player says "rendering… N %" until the server has stored it, then plays it in step.

import { $ } from "./dom.js";
import { api } from "./api.js";
import { describeJob, jobs, refreshJobs } from "./jobs.js";

const SYNC_TOLERANCE_S = 0.08;
const RENDER_POLL_MS = 1000;
let syncLoop = null;
let plots = [];
const renders = new Map(); // "job/name" -> {done: Promise<url>, listeners}: one request per video, however many players ask

/** The URL of a video of `jobId`: at once when stored, else once the render the server starts
 * (or already runs) for it has stored it; `onProgress(fraction)` while it renders. */
function requestVideo(jobId, name, onProgress) {
  const key = `${jobId}/${name}`;
  let entry = renders.get(key);
  if (!entry) {
    entry = { listeners: new Set() };
    entry.done = (async () => {
      for (;;) {
        const video = await api(`/v1/jobs/${jobId}/videos/${encodeURIComponent(name)}`, { method: "POST" });
        if (video.artifact) return video.artifact.presigned_url;
        let job = video.render_job;
        while (!["succeeded", "failed", "cancelled"].includes(job.state)) {
          entry.listeners.forEach((listener) => listener(job.progress));
          await new Promise((resolve) => setTimeout(resolve, RENDER_POLL_MS));
          job = await api(`/v1/jobs/${job.id}`);
        }
        if (job.state !== "succeeded") throw new Error(job.error || `the render was ${job.state}`);
      }
    })();
    entry.done.finally(() => renders.delete(key)).catch(() => {}); // once stored, the video list names it
    renders.set(key, entry);
  }
  if (onProgress) entry.listeners.add(onProgress);
  return entry.done;
}

const videoLabel = (v) => (v.kind === "video" ? `camera ${v.camera}` : v.kind.replaceAll("_", " "));

/** Video choices of one job: [{label, url, name, jobId, camera, kind}] with the orbit last;
 * `url` is null for a video not rendered yet. */
function videoChoices(videos, prefix, jobId) {
  return videos.map((v) => ({ label: `${prefix}${videoLabel(v)}`, url: v.artifact ? v.artifact.presigned_url : null,
    name: v.name, jobId, camera: v.kind === "video" ? v.camera : null, kind: v.kind }))
    .sort((a, b) => (a.camera === null) - (b.camera === null));
}

/** The players to show: [{title, choices, initial}]. */
function playerPlan(job, manifest, own, factual) {
  const input = (manifest.input_views || [])[0];
  const mine = videoChoices(own, job.type === "interact" ? "what-if: " : "", job.id);
  const pick = (choices, camera) => Math.max(0, choices.findIndex((c) => c.camera === camera));
  const orbit = (choices) => Math.max(0, choices.findIndex((c) => c.kind === "orbit"));
  if (factual) {
    const theirs = videoChoices(factual.videos, "factual: ", factual.jobId);
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

function player({ title, choices, initial }, index, onRendered) {
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
  const status = Object.assign(document.createElement("p"), { className: "player-status" });
  status.setAttribute("role", "status");
  video.loop = true; // a shorter video starts again rather than stopping while the others play
  let shown = 0; // the latest choice wins over an earlier one still rendering
  const show = async () => {
    const choice = choices[Number(select.value)];
    const mine = ++shown;
    status.textContent = "";
    if (!choice.url) {
      figure.classList.add("rendering");
      video.removeAttribute("src");
      video.load();
      status.textContent = "rendering… 0 %";
      try {
        choice.url = await requestVideo(choice.jobId, choice.name, (fraction) => {
          if (mine === shown) status.textContent = `rendering… ${Math.round(fraction * 100)} %`;
        });
        onRendered();
      } catch (error) {
        if (mine === shown) status.textContent = `Could not render it: ${error.message}`;
        return;
      }
      if (mine !== shown) return;
      figure.classList.remove("rendering");
      status.textContent = "";
    }
    const leader = document.querySelector("#players video");
    const time = leader && leader !== video ? leader.currentTime : 0;
    video.src = choice.url;
    video.currentTime = time;
  };
  video.addEventListener("loadedmetadata", () => { // portrait videos get a taller frame than landscape ones
    figure.classList.toggle("portrait", video.videoHeight > video.videoWidth);
  });
  select.addEventListener("change", show);
  if (choices.length) show();
  const caption = document.createElement("figcaption");
  caption.append(label, select);
  figure.append(video, status, caption);
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

/** Every file the artifacts API lists, in its order: videos, exports, states, the manifest; then
 * the videos not rendered yet, each a button that renders it and lists it with the rest. */
function downloads(jobId, artifacts, videos) {
  const items = artifacts.map((a) => {
    const li = document.createElement("li");
    const link = Object.assign(document.createElement("a"), { href: a.presigned_url, textContent: a.name });
    link.download = a.name.split("/").pop();
    li.append(link, ` (${(a.size / 1024).toFixed(1)} KiB)`);
    return li;
  });
  const missing = videos.filter((v) => !v.artifact).map((v) => {
    const li = document.createElement("li");
    const button = Object.assign(document.createElement("button"), { type: "button", className: "secondary",
      textContent: `Render ${v.name}.mp4` });
    button.addEventListener("click", async () => {
      button.disabled = true;
      try {
        await requestVideo(jobId, v.name, (fraction) => { button.textContent = `Rendering ${v.name}.mp4… ${Math.round(fraction * 100)} %`; });
        await refreshDownloads(jobId);
      } catch (error) {
        button.disabled = false;
        button.textContent = `Render ${v.name}.mp4 (failed: ${error.message})`;
      }
    });
    li.append(button);
    return li;
  });
  $("downloads").replaceChildren(...items, ...missing);
}

async function refreshDownloads(jobId) {
  const [artifacts, videos] = await Promise.all([api(`/v1/jobs/${jobId}/artifacts`), api(`/v1/jobs/${jobId}/videos`)]);
  if ($("downloads").dataset.jobId === jobId) downloads(jobId, artifacts.items, videos.items);
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
  $("downloads").dataset.jobId = jobId;
  try {
    const job = await api(`/v1/jobs/${jobId}`);
    const [own, videos] = await Promise.all([api(`/v1/jobs/${jobId}/artifacts`), api(`/v1/jobs/${jobId}/videos`)]);
    const manifestItem = own.items.find((a) => a.kind === "manifest");
    const manifest = manifestItem ? await api(manifestItem.url) : { frames: [] };
    const twin = await factualFor(job);
    const factual = twin ? { jobId: twin.id, videos: (await api(`/v1/jobs/${twin.id}/videos`)).items } : null;
    $("results-title").textContent = `Results of ${describeJob(job)}`;
    const range = manifest.frame_range ? `frames ${manifest.frame_range[0]}–${manifest.frame_range[1] - 1}` : "";
    $("results-summary").textContent = `${job.state}; ${range}; input views ${(manifest.input_views || []).join(", ")}`
      + (job.type !== "interact" ? "."
        : job.params.from_frame != null ? `; branched at frame ${job.params.from_frame}: the factual | what-if player shows the run without the intervention.`
          : twin ? `; shown next to the factual prediction (${describeJob(twin)}) from the same frame.`
            : "; no succeeded factual prediction with the same frames yet.");
    const rendered = () => refreshDownloads(jobId).catch(() => {});
    $("players").replaceChildren(...playerPlan(job, manifest, videos.items, factual).map((plan, i) => player(plan, i, rendered)));
    drawPlots(manifest);
    downloads(jobId, own.items, videos.items);
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
