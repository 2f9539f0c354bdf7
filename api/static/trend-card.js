// The loop page's trend card: PV and SP, MV and, during an experiment, the relay output (±1) on a clock time axis.
// Its samples (one record per loop, `trendOf`) outlive the page's view: looking at another view and coming back
// keeps what was seen.

import { clock } from "./display.js";
import { h, svgNode } from "./dom.js";
import { clockTicks, cssWidth, timeChart } from "./plot.js";
import { axis, unitsOf } from "./units.js";

const TREND_WINDOW = 600; // wall seconds kept in the trend (more to keep the whole of the last experiment)
const TREND_MAX = 30000; // samples kept
const SERIES = ["time", "pv", "sp", "mv", "relay"];

// The trend of each loop seen since the page was opened: the samples, and `experiment`, the wall times of the
// experiment's first and last samples in it (null: none), so the window keeps it whole.
const trends = new Map();

function trendOf(id) {
  if (!trends.has(id)) trends.set(id, { time: [], pv: [], sp: [], mv: [], relay: [], experiment: null });
  return trends.get(id);
}

function clear(trend) {
  for (const k of SERIES) trend[k].length = 0;
  trend.experiment = null;
}

// A break in the lines where samples were missed (another view, a lost stream, the end of an experiment).
function gap(trend) {
  const n = trend.time.length;
  if (!n || trend.pv[n - 1] === null) return;
  trend.time.push(trend.time[n - 1]);
  for (const k of SERIES.slice(1)) trend[k].push(null);
}

// One sample into the trend: a break in the lines where the experiment's samples give way to the monitor's.
function push(trend, time, pv, sp, mv, relay) {
  const n = trend.time.length;
  if (n && trend.pv[n - 1] !== null && (trend.relay[n - 1] === null) !== (relay === null)) gap(trend);
  trend.time.push(time);
  trend.pv.push(pv);
  trend.sp.push(sp);
  trend.mv.push(mv);
  trend.relay.push(relay);
  if (relay !== null) trend.experiment = trend.experiment ? [trend.experiment[0], time] : [time, time];
}

// Samples older than the window go, unless they are of the last experiment (kept whole while it is recent).
function trim(trend, now) {
  const span = trend.experiment ? trend.experiment[1] - trend.experiment[0] : 0;
  const keep = Math.max(TREND_WINDOW, 2 * span);
  const cut = trend.time.findIndex((x) => x >= now - keep);
  const drop = Math.max(cut, trend.time.length - TREND_MAX);
  if (drop > 0) for (const k of SERIES) trend[k].splice(0, drop);
  if (trend.experiment && trend.time[0] > trend.experiment[1]) trend.experiment = null;
}

// The card; `page` is the loop page's record (its `loop` sets the units and, while tuning, the time axis's end).
export function trendCard(page) {
  const trend = trendOf(page.id);
  const svg = svgNode("trend", "trend of PV, SP and MV");
  svg.id = "trend";
  const info = h("span", { class: "muted small", id: "trend-info" }, "waiting for samples…");
  const node = h("section", { class: "card wide" }, h("div", { class: "card-head" }, h("h2", {}, "Trend"), info), svg);
  const width = () => cssWidth(svg) || 960;
  const resized = new ResizeObserver(() => {
    if (!page.closed && trend.time.length && Number(svg.dataset.width) !== width()) draw();
  });
  resized.observe(svg);

  function draw() {
    const n = trend.time.length;
    info.textContent = n ? `${n} samples · last ${clock(trend.time[n - 1])}` : "waiting for samples…";
    if (!n) return;
    const loop = page.loop;
    // The window fits what there is; while tuning it reaches to the estimated end (at most twice the time so far).
    const x0 = trend.time[0];
    let x1 = trend.time[n - 1];
    if (loop?.tbsy && loop.ite > 0) x1 = Math.min(x1 + loop.ite / (loop.speed || 1), x1 + Math.max(5, 2 * (x1 - x0)));
    x1 = Math.max(x1, x0 + 1);
    const hasRelay = trend.relay.some((r) => r !== null);
    const u = unitsOf(loop);
    const panels = [
      { height: 190, label: axis("PV, SP", u.pv), yAtLeast: u.pv_range, series: [
        { name: "SP", cls: "s-sp", x: trend.time, y: trend.sp, step: true },
        { name: "PV", cls: "s-pv", x: trend.time, y: trend.pv },
      ] },
      { height: 120, label: axis("MV", u.mv), yAtLeast: u.mv_range,
        series: [{ name: "MV", cls: "s-mv", x: trend.time, y: trend.mv, step: true }] },
    ];
    if (hasRelay) {
      panels.push({ height: 54, label: "relay", yRange: [-1.4, 1.4], yTicks: [-1, 0, 1],
                    series: [{ name: "relay ±1", cls: "s-relay", x: trend.time, y: trend.relay, step: true }] });
    }
    timeChart(svg, { width: width(), xRange: [x0, x1], panels, xTick: clock, xTicks: clockTicks, xLabel: "time (clock)" });
    svg.dataset.samples = n;
    svg.dataset.first = trend.time[0];
    svg.dataset.experimentStart = trend.experiment ? trend.experiment[0] : "";
    svg.dataset.width = width();
  }

  return {
    node,
    draw,
    gap: () => gap(trend),
    clear: () => clear(trend),
    // The daemon's trend when the stream opens (the running or last session from its start, then the monitor):
    // it replaces what the page held.
    replay(r) {
      clear(trend);
      for (let i = 0; i < r.time.length; i++) push(trend, r.time[i], r.pv[i], r.sp[i], r.mv[i], r.relay[i]);
      if (r.time.length) trim(trend, r.time[r.time.length - 1]);
    },
    sample(s) {
      const t = typeof s.time === "number" ? s.time : Date.now() / 1000;
      push(trend, t, s.pv ?? null, s.sp ?? null, s.mv ?? null, s.relay ?? null);
      trim(trend, t);
    },
    stale: (on) => node.classList.toggle("stale", on),
    close: () => resized.disconnect(),
  };
}
