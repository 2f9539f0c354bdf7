// The loop page's health card (GET /loops/{id}/health): the state, the flags with their reasons, the
// recommendation (with "tune now" where it is to retune), the indices with their units — now and, after a
// tuning, before it — the window, and the evidence as the daemon sent it: the assessed window's trend with the
// zero crossings the oscillation detector counted, and the MV–PV figure when the valve is flagged for stiction.

import { get } from "./api.js";
import { clock } from "./display.js";
import { esc, fill, h, svgNode } from "./dom.js";
import { fmt } from "./gains.js";
import { advice, flagChip, healthBadge } from "./health.js";
import { notify } from "./notices.js";
import { fitted, timeChart, xyPlot } from "./plot.js";
import { axis, derived, unitsOf } from "./units.js";
import { canOperate } from "./who.js";

// The indices in the order shown: [name, label, unit]; PV and MV stand for the loop's units (units.js derived).
// An index the daemon sends that is not here is shown under its own name.
const INDICES = [
  ["utilization", "utilization (share in AUTO)", "0–1"],
  ["saturation", "MV at a limit", "0–1"],
  ["oscillation_rate", "oscillation detections", "per 50 periods"],
  ["regularity", "regularity of the zero crossings", "> 1: regular"],
  ["oscillation_period", "oscillation period", "s"],
  ["oscillation_amplitude", "oscillation amplitude", "PV"],
  ["ccf_zero_lag", "MV–PV cross-correlation at lag 0", "0 odd … 1 even"],
  ["shape_index", "PV shape index", "> 0.5: triangular"],
  ["stiction_band", "stiction band (estimate)", "MV"],
  ["idle_index", "idle index", "−1…1"],
  ["load_recovery", "load recovery time", "s"],
  ["error_mean", "mean control error", "PV"],
  ["error_std", "σ of the control error", "PV"],
  ["harris", "Harris index", "0–1"],
  ["dead_time", "dead time of the Harris index", "s"],
  ["setpoint_steps", "set-point steps analysed", ""],
  ["overshoot", "overshoot after a step", "% of step"],
  ["settling_time", "settling time after a step", "s"],
  ["pv_noise", "PV noise σ", "PV"],
  ["mv_noise", "MV noise σ", "MV"],
  ["mv_travel", "MV travel", "MV/h"],
  ["mv_reversals", "MV reversals", "per hour"],
  ["frozen_share", "longest frozen PV", "share of window"],
];

const REFRESH_MS = 5000;

const DEAD_TIME_SOURCE = { model: "from the last tuning's model", "one sample": "one sample (no model: the Harris index is a lower bound)" };

// `page`: the loop page's record; `actions`: the actions card, whose TUNE flow "tune now" uses.
// The card's parts are built once and a redraw fills their contents: what the operator can press ("Tune now", the
// indices' fold) stays the same element in the page across redraws, keeping its focus and any press under way (a
// mousedown whose element leaves the page, even to come straight back, makes no click).
export function healthCard(page, actions) {
  const node = h("section", { class: "card wide health", id: "health" }, h("h2", {}, "Loop health"),
    h("p", { class: "muted" }, "loading…"));
  const tuneNow = h("button", { type: "button", class: "primary", id: "tune-now", onclick: () => actions.tune() }, "Tune now");
  const time = h("span", { class: "muted small", id: "health-time" });
  const verdict = slot(); // the badge and the advice, before "tune now"
  const summary = h("div", { class: "summary", id: "health-summary" }, verdict);
  const [flags, comparison, proof, indicesSlot, windowSlot] = [slot(), slot(), slot(), slot(), slot()];
  const indices = indicesBox();
  const parts = [h("div", { class: "card-head" }, h("h2", {}, "Loop health"), time), summary, flags, comparison, proof,
    h("div", { class: "health-details" }, indicesSlot, windowSlot)];
  // What the card shows: the verdict (state, severity, flags, the loop's session) and the assessment's time it was
  // drawn for, and when. A new verdict is fetched at once; a newer assessment of the same verdict at most every
  // REFRESH_MS (the daemon may assess every second of wall time at a demo's speed).
  let drawn = { verdict: null, time: null, at: 0 };
  let loading = null;
  let timer = null;

  function update(loop) {
    const s = loop.health ?? null;
    const verdict = JSON.stringify([s?.state, s?.severity, s?.flags, loop.session]);
    const newer = s?.time !== drawn.time;
    const wait = REFRESH_MS - (Date.now() - drawn.at);
    if (!loading && (verdict !== drawn.verdict || (newer && wait <= 0))) {
      drawn = { verdict, time: s?.time, at: Date.now() };
      // Never assessed (null; or a daemon without health monitoring): nothing to fetch.
      if (!s) render({ state: null, severity: null, assessment: null, before_tuning: null, evidence: null, reason: "" });
      else loading = load().finally(() => { loading = null; if (!page.closed) update(page.loop); });
    } else if (!loading && newer && !timer) {
      timer = setTimeout(() => { timer = null; if (!page.closed) update(page.loop); }, wait);
    }
    // "Tune now" runs the TUNE form's request: enabled when TUNE is (operator token, loop idle and handed back).
    tuneNow.disabled = !actions.tunable();
    tuneNow.title = !canOperate() ? "needs an operator token" : tuneNow.disabled ? "the loop cannot be tuned now"
      : "start the relay experiment with the settings in the TUNE form";
  }

  async function load() {
    try {
      const body = await get(`/loops/${esc(page.id)}/health`);
      if (!page.closed) render(body);
    } catch (err) {
      drawn.time = null; // tried again after REFRESH_MS
      if (!page.closed) notify(err, node);
    }
  }

  function render(body) {
    const u = unitsOf(page.loop);
    const a = body.assessment;
    const before = body.before_tuning;
    node.dataset.state = body.state;
    node.dataset.severity = body.severity;
    node.dataset.time = a?.time ?? ""; // the assessment shown (unix s), as the daemon stamped it
    if (!node.contains(summary)) fill(node, parts); // the first drawing replaces "loading…"
    time.textContent = a?.time ? `assessed ${clock(a.time)}` : "";
    fill(verdict, healthBadge(body.state ? body : null),
      a ? advice(a.recommendation) : h("span", { class: "muted" }, body.reason || stateWords(body.state)));
    present(summary, tuneNow, a?.recommendation === "retune");
    fill(flags, a ? flagList(a) : null);
    fill(comparison, before ? beforeAfter(before, a) : null);
    fill(proof, body.evidence ? evidence(body.evidence, a, u) : null);
    if (a) indices.show(a, before, u);
    present(indicesSlot, indices.node, Boolean(a));
    fill(windowSlot, windowInfo(body, a));
  }

  return { node, update, close: () => clearTimeout(timer) };
}

// A place in the card whose contents a redraw replaces; it draws no box of its own (CSS: .slot).
const slot = () => h("div", { class: "slot" });

// `child` in `parent` (at its end) when `wanted`, else out of the page; moved only when that changes.
function present(parent, child, wanted) {
  if (!wanted) child.remove();
  else if (child.parentNode !== parent) parent.append(child);
}

function stateWords(state) {
  return state === "off" ? "health monitoring is off for this loop (its config)"
    : state === "pending" ? "collecting samples" : "not assessed yet";
}

function flagList(a) {
  if (!a.flags.length) return h("p", { class: "muted", id: "health-flags" }, "No flags: nothing wrong found in the window.");
  return h("ul", { class: "hflags", id: "health-flags" }, a.flags.map((name) => h("li", { "data-flag": name },
    flagChip(name, a.severities[name]), h("span", { class: "muted small" }, a.severities[name]), " ",
    h("span", { class: "reason" }, a.reasons[name] || ""))));
}

// The window's trend with the crossings marked, and the MV–PV figure when stiction is flagged.
function evidence(ev, a, u) {
  const osc = a?.flags.includes("oscillating") && ev.period !== null && ev.period !== undefined
    ? ` · oscillation period ${fmt(ev.period, 3)} s, amplitude ${fmt(ev.amplitude, 3)}${u.pv ? ` ${u.pv}` : ""}` : "";
  const trend = svgNode("trend health-trend", "the assessed window");
  trend.id = "health-trend";
  const boxes = [h("div", { class: "panel-box" }, h("h3", {}, `The assessed window${osc}`), trend,
    h("p", { class: "muted small" }, `▼ ${ev.crossings.length} zero crossings of the control error SP − PV, as the oscillation detector counted them.`))];
  const span = [ev.t[0] ?? 0, Math.max(ev.t[ev.t.length - 1] ?? 1, (ev.t[0] ?? 0) + 1)];
  fitted(trend, (w) => timeChart(trend, { width: w, xRange: span, panels: [
    { height: 150, label: axis("PV, SP", u.pv),
      // the crossings in the legend where it has room (the caption below says what they are in any case)
      marks: { name: w >= 600 ? "zero crossings" : "", cls: "crossings", x: ev.crossings },
      series: [{ name: "SP", cls: "s-sp", x: ev.t, y: ev.sp, step: true }, { name: "PV", cls: "s-pv", x: ev.t, y: ev.pv }] },
    { height: 90, label: axis("MV", u.mv), series: [{ name: "MV", cls: "s-mv", x: ev.t, y: ev.mv, step: true }] },
  ], xLabel: "plant seconds from the window's start" }), 700);
  if (a?.flags.includes("stiction")) {
    const xy = svgNode("mvpv", "PV against MV");
    xy.id = "health-mvpv";
    const band = a.indices.stiction_band;
    boxes.push(h("div", { class: "panel-box mvpv-box" },
      h("h3", {}, `PV against MV${band !== null && band !== undefined ? ` · stiction band ≈ ${fmt(band, 3)}${u.mv ? ` ${u.mv}` : ""}` : ""}`), xy,
      h("p", { class: "muted small" }, "A sticking valve draws a parallelogram: the MV moves and the PV stays until the valve jumps.")));
    fitted(xy, (w) => xyPlot(xy, { width: Math.min(w, 460), x: ev.mv, y: ev.pv, name: "PV(MV)", cls: "s-pv",
                                   xLabel: axis("MV", u.mv), yLabel: axis("PV", u.pv) }), 420);
  }
  return h("div", { class: `health-evidence${boxes.length > 1 ? " two" : ""}`, id: "health-evidence" }, boxes);
}

// Every index with its unit, now and (after a tuning) before it: the fold built once (the operator's open or
// folded stays, and its summary is never replaced under the pointer), its table drawn anew by `show`.
function indicesBox() {
  const table = h("div", { class: "scroll-x" });
  const node = h("details", { class: "health-indices", open: true }, h("summary", {}, "Indices"), table);
  return { node, show: (a, before, u) => fill(table, indicesTable(a, before, u)) };
}

function indicesTable(a, before, u) {
  const known = new Set(INDICES.map(([name]) => name));
  const rows = [...INDICES, ...Object.keys(a.indices).filter((k) => !known.has(k)).map((k) => [k, k, ""])];
  const value = (v) => (typeof v === "number" ? fmt(v) : "—");
  return h("table", { class: "indices", id: "health-indices" },
    h("thead", {}, h("tr", {}, h("th", {}, "index"), h("th", { class: "num" }, "now"),
      before ? h("th", { class: "num" }, "before tuning") : null, h("th", {}, "unit"))),
    h("tbody", {}, rows.filter(([name]) => name in a.indices).map(([name, label, unit]) => h("tr", { "data-index": name },
      h("th", {}, label), h("td", { class: "num now" }, value(a.indices[name])),
      before ? h("td", { class: "num before" }, value(before.indices?.[name])) : null,
      h("td", { class: "unit" }, unitText(unit, u))))));
}

// An index's unit in the loop's units: "°C" for PV, "%/h" for MV/h; as written where the loop names none.
function unitText(unit, u) {
  if (unit === "PV" || unit === "MV") return (unit === "PV" ? u.pv : u.mv) || unit;
  return derived(unit, u);
}

// The assessment before the loop's newest tuning beside the one now.
function beforeAfter(before, a) {
  const side = (title, x, id) => h("div", { class: "side", id }, h("h3", {}, title),
    x ? [h("div", { class: "status-line" }, ...(x.flags.length ? x.flags.map((f) => flagChip(f, x.severities?.[f])) : [h("span", { class: "muted" }, "no flags")])),
      h("div", { class: "small" }, advice(x.recommendation))] : h("p", { class: "muted small" }, "not assessed since"));
  return h("div", { class: "before-after", id: "health-before-after" },
    side(`Before tuning (session ${String(before.session || "").slice(0, 8)}, assessed ${clock(before.time)})`, before, "health-before"),
    side("Now", a, "health-now"));
}

function windowInfo(body, a) {
  const w = a?.window;
  return h("dl", { class: "kv small", id: "health-window" },
    h("dt", {}, "window"), h("dd", {}, w ? `${fmt(w.end - w.start, 4)} plant s (${w.samples} samples at ${fmt(w.ts, 3)} s)` : "—",
      body.window_setting ? ` · configured ${fmt(body.window_setting, 4)} s` : ""),
    a?.dead_time_source ? [h("dt", {}, "Harris dead time"), h("dd", {}, DEAD_TIME_SOURCE[a.dead_time_source] || a.dead_time_source)] : null);
}
