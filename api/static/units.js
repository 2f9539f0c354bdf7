// A loop's engineering units and display (the status's `units`, from the config's `units:`; docs/daemon.md):
// values with their unit and decimals, and the units of gains derived from the PV and MV units.

import { fmt } from "./gains.js";

// What a loop without a units section shows: no unit, 4 significant digits, axes fitted to the data.
export const NO_UNITS = Object.freeze({ pv: "", mv: "", decimals: null, pv_range: null, mv_range: null });

export function unitsOf(loop) {
  return { ...NO_UNITS, ...(loop?.units || {}) };
}

// A PV, SP or MV value as text: the loop's decimals (else 4 significant digits) and its unit; "—" when missing.
export function quantity(x, unit, decimals) {
  if (x === null || x === undefined || Number.isNaN(x)) return "—";
  const text = decimals === null || decimals === undefined || !Number.isFinite(x) ? fmt(x)
    : x.toFixed(decimals).replace("-", "−");
  return unit ? `${text} ${unit}` : text;
}

export const pvText = (x, units) => quantity(x, units.pv, units.decimals);
export const mvText = (x, units) => quantity(x, units.mv, units.decimals);

// A unit inside a compound one: "m³/h" in "%/(m³/h)" needs brackets, "°C" does not.
const part = (u) => (/[/·\s]/.test(u) ? `(${u})` : u);

// A compound unit written with MV and PV ("MV/PV", "MV/(PV·s)", "PV/MV") in the loop's units; unchanged where the
// loop names none.
export function derived(template, units) {
  if (!template) return template;
  return template.replace(/MV|PV/g, (m) => {
    const u = m === "MV" ? units.mv : units.pv;
    return u ? part(u) : m;
  });
}

// An axis label: "PV, SP (°C)".
export function axis(label, unit) {
  return unit ? `${label} (${unit})` : label;
}
