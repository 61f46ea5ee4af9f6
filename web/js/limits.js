// The bounds of every job parameter as the API declares them (GET /v1/limits, derived from the
// parameter models' JSON Schema: fluidcore.spec.limits). The forms check their values against
// these before anything is sent and hold no bounds of their own; the server checks again.

import { api } from "./api.js";

let pending = null;

/** The limits by job type, then by field path ("air_cells", "frames[1]", "wind.strength"); read once. */
export function loadLimits() {
  pending = pending || api("/v1/limits").catch((error) => { pending = null; throw error; });
  return pending;
}

const kind = (limit) => (limit.type === "integer" ? "a whole number" : "a number");

/** A bound in words: "a whole number from 8 to 128", "a number more than 0", "one of a, b". */
function range(limit) {
  if (limit.enum) return `one of ${limit.enum.join(", ")}`;
  if (limit.minimum !== undefined && limit.maximum !== undefined) return `${kind(limit)} from ${limit.minimum} to ${limit.maximum}`;
  const low = limit.exclusiveMinimum !== undefined ? `more than ${limit.exclusiveMinimum}`
    : limit.minimum !== undefined ? `at least ${limit.minimum}` : null;
  const high = limit.exclusiveMaximum !== undefined ? `less than ${limit.exclusiveMaximum}`
    : limit.maximum !== undefined ? `at most ${limit.maximum}` : null;
  return [kind(limit), low, high].filter(Boolean).join(" ");
}

/** Whether `value` meets one branch of the field's limits (keywords as in JSON Schema). */
function meets(value, limit) {
  if (limit.const !== undefined) return value === limit.const;
  if (limit.enum) return limit.enum.includes(value);
  if (limit.type === "integer" ? !Number.isInteger(value) : !Number.isFinite(value)) return false;
  return !(value < limit.minimum || value > limit.maximum || value <= limit.exclusiveMinimum || value >= limit.exclusiveMaximum);
}

/** Each `anyOf` branch merged into the field's other bounds; the field itself when it has none. */
const branches = ({ anyOf, ...limit }) => (anyOf ? anyOf.map((branch) => ({ ...limit, ...branch })) : [limit]);

/** The words for what a field allows, e.g. "0 or a whole number from 8 to 128". */
export const allowedText = (limit) => branches(limit)
  .map((branch) => (branch.const !== undefined ? String(branch.const) : range(branch))).join(" or ");

/** "NAME must be ..., got VALUE." when `value` is outside `limit`, else null. */
export function limitProblem(name, value, limit) {
  return branches(limit).some((branch) => meets(value, branch)) ? null : `${name} must be ${allowedText(limit)}, got ${value}.`;
}

/** An input's min and max attributes (its spinner's range) from the field's limits. */
export function bound(input, limit) {
  if (limit.minimum !== undefined) input.min = String(limit.minimum);
  if (limit.maximum !== undefined) input.max = String(limit.maximum);
}
