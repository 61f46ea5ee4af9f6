// Numbers as every view writes them.

/** `v` to at most `digits` decimals, trailing zeros dropped, and never "-0": a box edge at
 * -0.0004 reads "0", not "-0.00". */
export const decimal = (v, digits = 3) => {
  const rounded = Number(v.toFixed(digits));
  return (rounded === 0 ? 0 : rounded).toString();
};
