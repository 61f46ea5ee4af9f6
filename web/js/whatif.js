// What-if view: wind and ball controls drawn over a 3D view of the reconstructed particles and
// the scene box, and, for a run that simulates the air, arrows of the air's velocity sampled from
// the saved frame (the particles answer's `air`). The form checks its values against the API's
// limits (GET /v1/limits) and refuses a ball outside the box (naming the box's limits) before
// anything is sent; the wind's arrows are the API's accelerations (POST /v1/wind/accelerations,
// which also refuses a wind the model refuses); the server checks everything again
// (fluidcore.spec.controls). For a reconstruction from one view, the view also draws the stretch of
// the input ray its source could lie on (GET /v1/scenes/{id}: geometry.source.depth), and a slider
// along it fills the source hint of a new reconstruction of the scene.

import { $, showList } from "./dom.js";
import { api } from "./api.js";
import { boxText, decimal, point } from "./format.js";
import { describeJob, jobs, refreshJobs } from "./jobs.js";
import { bound, limitProblem, loadLimits } from "./limits.js";
import { fractionAlong, hintText, insideBox, parseSource, pointAlong } from "./source.js";
import {
  ArrowHelper, Box3, Box3Helper, BufferAttribute, BufferGeometry, Color, Group, Mesh, MeshBasicMaterial,
  OrbitControls, PerspectiveCamera, Points, PointsMaterial, Scene, SphereGeometry, Vector3, WebGLRenderer,
} from "../vendor/three.min.js";

const num = (id) => Number($(id).value);
// The form's number inputs whose spinners take their range from a field's limits.
const BOUNDED = [["wi-frames", "frames"], ["wi-from", "from_frame"], ["wind-strength", "wind.strength"],
  ["wind-growth", "wind.growth"], ["wind-start", "wind.start_frame"], ["ball-start", "ball.start_frame"]];
const vec = (...ids) => ids.map(num);
const WIND_ARROWS = 5; // arrows up the box's height show how the wind grows
// The default wind moves smoke at rest a quarter of the box's width (along the wind) in
// WIND_HORIZON frames: clearly visible, and inside the box (a constant 2 units/s² blew ScalarFlow's
// smoke, 0.49 units wide at 30 fps, out of the box within 15 frames).
const WIND_HORIZON = 15;
const WIND_SHIFT = 0.25;
const RETRY_MS = 3000;
const AIR_COLOR = 0xb36bff; // violet: red is the ball, blue the wind, yellow and green the source
// An arrow per air sample at least this fraction of the fastest one: slower air is clutter.
const AIR_MIN_SHARE = 0.05;

let view = null; // {renderer, scene, camera, controls, overlay}
let run = null; // {jobId, box: {lo, hi}, up, source, frames, dt}
let retry = null;
let onSubmitted = () => {};
let onReconstruct = () => {};
let depth = null; // {jobId, sceneId, params, range: [near, far], center, radius, cue}: one view's source
let hintTouched = false; // until the slider or the hint is used, an empty hint is no problem to show
let limits = null; // the interact parameters' limits (GET /v1/limits)
let windRefusal = null; // the API's refusal of the form's wind, from the last arrows asked for
let windAsked = 0; // numbers the requests for arrows: an answer to an older one is dropped

/** The values in the form, as the API's interact params. */
function formParams() {
  const params = { frames: num("wi-frames") };
  if ($("wi-from").value.trim() !== "") params.from_frame = num("wi-from");
  if ($("wind-on").checked) {
    params.wind = { direction: vec("wind-dx", "wind-dy", "wind-dz"), strength: num("wind-strength"),
      growth: num("wind-growth"), profile: $("wind-profile").value, start_frame: num("wind-start") };
  }
  if ($("ball-on").checked) {
    params.ball = { center: vec("ball-cx", "ball-cy", "ball-cz"), radius: num("ball-radius"),
      start_frame: num("ball-start"), velocity: vec("ball-vx", "ball-vy", "ball-vz") };
  }
  return params;
}

/** What the server would refuse, in words: values outside the API's `limits` of each field, and
 * against the parent run, a ball outside its box, a branch frame it has not finished, an
 * intervention starting after the new frames. */
function whatifProblems(params, limits, box, frames) {
  const problems = [];
  const check = (name, value, field) => {
    const problem = limitProblem(name, value, limits[field]);
    if (problem) problems.push(problem);
  };
  check("New frames", params.frames, "frames");
  if (params.from_frame !== undefined) {
    check("Branch frame", params.from_frame, "from_frame");
    if (frames && frames.length && Number.isInteger(params.from_frame) && !frames.includes(params.from_frame)) {
      problems.push(`Branch frame ${params.from_frame} is not a finished frame of the run (frames ${frames[0]} to ${frames[frames.length - 1]}).`);
    }
  }
  if (!params.wind && !params.ball) problems.push("Turn on the wind, the ball, or both.");
  if (params.wind) {
    const { strength, growth, start_frame: start } = params.wind;
    check("Wind strength", strength, "wind.strength");
    check("Wind growth", growth, "wind.growth");
    check("Wind start frame", start, "wind.start_frame");
    if (start >= params.frames) problems.push(`Wind start frame ${start} is not within the ${params.frames} new frames.`);
  }
  if (params.ball) {
    const { center, radius, start_frame: start, velocity } = params.ball;
    if (box) {
      "xyz".split("").forEach((axis, i) => {
        if (!(center[i] >= box.lo[i] && center[i] <= box.hi[i])) {
          problems.push(`Ball centre ${axis} = ${center[i]} is outside the scene box: ${axis} must be from ${fmt(box.lo[i])} to ${fmt(box.hi[i])}.`);
        }
      });
      const extent = Math.max(...box.hi.map((h, i) => h - box.lo[i]));
      if (radius > extent) problems.push(`Ball radius ${radius} is larger than the scene box (${fmt(extent)}).`);
    }
    check("Ball radius", radius, "ball.radius");
    if (velocity.some((v) => !Number.isFinite(v))) problems.push("Ball velocity must be three numbers.");
    check("Ball start frame", start, "ball.start_frame");
    if (start >= params.frames) problems.push(`Ball start frame ${start} is not within the ${params.frames} new frames.`);
  }
  return problems;
}

const fmt = (v) => decimal(v);

function createView() {
  const canvas = $("scene3d");
  let renderer;
  try {
    renderer = new WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  } catch (error) {
    return null; // no WebGL: the form still works, the view says why it is empty
  }
  renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
  renderer.setSize(canvas.clientWidth || canvas.width, (canvas.clientWidth || canvas.width) * 0.75, false);
  const scene = new Scene();
  scene.background = new Color(0x14161a);
  const camera = new PerspectiveCamera(40, 4 / 3, 0.001, 1000);
  const controls = new OrbitControls(camera, canvas);
  controls.listenToKeyEvents(canvas);
  const overlay = new Group(), sourceLayer = new Group(), air = new Group(), solids = new Group();
  scene.add(overlay, sourceLayer, air, solids);
  const current = { renderer, scene, camera, controls, overlay, sourceLayer, air, solids, points: null, box: null };
  controls.addEventListener("change", () => renderer.render(scene, camera));
  return current;
}

function showParticles(data) {
  const { scene, camera, controls } = view;
  if (view.points) scene.remove(view.points);
  if (view.box) scene.remove(view.box);
  const geometry = new BufferGeometry();
  geometry.setAttribute("position", new BufferAttribute(new Float32Array(data.positions), 3));
  const lo = new Vector3(...data.scene.box_lo), hi = new Vector3(...data.scene.box_hi);
  const size = hi.clone().sub(lo).length();
  // a few hundred particles fill a plume only drawn large: 1/60 of the box diagonal each
  view.points = new Points(geometry, new PointsMaterial({ color: 0xe8edf3, size: size / 60, transparent: true, opacity: 0.85, depthWrite: false }));
  view.box = new Box3Helper(new Box3(lo, hi), 0x4f9bea);
  scene.add(view.points, view.box);
  view.solids.clear(); // the run's own balls (its scene's solids), drawn as the what-if's ball is
  for (const solid of data.scene.solids || []) view.solids.add(ballMesh(solid.center, solid.radius));
  const centre = lo.clone().add(hi).multiplyScalar(0.5);
  const up = new Vector3(...data.scene.up).normalize();
  camera.up.copy(up);
  camera.position.copy(centre).addScaledVector(sideOf(up), 1.6 * size).addScaledVector(up, 0.5 * size);
  controls.target.copy(centre);
  controls.update();
}

// Directions the view looks from, in order of preference: a little off +z, else off +x (far from
// parallel, so the second is long enough across any up the first is not).
const SIDES = [new Vector3(0.4, 0, 1), new Vector3(1, 0.4, 0)];

/** A unit vector perpendicular to `up` (unit) to place the camera along, so the view looks across
 * the plume whichever axis is up (+y, or +z for a Blender scene), never down it: the first of
 * SIDES with its part along `up` removed. */
function sideOf(up) {
  const across = (candidate) => candidate.clone().addScaledVector(up, -candidate.dot(up));
  const side = across(SIDES[0]);
  return (side.lengthSq() > 0.1 ? side : across(SIDES[1])).normalize();
}

/** The speed (units/s) at each of the air's sampled points. */
function airSpeeds(air) {
  const speeds = [];
  for (let i = 0; i < air.velocities.length; i += 3) speeds.push(Math.hypot(...air.velocities.slice(i, i + 3)));
  return speeds;
}

/** The air's arrows from the particles answer's `air` ({points, velocities}, flat xyz lists),
 * longest for the fastest air (an eighth of the box's diagonal); returns how many were drawn. */
function showAir(air, box) {
  view.air.clear();
  if (!air) return 0;
  const size = new Vector3(...box.hi).sub(new Vector3(...box.lo)).length();
  const speeds = airSpeeds(air);
  const fastest = Math.max(0, ...speeds);
  if (!(fastest > 0)) return 0;
  speeds.forEach((speed, k) => {
    if (speed < AIR_MIN_SHARE * fastest) return;
    const dir = new Vector3(...air.velocities.slice(3 * k, 3 * k + 3)).divideScalar(speed);
    const length = (size / 8) * (speed / fastest);
    view.air.add(new ArrowHelper(dir, new Vector3(...air.points.slice(3 * k, 3 * k + 3)), length, AIR_COLOR, 0.3 * length, 0.12 * length));
  });
  return view.air.children.length;
}

/** In words: what the arrows show, or that the run's air is still. */
function airSummary(air, arrows) {
  if (!air) return " This run does not simulate the air (still air): no air arrows.";
  const speeds = airSpeeds(air);
  const fastest = Math.max(0, ...speeds);
  return ` Violet arrows: the air's velocity at ${arrows} of ${speeds.length} sampled points (fastest ${fmt(fastest)} units/s).`;
}

/** Redraw the ball and the wind arrows from the form's current values. */
function drawOverlay() {
  if (!run) return;
  const params = formParams();
  const lo = new Vector3(...run.box.lo), hi = new Vector3(...run.box.hi);
  const size = hi.clone().sub(lo).length();
  if (view) drawBall(params.ball, size);
  drawWind(params.wind, lo, hi, size).catch(showError); // without WebGL too: the API's verdict on the wind
}

/** The ball (red) and its velocity arrow on a cleared overlay; the wind's arrows join it when the API answers.
 * The ball is a translucent shell with a wireframe, drawn before the smoke and writing no depth: the
 * smoke in and around it is drawn over it and stays visible (a ball drawn over the smoke hid it). */
function drawBall(ball, size) {
  const { overlay, renderer, scene, camera } = view;
  overlay.clear();
  if (ball && ball.radius > 0 && ball.center.every(Number.isFinite)) {
    const mesh = ballMesh(ball.center, ball.radius);
    overlay.add(mesh);
    const v = new Vector3(...ball.velocity);
    if (v.length() > 0) overlay.add(new ArrowHelper(v.clone().normalize(), mesh.position, 0.3 * size, 0xe74c3c));
  }
  renderer.render(scene, camera);
}

/** A ball at `center` of `radius` (world units) as this view draws every ball, the what-if's and the
 * scene's solids: a translucent red shell with a wireframe, before the smoke and writing no depth. */
function ballMesh(center, radius) {
  const behindSmoke = (material) => new MeshBasicMaterial({ color: 0xe74c3c, transparent: true, depthWrite: false, ...material });
  const mesh = new Mesh(new SphereGeometry(radius, 24, 16), behindSmoke({ opacity: 0.3 }));
  const wire = new Mesh(new SphereGeometry(radius, 12, 8), behindSmoke({ opacity: 0.6, wireframe: true }));
  mesh.renderOrder = wire.renderOrder = -1; // the smoke's points (order 0) come after
  mesh.add(wire);
  mesh.position.set(...center);
  return mesh;
}

/** The wind's arrows up the box's height, each as long as the API's acceleration there (the
 * simulator's gain, fluidcore.spec.controls.WindParams.gain); a wind the API refuses draws none
 * and its reason joins the form's problems. */
async function drawWind(wind, lo, hi, size) {
  const asked = ++windAsked;
  let answer = null;
  if (wind) {
    const up = new Vector3(...run.up).normalize();
    const heights = [...Array(WIND_ARROWS).keys()].map((i) => lo.dot(up) + ((i + 0.5) / WIND_ARROWS) * hi.clone().sub(lo).dot(up));
    const body = { wind, source_height: up.dot(new Vector3(...(run.source.center || [0, 0, 0]))), heights };
    try {
      answer = { heights, ...(await api("/v1/wind/accelerations", { method: "POST", body })) };
    } catch (error) {
      if (asked !== windAsked) return;
      if (error.status !== 422) throw error;
      answer = { refusal: `Wind: ${error.message}` };
    }
  }
  if (asked !== windAsked) return; // the form changed meanwhile: a newer request draws
  windRefusal = answer && answer.refusal ? answer.refusal : null;
  validate();
  if (!view || !answer || !answer.accelerations) return;
  const { overlay, renderer, scene, camera } = view;
  const dir = new Vector3(...wind.direction).normalize(), up = new Vector3(...run.up).normalize();
  const centre = lo.clone().add(hi).multiplyScalar(0.5);
  const peak = Math.max(...answer.accelerations, 1e-12);
  answer.heights.forEach((h, i) => {
    const at = centre.clone().addScaledVector(up, h - centre.dot(up)).addScaledVector(dir, -0.25 * size);
    const length = Math.max(0.02 * size, (0.25 * size * answer.accelerations[i]) / peak); // short: the smoke stays in view
    overlay.add(new ArrowHelper(dir, at, length, 0x3498db, 0.2 * length, 0.08 * length));
  });
  renderer.render(scene, camera);
}

function showLimits(box) {
  $("box-limits").textContent = `${boxText(box)}.`;
  ["ball-cx", "ball-cy", "ball-cz"].forEach((id, i) => { $(id).min = String(box.lo[i]); $(id).max = String(box.hi[i]); });
  const centre = box.lo.map((l, i) => (l + box.hi[i]) / 2);
  if ($("ball-cx").dataset.placedFor !== run.jobId) { // a new run: start with the ball in the middle of its box
    ["ball-cx", "ball-cy", "ball-cz"].forEach((id, i) => { $(id).value = fmt(centre[i]); });
    $("ball-radius").value = fmt(0.15 * Math.min(...box.hi.map((h, i) => h - box.lo[i])));
    const strength = defaultWindStrength(box, vec("wind-dx", "wind-dy", "wind-dz"), run.dt);
    if (strength !== null) $("wind-strength").value = fmt(strength);
    $("wi-from").placeholder = `last: ${run.frames[run.frames.length - 1]}`;
    $("ball-cx").dataset.placedFor = run.jobId;
  }
}

/** Wind acceleration (units/s²) that moves smoke at rest WIND_SHIFT of the box's width along
 * `direction` in WIND_HORIZON frames: ½ a t² = shift. null without a direction or time step. */
function defaultWindStrength(box, direction, dt) {
  const norm = Math.hypot(...direction);
  if (!(norm > 0) || !(dt > 0)) return null;
  const width = box.hi.reduce((sum, h, i) => sum + Math.abs((h - box.lo[i]) * direction[i]) / norm, 0);
  const seconds = WIND_HORIZON * dt;
  return (2 * WIND_SHIFT * width) / (seconds * seconds);
}

function validate() {
  const problems = limits ? whatifProblems(formParams(), limits, run && run.box, run && run.frames) : ["Reading the server's limits…"];
  if (windRefusal) problems.push(windRefusal);
  showList("whatif-problems", problems);
  for (const id of ["ball-cx", "ball-cy", "ball-cz", "ball-radius"]) {
    $(id).setAttribute("aria-invalid", String(problems.some((p) => p.includes(`centre ${id.slice(-1)} `) || (id === "ball-radius" && p.startsWith("Ball radius")))));
  }
  return problems;
}

async function loadParticles(jobId) {
  clearTimeout(retry);
  try {
    const data = await api(`/v1/jobs/${jobId}/particles?max_points=20000`);
    run = { jobId, box: { lo: data.scene.box_lo, hi: data.scene.box_hi }, up: data.scene.up, source: data.scene.source,
      frames: data.frames, dt: data.scene.dt };
    showLimits(run.box);
    if (view) showParticles(data);
    const arrows = view ? showAir(data.air, run.box) : 0;
    $("whatif-summary").textContent += ` Showing ${data.positions.length / 3} of ${data.total} particles at frame ${data.frame}; `
      + "the what-if continues after the run's last frame, or after the branch frame you choose." + airSummary(data.air, arrows);
    validate();
    drawOverlay();
  } catch (error) {
    if (error.status !== 409) throw error;
    $("whatif-summary").textContent = `${error.message}: the particles and box appear when it writes its first frame.`;
    retry = setTimeout(() => loadParticles(jobId).catch(showError), RETRY_MS);
  }
}

const showError = (error) => { $("whatif-error").textContent = error.message; };

export async function showWhatif(jobId) {
  run = null;
  depth = null;
  $("source-form").hidden = true;
  if (view) { view.sourceLayer.clear(); view.renderer.render(view.scene, view.camera); }
  $("whatif-error").textContent = "";
  $("box-limits").textContent = ""; // filled again when this run's box has loaded
  $("wi-from").value = ""; // each opening starts from the run's last frame, not the branch sent before
  view = view || createView();
  try {
    limits = (await loadLimits()).interact;
  } catch (error) {
    showError(error);
  }
  if (limits) BOUNDED.forEach(([id, field]) => bound($(id), limits[field]));
  await refreshJobs();
  const job = jobs.get(jobId) || (await api(`/v1/jobs/${jobId}`));
  $("whatif-title").textContent = `What if: continue ${describeJob(job)}`;
  $("whatif-summary").textContent = job.state === "succeeded" ? ""
    : `${describeJob(job)} is ${job.state}; what-ifs sent now run when it succeeds.`;
  if (!view) $("whatif-summary").textContent += " This browser has no WebGL, so the 3D view stays empty.";
  await loadParticles(jobId).catch(showError);
  if (job.type === "reconstruct" && job.state === "succeeded") await loadSourceDepth(job).catch(showSourceError);
}

const CUES = {
  "box axis": "where the ray passes nearest the box's vertical axis, a guess",
  floor: "resting on the floor the camera looks down on",
  "generated views": "triangulated with the generated views",
  given: "at the hint's centre",
};

/** The scene's source as its reconstruction `job` found it; the depth panel when one view left depth open. */
async function loadSourceDepth(job) {
  const source = (await api(`/v1/scenes/${job.scene_id}`)).geometry.source;
  if (!source || source.job_id !== job.id || !source.depth || !source.depth.range) return;
  depth = { jobId: job.id, sceneId: job.scene_id, params: job.params, range: source.depth.range,
    center: source.center, radius: source.radius, cue: source.depth.cue };
  const [near, far] = depth.range;
  $("source-depth").textContent = `One view cannot tell how far away the source is: the video allows its centre anywhere `
    + `on the input ray inside the box, from ${point(near)} (nearest) to ${point(far)} (farthest), the green line. `
    + `This reconstruction put it at ${point(depth.center)}, radius ${fmt(depth.radius)} (${CUES[depth.cue] || depth.cue}). `
    + "Slide it to where you know it is, or type a hint, then reconstruct the scene with it.";
  $("source-along").value = String(fractionAlong(depth.range, depth.center));
  $("source-hint").value = "";
  $("source-error").textContent = "";
  $("source-form").hidden = false;
  hintTouched = false;
  checkHint();
  drawSource();
}

const showSourceError = (error) => { $("source-error").textContent = error.message; };

/** The hint in the field, or null; its problems listed (and the button off) meanwhile. An empty
 * hint keeps the button off but is listed only once the slider or the field was used: a form
 * just opened is not an error. */
function checkHint() {
  const parsed = parseSource($("source-hint").value);
  const problems = parsed.error ? [parsed.error] : [];
  if (parsed.value && run && !insideBox(parsed.value.center, run.box)) {
    problems.push(`Smoke source ${point(parsed.value.center)} is outside the scene box ${point(run.box.lo)} to ${point(run.box.hi)}.`);
  }
  const empty = !parsed.error && !parsed.value;
  if (empty && hintTouched) problems.push("Slide along the ray or type a source hint first.");
  showList("source-problems", problems);
  $("source-submit").disabled = empty || problems.length > 0;
  return empty || problems.length ? null : parsed.value;
}

/** The input ray's stretch (green, pointing away from the camera), the source used (yellow), the hint (green). */
function drawSource() {
  if (!view || !depth || !run) return;
  const { sourceLayer, renderer, scene, camera } = view;
  sourceLayer.clear();
  const near = new Vector3(...depth.range[0]), far = new Vector3(...depth.range[1]);
  const length = far.distanceTo(near);
  if (length > 0) {
    const head = Math.min(0.3 * length, 0.05 * run.box.hi.reduce((sum, h, i) => sum + h - run.box.lo[i], 0));
    sourceLayer.add(new ArrowHelper(far.clone().sub(near).normalize(), near, length, 0x2ecc71, head, 0.5 * head));
  }
  const sphere = (center, radius, color) => {
    const mesh = new Mesh(new SphereGeometry(radius, 20, 14), new MeshBasicMaterial({ color, transparent: true, opacity: 0.6 }));
    mesh.position.set(...center);
    sourceLayer.add(mesh);
  };
  sphere(depth.center, depth.radius, 0xf1c40f);
  const hint = parseSource($("source-hint").value).value;
  if (hint) sphere(hint.center, hint.radius || depth.radius, 0x2ecc71);
  renderer.render(scene, camera);
}

/** A new reconstruction of the scene, with the reconstruction's own params and the hint as its source. */
async function reconstructWithHint(event) {
  event.preventDefault();
  $("source-error").textContent = "";
  const source = depth && checkHint();
  if (!source) return;
  try {
    const job = await api("/v1/jobs", { method: "POST",
      body: { type: "reconstruct", scene_id: depth.sceneId, params: { ...depth.params, source } } });
    onReconstruct(job);
  } catch (error) {
    $("source-error").textContent = `Refused: ${error.message}`;
  }
}

export function leaveWhatif() { clearTimeout(retry); }

/** Send the what-if, and the factual prediction it plays next to (unless one is already there, or
 * it branches inside the run: its side-by-side shows the run without the intervention); tell
 * `onSubmitted` which: (interact, {queued, existing, branched}). */
async function submit(event) {
  event.preventDefault();
  $("whatif-error").textContent = "";
  if (!run || validate().length) {
    if (!run) $("whatif-error").textContent = "Wait until the run's particles and box are shown.";
    return;
  }
  const params = formParams();
  try {
    const interact = await api("/v1/jobs", { method: "POST", body: { type: "interact", parent_job_id: run.jobId, params } });
    await refreshJobs();
    const branched = params.from_frame !== undefined;
    const existing = branched ? null : [...jobs.values()].find((j) => j.type === "predict"
      && j.parent_job_id === run.jobId && j.params.frames === params.frames && j.state !== "failed" && j.state !== "cancelled");
    const queued = branched || existing ? null : await api("/v1/jobs", { method: "POST",
      body: { type: "predict", parent_job_id: run.jobId, params: { frames: params.frames } } });
    onSubmitted(interact, { queued, existing, branched: branched ? params.from_frame : null });
  } catch (error) {
    $("whatif-error").textContent = `Refused: ${error.message}`;
  }
}

export function initWhatif(submitted, reconstructed) {
  onSubmitted = submitted;
  onReconstruct = reconstructed;
  $("source-along").addEventListener("input", () => {
    hintTouched = true;
    if (depth) $("source-hint").value = hintText(pointAlong(depth.range, Number($("source-along").value)));
    checkHint();
    drawSource();
  });
  $("source-hint").addEventListener("input", () => { hintTouched = true; checkHint(); drawSource(); });
  $("source-form").addEventListener("submit", reconstructWithHint);
  $("whatif-form").addEventListener("input", () => { validate(); drawOverlay(); });
  $("whatif-form").addEventListener("submit", submit);
}
