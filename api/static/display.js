// How a loop reads on the page: its state in words and badges, the outcome codes' meanings, times, gains in brief.

import { get } from "./api.js";
import { esc, h } from "./dom.js";
import { fmt } from "./gains.js";
import { notify } from "./notices.js";
import { NO_UNITS, derived, mvText, unitsOf } from "./units.js";

// Meaning of ite when the experiment has ended: GET /api/v1/codes (value → {name, message, warning}), loaded once
// after login.
export const CODES = new Map();
export async function loadCodes() {
  if (CODES.size) return;
  try {
    for (const c of await get("/codes")) CODES.set(c.value, c);
  } catch (err) {
    if (err.status !== 401) notify(err); // the page still shows each session's own message
  }
}
// "code 3 NO_OSCILLATION" (the name when the daemon gave the table).
export function codeName(code) {
  const c = CODES.get(code);
  return c ? `code ${code} ${c.name}` : `code ${code}`;
}

export const STAGES = { noise: "measuring noise", relay: "relay experiment", done: "designing" };

export function when(iso) {
  if (!iso) return "—";
  const d = new Date(iso);
  if (Number.isNaN(d.getTime())) return iso;
  const pad = (n) => String(n).padStart(2, "0");
  return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
}

export function clock(unix) {
  const d = new Date(unix * 1000);
  const pad = (n) => String(n).padStart(2, "0");
  return `${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
}

// The loop's state in words and a CSS class: tuning, notrestored, failed, warn, ok, idle.
export function statusOf(loop) {
  if (loop.restore) { // before everything else: the loop is not back in its mode (ite 20), whatever the session did
    return { cls: "notrestored", badge: "LOOP NOT RESTORED", text: restoreText(loop.restore) };
  }
  if (loop.tbsy) {
    return { cls: "tuning", badge: "TUNING", text: `${STAGES[loop.stage] || "starting"} · ${timeLeft(loop)}` };
  }
  const code = Math.round(loop.ite);
  const meaning = CODES.get(code)?.message;
  if (loop.te) return { cls: "failed", badge: "FAILED", text: `${codeName(code)}: ${loop.message || meaning || "?"}` };
  if (loop.session && CODES.get(code)?.warning) {
    return { cls: "warn", badge: "WARNING", text: `${codeName(code)}: ${loop.message || meaning}` };
  }
  if (loop.session) return { cls: "ok", badge: "OK", text: withMessage(codeName(code), meaning || loop.message) };
  return { cls: "idle", badge: "IDLE", text: "not tuned since the daemon started" };
}

// "code 0 OK" and a message, unless the message only repeats the code's name ("code 0 OK: ok" said it twice).
export function withMessage(code, message) {
  return !message || code.toLowerCase().endsWith(` ${message.toLowerCase()}`) ? code : `${code}: ${message}`;
}

// A loop the daemon could not hand back yet: what it restores, since when, how often it tried and why it failed.
export function restoreText(r) {
  return `the daemon retries handing it back to ${r.mode} at MV ${fmt(r.mv)} · ${r.attempts} attempt${r.attempts === 1 ? "" : "s"} `
    + `since ${when(r.since)} · last error: ${r.last_error}`;
}

// The prominent box of a loop not handed back (overview row and loop page), with what the operator can do.
export function restoreBox(loop) {
  const r = loop.restore;
  const u = unitsOf(loop);
  return h("div", { class: "not-restored", role: "alert", "data-restore": r.session },
    h("strong", {}, "LOOP NOT RESTORED"),
    h("div", {}, `Session ${r.session.slice(0, 8)} could not hand the loop back to ${r.mode} at MV ${mvText(r.mv, u)}.`),
    h("div", { "data-restore-attempts": r.attempts }, `${r.attempts} attempt${r.attempts === 1 ? "" : "s"} since ${when(r.since)}; the daemon keeps retrying.`),
    h("div", { class: "mono small", "data-restore-error": "" }, `last error: ${r.last_error}`),
    h("div", { class: "small" }, `Or set mode ${r.mode} and MV ${mvText(r.mv, u)} at the controller by hand.`));
}

// The time left in wall-clock seconds (what the operator waits), and the plant seconds of ite where they differ
// (a simulated plant run faster than real time); ite itself keeps its meaning (plant seconds, as on the PLC).
export function timeLeft(loop) {
  const plant = Math.max(0, loop.ite);
  const speed = loop.speed || 1;
  const wall = `about ${duration(plant / speed)} left`;
  return speed === 1 ? wall : `${wall} (ite ${Math.round(plant)} plant s at ${fmt(speed, 3)}× real time)`;
}

export function duration(seconds) {
  if (seconds < 90) return `${Math.round(seconds)} s`;
  if (seconds < 5400) return `${Math.round(seconds / 60)} min`;
  return `${fmt(seconds / 3600, 2)} h`;
}

export function tuningFlags(loop) {
  const ite = loop.tbsy ? `${fmt(Math.max(0, loop.ite), 3)} s` : String(Math.round(loop.ite));
  return h("span", { class: "flags" },
    h("span", { class: `flag ${loop.tbsy ? "on" : ""}`, "data-flag": "tbsy" }, `TBSY ${loop.tbsy ? 1 : 0}`),
    h("span", { class: `flag ${loop.te ? "on bad" : ""}`, "data-flag": "te" }, `TE ${loop.te ? 1 : 0}`),
    h("span", { class: "flag ite", "data-flag": "ite" }, `ite ${ite}`));
}

// Only while tuning: a finished or failed session has no "progress" to show (the badge and code say how it ended).
export function progressBar(loop) {
  const pct = Math.round(100 * (loop.progress || 0));
  return h("div", { class: "progress running", role: "progressbar", "aria-valuenow": pct,
                    "aria-valuemin": 0, "aria-valuemax": 100 },
    h("div", { class: "bar", style: `width:${pct}%` }), h("span", {}, `${pct} %`));
}

export function modeBadge(mode) {
  if (!mode) return h("span", { class: "mode unknown" }, "—");
  return h("span", { class: `mode ${mode === "AUTO" ? "auto" : "man"}` }, mode);
}

export function outcomeBadge(outcome, code) {
  if (!outcome) return h("span", { class: "badge idle" }, "—");
  const ok = outcome === "success";
  return h("span", { class: `badge ${ok ? "ok" : "failed"}` },
    ok ? "success" : `failure${code !== null && code !== undefined ? ` (${code})` : ""}`);
}

// K (in the loop's MV/PV units when it names them), Ti and Td in a few characters.
export function gainsBrief(g, units = NO_UNITS) {
  if (!g) return h("span", { class: "muted" }, "—");
  const k = units.pv || units.mv ? ` ${derived("MV/PV", units)}` : "";
  return h("span", { class: "mono small" }, `K ${fmt(g.pk, 3)}${k} · Ti ${g.pti === null ? "∞" : `${fmt(g.pti, 3)} s`}`
    + (g.ptd ? ` · Td ${fmt(g.ptd, 3)} s` : ""));
}

// -- loop page

export function loopTabs(id, active) {
  return h("nav", { class: "tabs" },
    h("a", { href: `#/loop/${esc(id)}`, class: active === "live" ? "active" : "" }, "Live"),
    h("a", { href: `#/loop/${esc(id)}/history`, class: active === "history" ? "active" : "", id: "tab-history" }, "History"));
}

export function readout(label, value, key) {
  return h("div", { class: "readout" }, h("div", { class: "label" }, label),
    h("div", { class: "value", "data-readout": key || label.toLowerCase() }, value));
}

// A parameter's label with its unit when that is in the loop's MV/PV units ("K (%/°C)"); seconds stay with values.
export function paramLabel(label, unit, units) {
  return /MV|PV/.test(unit) && (units.pv || units.mv) ? `${label} (${derived(unit, units)})` : label;
}

