// PID gains as the page shows them: numbers as text, the rows of the side-by-side table and the parameters that an
// apply changes. The gains come in the standard (ISA) form {pk, pti (null: no integral), ptd, pnd, pb, pc}; their
// series and parallel forms come computed by the daemon (the analysis's and the result's `forms`:
// autotuner/engine/control/gains.py), never here.

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

// Rows of the side-by-side table, per form: [label, unit, value of one side, key]. A side is {gains, forms} (forms:
// the daemon's {parallel, series}; null when it was not given: the series and parallel cells show "—").
const series = (key) => (side) => (side.forms ? (side.forms.series ? side.forms.series[key] ?? Infinity : "n/a") : null);
const parallel = (key) => (side) => side.forms?.parallel?.[key] ?? null;
export const ROWS = [
  { form: "standard (ISA)", rows: [
    ["K", "MV/PV", (s) => s.gains.pk, "pk"],
    ["Ti", "s", (s) => (s.gains.pti === null ? Infinity : s.gains.pti), "pti"],
    ["Td", "s", (s) => s.gains.ptd, "ptd"],
    ["N", "", (s) => s.gains.pnd, "pnd"],
    ["b", "", (s) => s.gains.pb, "pb"],
    ["c", "", (s) => s.gains.pc, "pc"],
  ] },
  { form: "series (interacting)", rows: [
    ["K′", "MV/PV", series("k")],
    ["Ti′", "s", series("ti")],
    ["Td′", "s", series("td")],
  ] },
  { form: "parallel", rows: [
    ["Kp", "MV/PV", parallel("kp")],
    ["Ki", "MV/(PV·s)", parallel("ki")],
    ["Kd", "MV·s/PV", parallel("kd")],
  ] },
];

// The text of one cell; `side` null: "—". A series form that does not exist (Ti < 4·Td) is "n/a".
export function cell(row, side) {
  if (!side?.gains) return "—";
  const v = row[2](side);
  return v === "n/a" ? v : fmt(v);
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
