// Numbers as every view writes them.

/** `v` to at most `digits` decimals, trailing zeros dropped, and never "-0": a box edge at
 * -0.0004 reads "0", not "-0.00". */
export const decimal = (v, digits = 3) => {
  const rounded = Number(v.toFixed(digits));
  return (rounded === 0 ? 0 : rounded).toString();
};

/** A point or vector as "(x, y, z)". */
export const point = (v) => `(${v.map((x) => decimal(x)).join(", ")})`;

/** The scene box {lo, hi} in words, as the what-if form and the results page say it. */
export const boxText = (box) => `Scene box: ${"xyz".split("").map((axis, i) => `${axis} from ${decimal(box.lo[i])} to ${decimal(box.hi[i])}`).join(", ")}`;
