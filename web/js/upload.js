// Upload view: drop a camera file and videos, see them (first frames, cameras and box from
// above; for one video without a camera file, the box its field of view makes drawn on its first
// frame), read what is wrong before sending, then send with a progress bar.

import { $, showList } from "./dom.js";
import { api, uploadForm } from "./api.js";
import { drawTopDown, lookPoint, matchCamera, parseCameraFile } from "./cameras.js";
import { decimal } from "./format.js";
import { mp4Frames } from "./mp4.js";
import { allowedText, bound, limitProblem, loadLimits } from "./limits.js";
import { insideBox, parseBall, parseSource } from "./source.js";

const VIDEO_NAME = /\.(mp4|mov|m4v|webm|mkv|avi)$/i;
const BOX_COLOR = "#ffd23f"; // the field of view's box on the first frame: yellow, seen over smoke and most scenes

const state = { camerasFile: null, parsed: null, cameraError: null, videos: [] };
let limits = null; // the reconstruction's parameter limits (GET /v1/limits), or {error}

/** The first frame of a video, decoded by the browser: {width, height, duration, frames} and a canvas. */
function firstFrame(file) {
  return new Promise((resolve) => {
    const video = document.createElement("video");
    const url = URL.createObjectURL(file);
    const done = (result) => { URL.revokeObjectURL(url); resolve(result); };
    video.muted = true;
    video.preload = "auto";
    video.addEventListener("loadeddata", async () => {
      const [canvas, frame] = [0, 1].map(() => Object.assign(document.createElement("canvas"),
        { width: video.videoWidth, height: video.videoHeight }));
      frame.getContext("2d").drawImage(video, 0, 0); // kept as decoded: `canvas` shows it, and the box over it
      canvas.getContext("2d").drawImage(frame, 0, 0);
      const counted = await mp4Frames(file); // null for other containers: the server counts them
      done({ width: video.videoWidth, height: video.videoHeight, duration: video.duration, canvas, frame,
        frames: counted && counted.frames, fps: counted && counted.fps });
    }, { once: true });
    video.addEventListener("error", () => done({ error: "this browser cannot decode it (the server will still check it)" }), { once: true });
    video.src = url;
  });
}

let generation = 0; // bumped by Clear: files still being read for an earlier selection are dropped

async function addFiles(files) {
  const mine = generation;
  for (const file of files) {
    if (VIDEO_NAME.test(file.name) || file.type.startsWith("video/")) {
      const video = { file, ...(await firstFrame(file)) };
      if (mine !== generation) return;
      state.videos = [...state.videos.filter((v) => v.file.name !== file.name), video];
    } else {
      state.camerasFile = file;
      try {
        state.parsed = parseCameraFile(file.name, await file.arrayBuffer());
        state.cameraError = null;
      } catch (error) {
        state.parsed = null;
        state.cameraError = error.message;
      }
    }
  }
  render();
}

/** Everything that would make the server refuse this upload and that the browser can already see. */
function uploadProblems({ camerasFile, parsed, cameraError, videos }) {
  const problems = [];
  const fov = fieldOfView();
  if (fov.error) problems.push(fov.error);
  if (!camerasFile && fov.value === undefined) {
    problems.push("Add a camera file (transforms.json, info.json or a zipped COLMAP model), or give one video's field of view.");
  }
  if (camerasFile && fov.value !== undefined) problems.push("Give a camera file or a field of view, not both: clear the field of view.");
  if (!camerasFile && fov.value !== undefined && videos.length > 1) {
    problems.push(`A field of view makes the camera of one video; ${videos.length} videos need a camera file.`);
  }
  if (cameraError) problems.push(`Camera file: ${cameraError}`);
  if (!videos.length) problems.push("Add at least one video, named after its camera.");
  const cameras = parsed && parsed.cameras;
  const source = parseSource($("source").value);
  if (source.error) problems.push(source.error);
  const plate = parseFrameSpan($("background-frames").value);
  if (plate.error) problems.push(plate.error);
  else if (source.value && parsed && parsed.box && !insideBox(source.value.center, parsed.box)) {
    problems.push(`Smoke source ${fmt(source.value.center)} is outside the scene box ${fmt(parsed.box.lo)} to ${fmt(parsed.box.hi)}.`);
  }
  problems.push(...ballProblems(parseBall($("ball").value), parsed && parsed.box));
  if (!limits) problems.push("Reading the server's limits…");
  else if (limits.error) problems.push(`The server's limits could not be read: ${limits.error}`);
  else {
    const air = $("air-cells").value && limitProblem("Simulated air", Number($("air-cells").value), limits.air_cells);
    if (air) problems.push(air);
    else if ($("motion").value === "carrier" && $("air-cells").value !== "" && Number($("air-cells").value) === 0) {
      problems.push("Simulated air 0 is still air, which cannot carry the smoke: leave it empty, give cells, or choose the paper's particles.");
    }
  }
  if (!cameras) return problems;
  const known = cameras.map((c) => c.name).join(", ");
  const taken = new Map();
  for (const video of videos) {
    const camera = cameraOf(video, cameras);
    if (!camera) {
      problems.push(`${video.file.name} matches no camera; pick its camera beside it, or name it after one of: ${known}.`);
      continue;
    }
    if (taken.has(camera.name)) {
      problems.push(`${video.file.name} and ${taken.get(camera.name)} are both for camera ${camera.name}.`);
    }
    taken.set(camera.name, video.file.name);
    if (camera.width && video.width && (camera.width !== video.width || camera.height !== video.height)) {
      problems.push(`${video.file.name} is ${video.width}x${video.height} but camera ${camera.name} is `
        + `${camera.width}x${camera.height}; the video must have its camera's exact frame size.`);
    }
  }
  return [...problems, ...frameRangeProblems(videos)];
}

/** A ball's problems the server would refuse it for (fluidcore.spec.solids.ball_box_problem): its centre
 * outside the scene box, a radius beyond the box's size; against the box where the camera file declares one. */
function ballProblems(ball, box) {
  if (ball.error) return [ball.error];
  if (!ball.value || !box) return [];
  const { center, radius } = ball.value;
  if (!insideBox(center, box)) return [`Ball centre ${fmt(center)} is outside the scene box ${fmt(box.lo)} to ${fmt(box.hi)}.`];
  const size = Math.max(...box.hi.map((h, k) => h - box.lo[k]));
  return radius > size ? [`Ball radius ${radius} is larger than the scene box (${decimal(size)}).`] : [];
}

/** The frame range against its limits and the shortest video's frame count, where the browser could count it. */
function frameRangeProblems(videos) {
  const start = Number($("frame-start").value || 0), endText = $("frame-end").value;
  const end = endText ? Number(endText) : null;
  const bad = limits && !limits.error && (limitProblem("First frame", start, limits["frames[0]"])
    || (end !== null && limitProblem("End frame", end, limits["frames[1]"])));
  if (bad) return [bad];
  if (end !== null && end <= start) return [`End frame must be above the first frame (${start}), got ${endText}.`];
  const counted = videos.filter((v) => v.frames);
  if (!counted.length) return start > 0 && end === null && videos.length ? ["Give an end frame too: this browser could not count the video's frames."] : [];
  const shortest = counted.reduce((a, b) => (b.frames < a.frames ? b : a));
  const limit = `${shortest.file.name} has ${shortest.frames} frames (${shortest.duration.toFixed(2)} s at ${Math.round(shortest.fps)} fps)`;
  if (end !== null && end > shortest.frames) return [`End frame ${end} is past the video: ${limit}.`];
  if (start >= shortest.frames) return [`First frame ${start} is past the video: ${limit}.`];
  return [];
}

function render() {
  const { parsed } = state;
  const summary = $("camera-summary");
  const canvas = $("topdown");
  if (parsed && parsed.cameras) {
    const look = parsed.box ? null : lookPoint(parsed.cameras);
    drawTopDown(canvas, parsed.cameras, parsed.box, look);
    const boxText = parsed.box
      ? `scene box ${fmt(parsed.box.lo)} to ${fmt(parsed.box.hi)}`
      : "no box in the file: the server estimates it from the cameras' common view";
    summary.textContent = `${state.camerasFile.name}: ${parsed.format}, ${parsed.cameras.length} cameras `
      + `(${parsed.cameras.map((c) => c.name).join(", ")}); ${boxText}.`;
  } else {
    canvas.getContext("2d").clearRect(0, 0, canvas.width, canvas.height);
    const fov = fieldOfView().value;
    summary.textContent = parsed ? `${state.camerasFile.name}: ${parsed.format}; the server reads it.`
      : state.camerasFile ? `${state.camerasFile.name} could not be read.`
        : fov !== undefined ? `No camera file: the server makes one camera with a ${fov}° field of view, 1 unit from the `
          + "scene's centre, and a box as wide and tall as the frame there (as `fluidnexus cameras single` does). "
          + "Yellow on the first frame: that box. Its middle section fills the frame and its far face shrinks as the "
          + "field of view widens: right, its edges run with the scene's own (a floor, a table), and the smoke stays inside it."
          : "No camera file yet.";
  }
  const list = $("video-list");
  list.replaceChildren(...state.videos.map(videoCard));
  $("entrainment").disabled = $("motion").value !== "paper";  // the paper model's spreading
  drawFovBox().catch(() => {}); // a refused value is already among the problems
  const problems = uploadProblems(state);
  showList("upload-problems", problems);
  $("upload-button").disabled = problems.length > 0;
  if (!$("scene-name").value && state.camerasFile) $("scene-name").value = state.camerasFile.name.replace(/\.[^.]*$/, "");
}

let boxAsked = 0; // numbers the requests for the box: an answer to an older field of view is dropped

/** With one video and a field of view instead of a camera file: the scene box the server would
 * make (GET /v1/cameras/single: its camera and box, `fluidcore.cameras.single`, projected there)
 * drawn on the video's first frame, so a guessed field of view can be checked against the footage;
 * otherwise every first frame as decoded. */
async function drawFovBox() {
  const asked = ++boxAsked;
  const restore = (v) => v.canvas.getContext("2d").drawImage(v.frame, 0, 0);
  const fov = fieldOfView().value;
  const [video] = state.videos;
  if (state.camerasFile || fov === undefined || state.videos.length !== 1 || !video.frame) {
    state.videos.filter((v) => v.frame).forEach(restore);
    return;
  }
  const query = new URLSearchParams({ width: video.width, height: video.height, fov, up: $("image-up").value });
  let view = null;
  try {
    view = await api(`/v1/cameras/single?${query}`);
  } finally {
    if (asked === boxAsked) restore(video); // a refused value leaves the frame bare; a newer answer draws itself
  }
  if (asked !== boxAsked) return;
  const context = video.canvas.getContext("2d");
  context.strokeStyle = BOX_COLOR;
  context.lineWidth = Math.max(2, Math.round(Math.max(video.width, video.height) / 160));
  context.beginPath();
  for (const [[u0, v0], [u1, v1]] of view.edges) { context.moveTo(u0, v0); context.lineTo(u1, v1); }
  context.stroke();
}

/** The camera a video is for: the one picked beside it, else the one its file name names. */
function cameraOf(video, cameras) {
  return (video.camera && cameras.find((c) => c.name === video.camera)) || matchCamera(video.file.name, cameras);
}

/** The field of view typed for a video without a camera file: {} when empty, {value} or {error}. */
function fieldOfView() {
  const text = $("fov").value.trim();
  if (!text) return {};
  const value = Number(text);
  if (!Number.isFinite(value) || value <= 0 || value >= 180) {
    return { error: `Field of view: give degrees between 0 and 180 (a phone's main camera: 60-70), not "${text}".` };
  }
  return { value };
}

/** The name a video is sent under: its camera's, when it was picked by hand (the server matches a
 * video to its camera by the file name's stem). */
function sentName(video) {
  if (!video.camera) return video.file.name;
  const extension = (/\.[^.]*$/.exec(video.file.name) || [".mp4"])[0];
  return `${video.camera}${extension}`;
}

function videoCard(video) {
  const li = document.createElement("li");
  if (video.canvas) { video.canvas.setAttribute("role", "img"); video.canvas.setAttribute("aria-label", `first frame of ${video.file.name}`); li.append(video.canvas); }
  const cameras = state.parsed && state.parsed.cameras;
  const camera = cameras ? cameraOf(video, cameras) : null;
  const text = document.createElement("p");
  text.textContent = video.error ? `${video.file.name}: ${video.error}`
    : `${video.file.name}: ${video.width}x${video.height}, ${video.duration.toFixed(2)} s`
      + (video.frames ? `, ${video.frames} frames` : "")
      + (camera ? ` → camera ${camera.name}` : "");
  if (video.error) text.className = "bad";
  li.append(text);
  if (cameras) li.append(cameraPicker(video, cameras));
  return li;
}

/** A menu beside a video: which camera it belongs to (by its file name, or one picked). */
function cameraPicker(video, cameras) {
  const select = document.createElement("select");
  select.setAttribute("aria-label", `Camera of ${video.file.name}`);
  const byName = matchCamera(video.file.name, cameras);
  select.append(Object.assign(document.createElement("option"), {
    value: "", textContent: byName ? `by its name (${byName.name})` : "by its name (none matches)",
  }));
  for (const c of cameras) select.append(Object.assign(document.createElement("option"), { value: c.name, textContent: c.name }));
  select.value = video.camera || "";
  select.addEventListener("change", () => { video.camera = select.value || null; render(); });
  return select;
}

const fmt = (v) => `(${v.map((x) => decimal(x, 2)).join(", ")})`;

async function submit(event, onDone) {
  event.preventDefault();
  if (uploadProblems(state).length) return;
  const form = new FormData();
  if (state.camerasFile) form.append("cameras", state.camerasFile, state.camerasFile.name);
  else {
    form.append("fov", String(fieldOfView().value));
    form.append("up", $("image-up").value);
  }
  for (const video of state.videos) form.append("video", video.file, sentName(video));
  form.append("name", $("scene-name").value);
  // sent with the upload, so the server checks it first and a refusal stores nothing
  if ($("auto-reconstruct").checked) form.append("reconstruct", JSON.stringify(reconstructParams()));
  const progress = $("upload-progress"), percent = $("upload-percent"), error = $("upload-error");
  error.textContent = "";
  progress.hidden = false;
  $("upload-button").disabled = true;
  try {
    const scene = await uploadForm("/v1/scenes", form, (fraction) => {
      progress.value = fraction;
      percent.textContent = fraction < 1 ? `${Math.round(fraction * 100)} % sent` : "sent; the server checks the videos…";
    });
    percent.textContent = `Scene ${scene.name || scene.id} stored: ${scene.n_frames} frames at ${scene.fps} fps.`;
    reset();
    onDone(scene, scene.reconstruct_job_id ? { id: scene.reconstruct_job_id } : null);
  } catch (failure) {
    error.textContent = `Upload refused: ${failure.message}`;
    percent.textContent = "";
    progress.hidden = true;
    $("upload-button").disabled = false;
  }
}

/** "START:END" -> { value: [start, end] }, "" -> {}, anything else -> { error } (the background plate's frames). */
function parseFrameSpan(text) {
  const trimmed = text.trim();
  if (!trimmed) return {};
  const match = /^(\d+)\s*:\s*(\d+)$/.exec(trimmed);
  if (!match) return { error: `Background plate: write its frames as START:END (e.g. 0:15), not "${trimmed}".` };
  const [start, end] = [Number(match[1]), Number(match[2])];
  if (end <= start) return { error: `Background plate: its end frame (${end}) must come after its first (${start}).` };
  return { value: [start, end] };
}

/** The reconstruction's params (the API's ReconstructParams); no end frame: to the clip's end. */
function reconstructParams() {
  const params = { quality: $("quality").value, physics: $("physics").value, motion: $("motion").value };
  if ($("air-cells").value !== "") params.air_cells = Number($("air-cells").value);
  if ($("entrainment").checked && params.motion === "paper") params.entrainment = true;
  const source = parseSource($("source").value).value;
  if (source) params.source = $("source-refine").checked ? { ...source, refine: true } : source;
  const ball = parseBall($("ball").value).value;
  if (ball) params.solids = [ball];
  const plate = parseFrameSpan($("background-frames").value).value;
  if (plate) params.background_frames = plate;
  if ($("world-up").value) params.world_up = $("world-up").value;
  const start = Number($("frame-start").value || 0), end = $("frame-end").value;
  if (end) params.frames = [start, Number(end)];
  else if (start > 0) params.frames = [start, Math.min(...state.videos.map((v) => v.frames || Infinity))];
  return params;
}

function reset() {
  generation += 1;
  Object.assign(state, { camerasFile: null, parsed: null, cameraError: null, videos: [] });
  $("upload-files").value = "";
  $("scene-name").value = "";
  $("source").value = "";
  $("source-refine").checked = false;
  $("ball").value = "";
  $("background-frames").value = "";
  $("world-up").value = "";
  $("fov").value = "";
  $("upload-progress").hidden = true;
  $("upload-error").textContent = "";
  render();
}

export function initUpload(onDone) {
  const zone = $("drop-zone");
  zone.addEventListener("dragover", (event) => { event.preventDefault(); zone.classList.add("over"); });
  zone.addEventListener("dragleave", () => zone.classList.remove("over"));
  zone.addEventListener("drop", (event) => {
    event.preventDefault();
    zone.classList.remove("over");
    addFiles([...event.dataTransfer.files]);
  });
  $("upload-files").addEventListener("change", (event) => addFiles([...event.target.files]));
  $("upload-form").addEventListener("submit", (event) => submit(event, onDone));
  $("upload-clear").addEventListener("click", reset);
  for (const id of ["source", "ball", "frame-start", "frame-end", "air-cells", "background-frames", "fov"]) $(id).addEventListener("input", render);
  $("motion").addEventListener("change", render);
  $("image-up").addEventListener("change", render);
  render();
  loadLimits().then((all) => { limits = all.reconstruct; showLimits(); }, (error) => { limits = { error: error.message }; })
    .finally(render);
}

/** The form's own hints from the limits: the air field's range and the choices of quality and physics. */
function showLimits() {
  $("air-cells-range").textContent = allowedText(limits.air_cells);
  bound($("air-cells"), limits.air_cells);
  bound($("frame-start"), limits["frames[0]"]);
  bound($("frame-end"), limits["frames[1]"]);
  for (const name of ["quality", "physics", "motion"]) {
    const select = $(name), labels = new Map([...select.options].map((o) => [o.value, o.textContent]));
    select.replaceChildren(...limits[name].enum.map((value) => new Option(labels.get(value) || value, value, false, value === limits[name].default)));
  }
}
