// Camera files read in the browser, to show what an upload holds and say what is wrong before
// it is sent. The server's reader (fluidcore.cameras) stays the judge; this mirrors the parts a
// user gets wrong most: names, frame sizes, the scene box.
//
// nerfstudio transforms.json (`frames`) and PINF info.json (`train_videos`, `val_videos`,
// `test_videos`) store a camera-to-world `transform_matrix` in OpenGL axes: the camera sits at
// its last column and looks along minus its third column.

const PINF_LISTS = ["train_videos", "val_videos", "test_videos"];

const stem = (path) => basename(path).replace(/\.[^.]*$/, "");
const basename = (path) => String(path).split(/[\\/]/).pop();
const lookup = (data, entry, key) => (entry[key] ?? data[key] ?? null);

/** Frame size of an entry, or null when only the server can tell (it reads it from the video). */
function entrySize(data, entry) {
  const w = lookup(data, entry, "w"), h = lookup(data, entry, "h");
  if (w !== null && h !== null) return [Number(w), Number(h)];
  const hw = lookup(data, entry, "camera_hw");
  if (Array.isArray(hw) && hw.length === 2) return [Number(hw[1]), Number(hw[0])];
  return null;
}

function entryCamera(data, entry, where) {
  const filePath = entry.file_path ?? entry.file_name ?? null;
  const name = entry.camera ?? (filePath ? stem(filePath) : null);
  if (!name) throw new Error(`${where}: no camera name (field camera) and no file_path to name it by`);
  const m = entry.transform_matrix;
  if (!Array.isArray(m) || m.length < 3 || m.some((row) => !Array.isArray(row) || row.length !== 4)) {
    throw new Error(`${where} (${name}): transform_matrix must be a 4x4 matrix`);
  }
  const size = entrySize(data, entry);
  return {
    name, filePath, width: size && size[0], height: size && size[1],
    center: [m[0][3], m[1][3], m[2][3]].map(Number),
    forward: [-m[0][2], -m[1][2], -m[2][2]].map(Number),
  };
}

/** The box a camera file declares, as fluidcore.cameras.scene_box reads it: FluidNexus's own
 * `scene_box` ({min, max}, written by `fluidnexus cameras single|colmap`) first, else PINF's voxel
 * box; null without either. */
function declaredBox(data) {
  const box = data.scene_box;
  if (box && Array.isArray(box.min) && Array.isArray(box.max)) return { lo: box.min.map(Number), hi: box.max.map(Number) };
  return voxelBox(data);
}

/** World bounds of PINF's voxel box (fluidcore.cameras.boxes.voxel_box), or null without one. */
function voxelBox(data) {
  if (data.voxel_matrix == null || data.voxel_scale == null) return null;
  const scale = Array.isArray(data.voxel_scale) ? data.voxel_scale.map(Number) : [0, 1, 2].map(() => Number(data.voxel_scale));
  const m = data.voxel_matrix;
  const rotation = [0, 1, 2].map((r) => [m[r][2], m[r][1], m[r][0]]); // PINF swaps its x and z columns
  const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  for (const corner of [[0, 0, 0], [0, 0, 1], [0, 1, 0], [0, 1, 1], [1, 0, 0], [1, 0, 1], [1, 1, 0], [1, 1, 1]]) {
    for (let r = 0; r < 3; r++) {
      const v = m[r][3] + corner.reduce((sum, c, k) => sum + rotation[r][k] * c * scale[k], 0);
      lo[r] = Math.min(lo[r], v); hi[r] = Math.max(hi[r], v);
    }
  }
  return { lo, hi };
}

/**
 * Parse a camera file's text. Returns {format, cameras, box}; throws Error with a readable message.
 * A zipped COLMAP model is binary: `{format: "colmap", cameras: null}` (the server reads it).
 */
export function parseCameraFile(name, bytes) {
  const head = new Uint8Array(bytes.slice(0, 4));
  if (head[0] === 0x50 && head[1] === 0x4b) return { format: "COLMAP model (zip)", cameras: null, box: null };
  let data;
  try {
    data = JSON.parse(new TextDecoder().decode(bytes).replace(/^\uFEFF/, ""));
  } catch (error) {
    throw new Error(`${name} is not valid JSON (${error.message})`);
  }
  if (data === null || typeof data !== "object" || Array.isArray(data)) throw new Error(`${name}: the top level must be a JSON object`);
  let lists = Array.isArray(data.frames) ? ["frames"] : PINF_LISTS.filter((k) => Array.isArray(data[k]));
  if (!lists.length) throw new Error(`${name}: no camera entries (expected frames, or PINF's train_videos)`);
  const cameras = new Map();
  for (const list of lists) {
    data[list].forEach((entry, i) => {
      const camera = entryCamera(data, entry, `${list}[${i}]`);
      if (!cameras.has(camera.name)) cameras.set(camera.name, camera);
    });
  }
  if (!cameras.size) throw new Error(`${name}: frames is empty (no cameras)`);
  return { format: lists[0] === "frames" ? "nerfstudio transforms.json" : "PINF info.json", cameras: [...cameras.values()], box: declaredBox(data) };
}

/** The camera a video belongs to (fluidcore's rule: file stem = camera name or its file_path's name), or null. */
export function matchCamera(filename, cameras) {
  const s = stem(filename);
  for (const camera of cameras) {
    const aliases = new Set([camera.name]);
    if (camera.filePath) { aliases.add(basename(camera.filePath)); aliases.add(stem(camera.filePath)); }
    if (aliases.has(s) || aliases.has(filename)) return camera;
  }
  return null;
}

/** The point nearest to every camera's optical axis (least squares): where the cameras look. */
export function lookPoint(cameras) {
  const a = [[0, 0, 0], [0, 0, 0], [0, 0, 0]], b = [0, 0, 0];
  for (const { center, forward } of cameras) {
    const n = Math.hypot(...forward) || 1, d = forward.map((v) => v / n);
    for (let i = 0; i < 3; i++) {
      for (let j = 0; j < 3; j++) {
        const p = (i === j ? 1 : 0) - d[i] * d[j];
        a[i][j] += p; b[i] += p * center[j];
      }
    }
  }
  return solve3(a, b);
}

function solve3(a, b) {
  const det = (m) => m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
    + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
  const d = det(a);
  if (Math.abs(d) < 1e-9) return null; // one camera, or all looking the same way
  return [0, 1, 2].map((k) => det(a.map((row, i) => row.map((v, j) => (j === k ? b[i] : v)))) / d);
}

/** Draw cameras (dot + viewing direction + name) and the box on the x-z plane, y up (seen from above). */
export function drawTopDown(canvas, cameras, box, look) {
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const points = cameras.map((c) => [c.center[0], c.center[2]]);
  if (box) points.push([box.lo[0], box.lo[2]], [box.hi[0], box.hi[2]]);
  if (look) points.push([look[0], look[2]]);
  if (!points.length) return;
  const xs = points.map((p) => p[0]), zs = points.map((p) => p[1]);
  const span = Math.max(Math.max(...xs) - Math.min(...xs), Math.max(...zs) - Math.min(...zs), 1e-6);
  const scale = (Math.min(canvas.width, canvas.height) - 70) / span;
  const cx = (Math.max(...xs) + Math.min(...xs)) / 2, cz = (Math.max(...zs) + Math.min(...zs)) / 2;
  const toPx = (x, z) => [canvas.width / 2 + (x - cx) * scale, canvas.height / 2 + (z - cz) * scale];
  ctx.font = "12px system-ui, sans-serif";
  if (box) {
    const [x0, z0] = toPx(box.lo[0], box.lo[2]), [x1, z1] = toPx(box.hi[0], box.hi[2]);
    ctx.fillStyle = "rgba(29,95,168,0.12)"; ctx.strokeStyle = "#1d5fa8"; ctx.lineWidth = 2;
    ctx.fillRect(x0, z0, x1 - x0, z1 - z0); ctx.strokeRect(x0, z0, x1 - x0, z1 - z0);
    ctx.fillStyle = "#1d5fa8"; ctx.fillText("scene box", x0 + 4, z0 + 14);
  }
  if (look) {
    const [x, z] = toPx(look[0], look[2]);
    ctx.strokeStyle = "#1d5fa8"; ctx.beginPath(); ctx.arc(x, z, 6, 0, 2 * Math.PI); ctx.stroke();
    ctx.fillStyle = "#1d5fa8"; ctx.fillText("cameras look here", x + 8, z + 4);
  }
  for (const camera of cameras) {
    const [x, z] = toPx(camera.center[0], camera.center[2]);
    const f = [camera.forward[0], camera.forward[2]], n = Math.hypot(...f) || 1;
    ctx.strokeStyle = "#333"; ctx.lineWidth = 2; ctx.beginPath(); ctx.moveTo(x, z);
    ctx.lineTo(x + (f[0] / n) * 24, z + (f[1] / n) * 24); ctx.stroke();
    ctx.fillStyle = "#c0392b"; ctx.beginPath(); ctx.arc(x, z, 5, 0, 2 * Math.PI); ctx.fill();
    ctx.fillStyle = "#222"; ctx.fillText(camera.name, x + 7, z - 7);
  }
  ctx.fillStyle = "#666"; ctx.fillText("x →   z ↓   (seen from +y)", 6, canvas.height - 6);
}
