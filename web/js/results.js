// Results view: MP4 players side by side and in sync (input view, any camera, the orbit; for a
// what-if, next to the factual prediction from the same frame; for a reconstruction, the uploaded
// footage of its input view beside the render of it, side by side, overlaid or as their
// difference), per-frame plots from the run manifest, and downloads of everything the job
// published, grouped (videos, bundles, single exports, the run's own files), with a form that
// makes a bundle: every frame as one zip (POST /v1/jobs/{id}/bundles), progress while it is made.
// A reconstruction publishes its input views, a prediction or what-if no video; any other video
// (a camera, the orbit, a what-if's side-by-side) is rendered when a player or a download asks for
// it (POST /v1/jobs/{id}/videos/{name}):
// the player says "rendering… N %" until the server has stored it, then plays it in step.

import { $ } from "./dom.js";
import { api } from "./api.js";
import { boxText, decimal, point } from "./format.js";
import { describeJob, jobs, refreshJobs } from "./jobs.js";

const SYNC_TOLERANCE_S = 0.08;
const JOB_POLL_MS = 1000;
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
        await finished(video.render_job, (fraction) => entry.listeners.forEach((listener) => listener(fraction)), "render");
      }
    })();
    entry.done.finally(() => renders.delete(key)).catch(() => {}); // once stored, the video list names it
    renders.set(key, entry);
  }
  if (onProgress) entry.listeners.add(onProgress);
  return entry.done;
}

/** Poll a render or bundle job until it ends; `onProgress(fraction)` meanwhile; throws unless it succeeded. */
async function finished(job, onProgress, what) {
  while (!["succeeded", "failed", "cancelled"].includes(job.state)) {
    onProgress(job.progress);
    await new Promise((resolve) => setTimeout(resolve, JOB_POLL_MS));
    job = await api(`/v1/jobs/${job.id}`);
  }
  if (job.state !== "succeeded") throw new Error(job.error || `the ${what} was ${job.state}`);
}

const videoLabel = (v) => (v.kind === "video" ? `camera ${v.camera}` : v.kind.replaceAll("_", " "));

/** Video choices of one job: [{label, url, name, jobId, camera, kind}] with the orbit last;
 * `url` is null for a video not rendered yet. */
function videoChoices(videos, prefix, jobId) {
  return videos.map((v) => ({ label: `${prefix}${videoLabel(v)}`, url: v.artifact ? v.artifact.presigned_url : null,
    name: v.name, jobId, camera: v.kind === "video" ? v.camera : null, kind: v.kind }))
    .sort((a, b) => (a.camera === null) - (b.camera === null));
}

/** The players to show: [{title, choices, initial}], and `{title, footage}` for the footage. */
function playerPlan(job, manifest, own, factual, footage) {
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
    ...(footage ? [{ title: `Footage, camera ${footage.camera}`, footage }] : []),
    { title: sideBySide >= 0 ? "Factual | what-if" : "Another camera", choices: mine,
      initial: sideBySide >= 0 ? sideBySide : other >= 0 ? other : pick(mine, input) },
    { title: "Orbit", choices: mine, initial: orbit(mine) },
  ];
}

function player(plan, index, onRendered) {
  if (plan.footage) return footagePlayer(plan);
  const { title, choices, initial } = plan;
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
    video.dataset.camera = choice.camera || "";
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

/** Where `video` should be when the leader is at `time`: the footage runs `offset` seconds
 * ahead (the run starts at a later frame of the clip); a shorter video loops. */
function followTime(video, time) {
  const target = time + Number(video.dataset.offset || 0);
  return video.duration ? target % video.duration : target;
}

/** The uploaded video of the reconstruction's input view (GET /v1/scenes/{id}/videos), or null:
 * {camera, url, offset}, `offset` the seconds of footage before the run's first frame. */
async function footageOf(job, manifest) {
  const camera = (manifest.input_views || [])[0];
  if (job.type !== "reconstruct" || !job.scene_id || !camera) return null;
  const link = (await api(`/v1/scenes/${job.scene_id}/videos`)).items.find((v) => v.camera === camera);
  if (!link) return null;
  const first = manifest.frame_range ? manifest.frame_range[0] : 0;
  return { camera, url: link.presigned_url, offset: manifest.fps ? first / manifest.fps : 0 };
}

const COMPARE = [["side", "side by side"], ["overlay", "overlay (render at half opacity)"],
  ["difference", "difference (black: they agree)"]];

/** The footage player: the uploaded clip, in step with the input-view render (the first player)
 * from the run's first frame on, and a canvas over it that shows the two overlaid or their
 * difference. */
function footagePlayer({ title, footage }) {
  const figure = document.createElement("figure");
  figure.className = "footage";
  const video = document.createElement("video");
  Object.assign(video, { muted: true, playsInline: true, preload: "auto", loop: true });
  video.dataset.offset = String(footage.offset);
  video.dataset.footageOf = footage.camera;
  video.setAttribute("aria-label", title);
  const canvas = document.createElement("canvas");
  canvas.hidden = true;
  canvas.setAttribute("role", "img");
  const frame = Object.assign(document.createElement("div"), { className: "footage-frame" });
  frame.append(video, canvas);
  const select = Object.assign(document.createElement("select"), { id: "footage-compare" });
  COMPARE.forEach(([value, text]) => select.append(new Option(text, value)));
  const label = Object.assign(document.createElement("label"), { htmlFor: select.id, textContent: `${title}: compare with the input view` });
  const status = Object.assign(document.createElement("p"), { className: "player-status" });
  status.setAttribute("role", "status");
  select.addEventListener("change", () => {
    canvas.hidden = select.value === "side";
    canvas.setAttribute("aria-label", `${COMPARE.find(([v]) => v === select.value)[1]}, camera ${footage.camera}`);
    drawComparison();
  });
  video.addEventListener("loadedmetadata", () => figure.classList.toggle("portrait", video.videoHeight > video.videoWidth));
  video.addEventListener("error", () => { status.textContent = "This browser cannot play the uploaded video (its format or codec)."; });
  video.src = footage.url;
  const caption = document.createElement("figcaption");
  caption.append(label, select);
  figure.append(frame, status, caption);
  return figure;
}

/** The footage's canvas: the footage, and over it the input-view render (the first player) half
 * transparent or as their per-pixel difference; both scaled to the footage's size. */
function drawComparison() {
  const canvas = document.querySelector("#players figure.footage canvas");
  if (!canvas || canvas.hidden) return;
  const footage = canvas.parentElement.querySelector("video");
  const [render] = videos();
  const status = canvas.closest("figure").querySelector(".player-status");
  const choose = `Choose camera ${footage.dataset.footageOf} in the Input view player to compare.`;
  if (!render || render.dataset.camera !== footage.dataset.footageOf) {
    status.textContent = choose;
    return;
  }
  if (status.textContent === choose) status.textContent = "";
  if (!footage.videoWidth || !render.videoWidth) return;
  if (canvas.width !== footage.videoWidth || canvas.height !== footage.videoHeight) {
    canvas.width = footage.videoWidth;
    canvas.height = footage.videoHeight;
  }
  const context = canvas.getContext("2d");
  const mode = document.getElementById("footage-compare").value;
  context.globalCompositeOperation = "source-over";
  context.globalAlpha = 1;
  context.drawImage(footage, 0, 0, canvas.width, canvas.height);
  if (mode === "overlay") context.globalAlpha = 0.5;
  else context.globalCompositeOperation = "difference";
  context.drawImage(render, 0, 0, canvas.width, canvas.height);
  context.globalCompositeOperation = "source-over";
  context.globalAlpha = 1;
}

/** One clock for all players: the first video leads; the others are nudged when they drift. */
function startSync() {
  stopSync();
  const seek = $("seek-all"), time = $("time-all");
  const tick = () => {
    const [leader, ...followers] = videos();
    if (leader) {
      for (const video of followers) {
        const target = followTime(video, leader.currentTime);
        if (Math.abs(video.currentTime - target) > SYNC_TOLERANCE_S && video.readyState >= 1) video.currentTime = target;
        if (leader.paused !== video.paused) leader.paused ? video.pause() : video.play().catch(() => {});
      }
      if (leader.duration) seek.value = String(leader.currentTime / leader.duration);
      time.textContent = `${leader.currentTime.toFixed(2)} s`;
      $("play-all").textContent = leader.paused ? "Play" : "Pause";
      drawComparison();
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

/** A uPlot chart of `series` ([name, values]) over the frames, with a caption under it. Its
 * legend always reads: with the pointer away from the chart it shows the last frame's values
 * (uPlot's own legend shows "--" until hovered). `options`: {caption, log, format}. */
function plot(title, frames, series, unit, { caption = "", log = false, format = fmt3 } = {}) {
  const figure = document.createElement("figure");
  figure.setAttribute("aria-label", title);
  $("plots").append(figure);
  const last = frames.length - 1;
  const lastOf = (values) => { for (let i = last; i >= 0; i--) if (values[i] != null) return values[i]; return null; };
  const legend = (values) => (u, value, _series, idx) => {
    const shown = idx == null ? lastOf(values) : value;
    return shown == null ? "–" : format(shown);
  };
  const opts = {
    title, width: 380, height: 220,
    scales: { x: { time: false }, y: log ? { distr: 3 } : {} },
    axes: [{ label: "frame", incrs: FRAME_STEPS }, { label: unit, size: 60 }],
    series: [{ label: "frame", value: (u, value, _series, idx) => (idx == null ? `${frames[last]} (last)` : String(value)) },
      ...series.map(([name, values], i) => ({ label: name, stroke: PALETTE[i % PALETTE.length], width: 2, value: legend(values) }))],
  };
  plots.push(new uPlot(opts, [frames, ...series.map(([, values]) => values)], figure));
  if (caption) figure.append(Object.assign(document.createElement("figcaption"), { className: "help", textContent: caption }));
}

const fmt3 = (v) => (Math.abs(v) >= 100 ? decimal(v, 0) : Number(v.toPrecision(3)).toString());
const FRAME_STEPS = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000]; // whole frames on the x axis
const PALETTE = ["#1d5fa8", "#c0392b", "#17692a", "#8e44ad", "#d35400", "#2c3e50"];
// dB, tens: apart from the losses; the background alone is the fit's yardstick (fluidcore.reconstruct.yardstick)
const PSNRS = { input_psnr: "after the fit", forecast_psnr: "forecast, before the fit", background_psnr: "background alone" };
// Per-frame records that are no loss: the yardstick's share explained and the smoke's place (fluidcore.health pools them).
const NOT_LOSSES = new Set([...Object.keys(PSNRS), "particles", "gaussians", "explained", "smoke_up", "smoke_across"]);

/** Each loss term divided by its first non-zero value (terms differ by orders of magnitude, and
 * what matters is whether each falls): [[name, ratios]] of the terms that have one; a ratio that
 * is not positive is a gap, a log axis cannot show it. `zero`: the terms 0 on every frame. */
function relativeLosses(names, column) {
  const drawn = [], zero = [];
  for (const name of names) {
    const values = column(name);
    const first = values.find((v) => v != null && v > 0);
    if (first === undefined) zero.push(name);
    else drawn.push([name, values.map((v) => (v != null && v > 0 ? v / first : null))]);
  }
  return { drawn, zero };
}

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
  const { drawn, zero } = relativeLosses(keys.filter((k) => !NOT_LOSSES.has(k)), column);
  if (drawn.length || zero.length) {
    plot("Loss per frame, relative to the first", t, drawn, "÷ first frame", { log: true, caption:
      "Each term divided by its first non-zero value, on a log axis: below 1 it fell. Each frame's fit ends on a "
      + "randomly chosen view, so neighbouring frames scatter; follow the trend."
      + (zero.length ? ` ${zero.join(", ")}: 0 on every frame (its weight is 0, or nothing violated it), not drawn.` : "") });
  }
  const psnrs = Object.keys(PSNRS).filter((k) => keys.includes(k));
  if (psnrs.length) {
    plot("PSNR of the input view", t, psnrs.map((k) => [PSNRS[k], column(k)]), "dB", { caption: (keys.includes("forecast_psnr")
      ? "After the fit: the frame's render against the footage. Forecast: before fitting a frame, the previous "
        + "frame's smoke moved on by the simulator alone, scored against the footage it has not seen yet."
      : "The frame's render against the footage.")
      + (keys.includes("background_psnr") ? " Background alone: what an empty reconstruction scores on the same frame; "
        + "a fit close to it reconstructs little of the smoke." : "") });
  }
  plot("Time per frame", t, [["seconds", frames.map((f) => f.seconds)]], "s");
  if (keys.includes("particles")) plot("Particles", t, [["particles", column("particles")], ["gaussians", column("gaussians")]], "count");
}

// The artifact kinds (api.schemas.ArtifactKind, listed in this order) under the headings they go under.
const DOWNLOAD_GROUPS = [
  ["Videos", ["video", "orbit", "side_by_side"]],
  ["Bundles (every frame in one zip)", ["bundle"]],
  ["Single files (the last frame in each format, every frame as VDB)", ["export"]],
  ["The run itself (particle states, manifest)", ["state", "manifest", "file"]],
];

const size = (bytes) => (bytes >= 1048576 ? `${(bytes / 1048576).toFixed(1)} MiB` : `${(bytes / 1024).toFixed(1)} KiB`);

/** Every file the artifacts API lists, grouped under DOWNLOAD_GROUPS in the API's order; the
 * videos not rendered yet close the videos, each a button that renders it and lists it with the rest. */
function downloads(jobId, artifacts, videos) {
  const item = (a) => {
    const li = document.createElement("li");
    const link = Object.assign(document.createElement("a"), { href: a.presigned_url, textContent: a.name });
    link.download = a.name.split("/").pop();
    li.append(link, ` (${size(a.size)})`);
    return li;
  };
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
  const groups = DOWNLOAD_GROUPS.map(([title, kinds], i) => {
    const items = artifacts.filter((a) => kinds.includes(a.kind)).map(item);
    if (i === 0) items.push(...missing);
    if (!items.length) return null;
    const list = Object.assign(document.createElement("ul"), { className: "download-list" });
    list.append(...items);
    const section = document.createElement("section");
    section.append(Object.assign(document.createElement("h4"), { textContent: title }), list);
    return section;
  });
  $("downloads").replaceChildren(...groups.filter(Boolean));
}

/** The bundle form for a succeeded job that has a run (GET /v1/jobs/{id}/bundles): its voxel
 * size defaults to the API's (a quarter of the kernel radius, at most the radius); hidden otherwise. */
async function offerBundles(job) {
  const form = $("bundle-form");
  form.hidden = true;
  $("bundle-status").textContent = "";
  if (job.state !== "succeeded" || ["render", "bundle"].includes(job.type)) return;
  const offer = await api(`/v1/jobs/${job.id}/bundles`);
  if (!offer.frames) return;
  const voxel = $("bundle-voxel");
  Object.assign(voxel, { value: "", max: String(offer.kernel_radius), placeholder: `${decimal(offer.default_voxel_size, 4)} (default)` });
  form.dataset.jobId = job.id;
  form.dataset.frames = `frames ${offer.frames[0]}–${offer.frames[1] - 1}`;
  $("bundle-frames").textContent = `${form.dataset.frames}, `;
  form.hidden = false;
}

async function makeBundle(event) {
  event.preventDefault();
  const form = $("bundle-form");
  const jobId = form.dataset.jobId;
  const format = $("bundle-format").value;
  const voxel = $("bundle-voxel").value;
  const status = $("bundle-status");
  const button = form.querySelector("button[type=submit]");
  button.disabled = true;
  status.className = "";
  try {
    const body = { format, ...(voxel !== "" && format !== "ply" ? { voxel_size: Number(voxel) } : {}) };
    let bundle = await api(`/v1/jobs/${jobId}/bundles`, { method: "POST", body });
    if (!bundle.artifact) {
      await finished(bundle.bundle_job, (fraction) => { status.textContent = `Making ${bundle.name}… ${Math.round(fraction * 100)} %`; }, "bundle");
      bundle = await api(`/v1/jobs/${jobId}/bundles`, { method: "POST", body });
    }
    status.textContent = `Ready: ${bundle.name} (${size(bundle.artifact.size)}), listed under Bundles.`;
    await refreshDownloads(jobId);
  } catch (error) {
    status.className = "error";
    status.textContent = `Could not make the zip: ${error.message}`;
  } finally {
    button.disabled = false;
  }
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

/** What the run's simulation used (manifest.scene): still or simulated air, and the plume's
 * spreading, said even when the identification found none (a spreading asked for but 0). */
function simulated(manifest) {
  const scene = manifest.scene;
  if (!scene) return "";
  const cells = (scene.air || {}).cells || 0;
  const rate = (scene.physics || {}).entrainment || 0;
  const asked = ((((manifest.settings || {}).quality || {}).simulation) || {}).entrainment;
  const spreading = rate > 0 ? `spreading ${rate.toFixed(2)} per unit risen (from the video)`
    : asked ? "spreading asked for, but the video showed none: not applied" : "no spreading";
  return `; air: ${cells ? `simulated, ${cells} cells on the box's long side` : "still"}; ${spreading}`;
}

// What to give next, in this page's words (fluidcore.health.Remedy; the CLI words them as its
// flags, the REST API as its fields): the upload form's fields, the what-if page's source slider.
const REMEDIES = {
  source: "give the source (the upload form's Smoke source, or the slider under Where the smoke starts on the what-if page)",
  background_plate: "give a background plate (the upload form's Background plate: frames without smoke)",
  another_view: "add a view (upload a camera file with another camera's video)",
  world_up: "give the right up (the upload form's World up; one video without a camera file: Where world up points in the image)",
  solids: "place the ball where the smoke passes (a new reconstruction's ball, in world units)",
};

/** A health check's finding and its remedies in this page's words, joined as fluidcore.health joins them. */
function advised(check) {
  const remedies = (check.advice || []).map((remedy) => REMEDIES[remedy] || remedy);
  if (!remedies.length) return check.finding;
  const last = remedies.pop();
  return `${check.finding}: ${remedies.length ? `${remedies.join("; ")}; or ${last}` : last}`;
}

/** The run's scene (manifest.scene) in words: its box and up, and the smoke source's centre and size
 * (world units), as the what-if page states them; empty before the manifest has a scene. */
function sceneText(manifest) {
  const scene = manifest.scene;
  if (!scene || !scene.box || !scene.source) return ""; // an older manifest's layout: the rest of the page stands
  const { center, radius } = scene.source;
  return `${boxText(scene.box)} (world units; up ${point(scene.up)}). `
    + `Smoke source: centre ${point(center)}, radius ${decimal(radius)} (${decimal(2 * radius)} across).`;
}

/** The health report of the reconstruction this job stands on (GET /v1/scenes/{id}: geometry.health,
 * fluidcore.health), worded for this page: warnings first, then notes; nothing before the scene
 * has a reconstruction. */
async function showHealth(job) {
  const list = $("results-health");
  list.replaceChildren();
  if (!job.scene_id) return;
  const geometry = (await api(`/v1/scenes/${job.scene_id}`)).geometry;
  if (!geometry.health) return;
  const item = (text, kind) => Object.assign(document.createElement("li"), { textContent: text, className: kind });
  const of = geometry.source.job_id === job.id ? "this reconstruction" : `reconstruction ${geometry.source.job_id}`;
  const checks = (level) => geometry.health.checks.filter((c) => c.level === level);
  list.replaceChildren(
    ...checks("warning").map((c) => item(`Warning (${of}): ${advised(c)}`, "warning")),
    ...checks("note").map((c) => item(`Note (${of}): ${advised(c)}`, "note")),
  );
}

export async function showResults(jobId) {
  $("results-error").textContent = "";
  $("results-health").replaceChildren();
  $("results-scene").textContent = "";
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
    const footage = await footageOf(job, manifest);
    $("results-title").textContent = `Results of ${describeJob(job)}`;
    const range = manifest.frame_range ? `frames ${manifest.frame_range[0]}–${manifest.frame_range[1] - 1}` : "";
    $("results-summary").textContent = `${job.state}; ${range}; input views ${(manifest.input_views || []).join(", ")}`
      + simulated(manifest)
      + (job.type !== "interact" ? "."
        : job.params.from_frame != null ? `; branched at frame ${job.params.from_frame}: the factual | what-if player shows the run without the intervention.`
          : twin ? `; shown next to the factual prediction (${describeJob(twin)}) from the same frame.`
            : "; no succeeded factual prediction with the same frames yet.");
    const rendered = () => refreshDownloads(jobId).catch(() => {});
    $("results-scene").textContent = sceneText(manifest);
    $("players").replaceChildren(...playerPlan(job, manifest, videos.items, factual, footage).map((plan, i) => player(plan, i, rendered)));
    drawPlots(manifest);
    downloads(jobId, own.items, videos.items);
    offerBundles(job).catch((error) => { $("bundle-status").textContent = `Bundles unavailable: ${error.message}`; });
    showHealth(job).catch(() => {}); // the results stand without it
    startSync();
  } catch (error) {
    $("results-error").textContent = `Could not load the results: ${error.message}`;
  }
}

export function initResults() {
  $("bundle-form").addEventListener("submit", makeBundle);
  $("bundle-format").addEventListener("change", (event) => { $("bundle-voxel").disabled = event.target.value === "ply"; });
  $("play-all").addEventListener("click", () => {
    const [leader] = videos();
    if (!leader) return;
    if (leader.paused) videos().forEach((v) => v.play().catch(() => {}));
    else videos().forEach((v) => v.pause());
  });
  $("seek-all").addEventListener("input", (event) => {
    const [leader] = videos();
    if (leader && leader.duration) videos().forEach((v) => { v.currentTime = followTime(v, Number(event.target.value) * leader.duration); });
  });
}
