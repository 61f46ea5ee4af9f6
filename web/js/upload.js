// Upload view: drop a camera file and videos, see them (first frames, cameras and box from
// above), read what is wrong before sending, then send with a progress bar.

import { $, showList } from "./dom.js";
import { api, uploadForm } from "./api.js";
import { drawTopDown, lookPoint, matchCamera, parseCameraFile } from "./cameras.js";

const VIDEO_NAME = /\.(mp4|mov|m4v|webm|mkv|avi)$/i;

const state = { camerasFile: null, parsed: null, cameraError: null, videos: [] };

/** The first frame of a video, decoded by the browser: {width, height, duration} and a canvas. */
function firstFrame(file) {
  return new Promise((resolve) => {
    const video = document.createElement("video");
    const url = URL.createObjectURL(file);
    const done = (result) => { URL.revokeObjectURL(url); resolve(result); };
    video.muted = true;
    video.preload = "auto";
    video.addEventListener("loadeddata", () => {
      const canvas = document.createElement("canvas");
      canvas.width = video.videoWidth; canvas.height = video.videoHeight;
      canvas.getContext("2d").drawImage(video, 0, 0);
      done({ width: video.videoWidth, height: video.videoHeight, duration: video.duration, canvas });
    }, { once: true });
    video.addEventListener("error", () => done({ error: "this browser cannot decode it (the server will still check it)" }), { once: true });
    video.src = url;
  });
}

async function addFiles(files) {
  for (const file of files) {
    if (VIDEO_NAME.test(file.name) || file.type.startsWith("video/")) {
      state.videos = state.videos.filter((v) => v.file.name !== file.name);
      state.videos.push({ file, ...(await firstFrame(file)) });
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
  if (!camerasFile) problems.push("Add a camera file (transforms.json, info.json or a zipped COLMAP model).");
  if (cameraError) problems.push(`Camera file: ${cameraError}`);
  if (!videos.length) problems.push("Add at least one video, named after its camera.");
  const cameras = parsed && parsed.cameras;
  const source = parseSource($("source").value);
  if (source.error) problems.push(source.error);
  else if (source.value && parsed && parsed.box && !insideBox(source.value.center, parsed.box)) {
    problems.push(`Smoke source ${fmt(source.value.center)} is outside the scene box ${fmt(parsed.box.lo)} to ${fmt(parsed.box.hi)}.`);
  }
  if (!cameras) return problems;
  const known = cameras.map((c) => c.name).join(", ");
  const taken = new Map();
  for (const video of videos) {
    const camera = matchCamera(video.file.name, cameras);
    if (!camera) {
      problems.push(`${video.file.name} matches no camera; name it after one of: ${known}.`);
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
  return problems;
}

/** "x, y, z[, r]" -> {value: {center, radius?}} (empty text: {value: null}) or {error}; the API's SourceHint. */
function parseSource(text) {
  if (!text.trim()) return { value: null };
  const numbers = text.split(",").map((part) => (part.trim() ? Number(part) : NaN));
  if (![3, 4].includes(numbers.length) || !numbers.every(Number.isFinite) || (numbers.length === 4 && numbers[3] <= 0)) {
    return { error: `Smoke source: expected x, y, z or x, y, z, radius (radius > 0) in world units, got "${text}".` };
  }
  const value = { center: numbers.slice(0, 3) };
  if (numbers.length === 4) value.radius = numbers[3];
  return { value };
}

function insideBox(point, box) {
  return point.every((c, k) => box.lo[k] <= c && c <= box.hi[k]);
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
    summary.textContent = parsed ? `${state.camerasFile.name}: ${parsed.format}; the server reads it.`
      : state.camerasFile ? `${state.camerasFile.name} could not be read.` : "No camera file yet.";
  }
  const list = $("video-list");
  list.replaceChildren(...state.videos.map(videoCard));
  const problems = uploadProblems(state);
  showList("upload-problems", problems);
  $("upload-button").disabled = problems.length > 0;
  if (!$("scene-name").value && state.camerasFile) $("scene-name").value = state.camerasFile.name.replace(/\.[^.]*$/, "");
}

function videoCard(video) {
  const li = document.createElement("li");
  if (video.canvas) { video.canvas.setAttribute("role", "img"); video.canvas.setAttribute("aria-label", `first frame of ${video.file.name}`); li.append(video.canvas); }
  const camera = state.parsed && state.parsed.cameras ? matchCamera(video.file.name, state.parsed.cameras) : null;
  const text = document.createElement("p");
  text.textContent = video.error ? `${video.file.name}: ${video.error}`
    : `${video.file.name}: ${video.width}x${video.height}, ${video.duration.toFixed(2)} s`
      + (camera ? ` → camera ${camera.name}` : "");
  if (video.error) text.className = "bad";
  li.append(text);
  return li;
}

const fmt = (v) => `(${v.map((x) => x.toFixed(2)).join(", ")})`;

async function submit(event, onDone) {
  event.preventDefault();
  if (uploadProblems(state).length) return;
  const form = new FormData();
  form.append("cameras", state.camerasFile, state.camerasFile.name);
  for (const video of state.videos) form.append("video", video.file, video.file.name);
  form.append("name", $("scene-name").value);
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
    let job = null;
    if ($("auto-reconstruct").checked) job = await api("/v1/jobs", { method: "POST", body: reconstructRequest(scene) });
    reset();
    onDone(scene, job);
  } catch (failure) {
    error.textContent = `Upload refused: ${failure.message}`;
    percent.textContent = "";
    progress.hidden = true;
    $("upload-button").disabled = false;
  }
}

function reconstructRequest(scene) {
  const params = { quality: $("quality").value, physics: $("physics").value };
  const source = parseSource($("source").value).value;
  if (source) params.source = source;
  const start = Number($("frame-start").value || 0), end = $("frame-end").value;
  if (start > 0 || end) params.frames = [start, end ? Number(end) : scene.n_frames];
  return { type: "reconstruct", scene_id: scene.id, params };
}

function reset() {
  Object.assign(state, { camerasFile: null, parsed: null, cameraError: null, videos: [] });
  $("upload-files").value = "";
  $("scene-name").value = "";
  $("source").value = "";
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
  $("source").addEventListener("input", render);
  render();
}
