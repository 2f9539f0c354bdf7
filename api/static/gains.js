// PID gain forms, computed here the same way as autotuner/gains.py does from the standard (ISA) form the API
// gives: {pk, pti (null: no integral), ptd, pnd, pb, pc}.
//   series (interacting, ideal) K'(1 + 1/(Ti' s))(1 + Td' s): exists only when Ti >= 4 Td;
//     K' = K (1 + r)/2, Ti' = Ti (1 + r)/2, Td' = Ti (1 − r)/2 with r = sqrt(1 − 4 Td/Ti)
//   parallel Kp = K, Ki = K/Ti, Kd = K·Td.
// N, b and c do not take part in the conversions.

const SERIES_TOL = 1e-12;

export function series(g) {
  if (!g) return null;
  if (g.pti === null || g.pti === undefined) return { k: g.pk, ti: null, td: g.ptd };
  let disc = 1 - (4 * g.ptd) / g.pti;
  if (disc < 0) {
    if (disc < -SERIES_TOL) return { error: `needs Ti ≥ 4·Td (Ti = ${fmt(g.pti)} s, Td = ${fmt(g.ptd)} s)` };
    disc = 0;
  }
  const r = Math.sqrt(disc);
  return { k: 0.5 * g.pk * (1 + r), ti: 0.5 * g.pti * (1 + r), td: 0.5 * g.pti * (1 - r) };
}

export function parallel(g) {
  if (!g) return null;
  const ki = g.pti === null || g.pti === undefined ? 0 : g.pk / g.pti;
  return { kp: g.pk, ki, kd: g.pk * g.ptd };
}

// A number with 4 significant digits, no exponent for ordinary magnitudes; "—" for missing.
export function fmt(x, digits = 4) {
  if (x === null || x === undefined || Number.isNaN(x)) return "—";
  if (!Number.isFinite(x)) return x > 0 ? "∞" : "−∞";
  if (x === 0) return "0";
  const a = Math.abs(x);
  if (a >= 1e6 || a < 1e-4) return x.toExponential(digits - 1).replace("-", "−");
  const s = Number(x.toPrecision(digits)).toString();
  return s.replace("-", "−");
}

// Rows of the side-by-side table: [label, unit, value(g)] per form.
export const ROWS = [
  { form: "standard (ISA)", rows: [
    ["K", "MV/PV", (g) => g.pk, "pk"],
    ["Ti", "s", (g) => (g.pti === null ? Infinity : g.pti), "pti"],
    ["Td", "s", (g) => g.ptd, "ptd"],
    ["N", "", (g) => g.pnd, "pnd"],
    ["b", "", (g) => g.pb, "pb"],
    ["c", "", (g) => g.pc, "pc"],
  ] },
  { form: "series (interacting)", rows: [
    ["K′", "MV/PV", (g) => series(g), "k"],
    ["Ti′", "s", (g) => series(g), "ti"],
    ["Td′", "s", (g) => series(g), "td"],
  ] },
  { form: "parallel", rows: [
    ["Kp", "MV/PV", (g) => parallel(g).kp],
    ["Ki", "MV/(PV·s)", (g) => parallel(g).ki],
    ["Kd", "MV·s/PV", (g) => parallel(g).kd],
  ] },
];

// The text of one cell.
export function cell(row, g, form) {
  if (!g) return "—";
  const v = row[2](g);
  if (form === "series (interacting)") {
    if (v.error) return "n/a";
    const x = v[row[3]];
    return x === null ? "∞" : fmt(x);
  }
  return fmt(v);
}

// The controller's parameters in the standard form, as the API names them: [key, label, unit].
export const PARAMS = [["pk", "K", "MV/PV"], ["pti", "Ti", "s"], ["ptd", "Td", "s"], ["pnd", "N", ""], ["pb", "b", ""],
  ["pc", "c", ""]];

// One parameter's value as text: Ti null is "∞" (no integral action), seconds with their unit.
export function paramText(key, v, unit) {
  if (key === "pti" && v === null) return "∞";
  const text = fmt(v);
  return unit === "s" && text !== "—" ? `${text} s` : text;
}

// Every parameter of `newG` with its value in `oldG` (null: not known) and whether it changes (relative 1e-9).
export function changes(oldG, newG) {
  return PARAMS.map(([key, label, unit]) => {
    const before = oldG ? oldG[key] : undefined;
    const after = newG[key];
    const same = before !== undefined && (before === after
      || (before !== null && after !== null && Math.abs(before - after) <= 1e-9 * Math.max(1, Math.abs(after))));
    return { key, label, unit, before, after, changed: !same };
  });
}
