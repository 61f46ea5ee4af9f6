// The smoke source hint (the API's SourceHint: x, y, z[, radius] in world units) as the upload
// form and the what-if view's depth slider write it, and the stretch of the input ray a
// reconstruction from one view could have put the source on (GET /v1/scenes/{id}:
// geometry.source.depth.range, the nearest and farthest centres inside the box).

/** "a, b, ..." -> numbers (NaN for a part that is not one). */
const numbersOf = (text) => text.split(",").map((part) => (part.trim() ? Number(part) : NaN));

/** "x, y, z[, r]" -> {value: {center, radius?}} (empty text: {value: null}) or {error}; the API's SourceHint. */
export function parseSource(text) {
  if (!text.trim()) return { value: null };
  const numbers = numbersOf(text);
  if (![3, 4].includes(numbers.length) || !numbers.every(Number.isFinite) || (numbers.length === 4 && numbers[3] <= 0)) {
    return { error: `Smoke source: expected x, y, z or x, y, z, radius (radius > 0) in world units, got "${text}".` };
  }
  const value = { center: numbers.slice(0, 3) };
  if (numbers.length === 4) value.radius = numbers[3];
  return { value };
}

/** "x, y, z, r" -> {value: {center, radius}} (empty text: {value: null}) or {error}: a static ball of the
 * scene (the API's SolidBall, one of a reconstruction's params.solids). */
export function parseBall(text) {
  if (!text.trim()) return { value: null };
  const numbers = numbersOf(text);
  if (numbers.length !== 4 || !numbers.every(Number.isFinite) || numbers[3] <= 0) {
    return { error: `Ball: expected x, y, z, radius (radius > 0) in world units, got "${text}".` };
  }
  return { value: { center: numbers.slice(0, 3), radius: numbers[3] } };
}

export function insideBox(point, box) {
  return point.every((c, k) => box.lo[k] <= c && c <= box.hi[k]);
}

/** The point a fraction `t` (0: nearest, 1: farthest) of the way along the range [near, far]. */
export function pointAlong([near, far], t) {
  return near.map((n, k) => n + t * (far[k] - n));
}

/** The fraction along the range [near, far] of the point on it nearest to `point` (clamped to 0..1). */
export function fractionAlong([near, far], point) {
  const d = far.map((f, k) => f - near[k]);
  const length2 = d.reduce((sum, v) => sum + v * v, 0);
  if (!(length2 > 0)) return 0;
  const t = d.reduce((sum, v, k) => sum + v * (point[k] - near[k]), 0) / length2;
  return Math.min(1, Math.max(0, t));
}

/** A hint's text for `center` (world units, 4 decimals: a tenth of a millimetre in a metre-sized box). */
export const hintText = (center) => center.map((c) => Number(c.toFixed(4)).toString()).join(", ");
