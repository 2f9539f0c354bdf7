// A session's result: what was identified, the Nyquist plot, the gains side by side and the simulated steps — all as
// the daemon computed them (GET /sessions/{sid}, GET /sessions/{sid}/analysis). Shown on the loop page (the last
// session, `resultCard`) and on a session's page (`renderResult`).

import { ApiError, get } from "./api.js";
import { CODES, codeName, outcomeBadge, restoreText, when } from "./display.js";
import { add, esc, fill, h, svgNode } from "./dom.js";
import { ROWS, cell, fmt } from "./gains.js";
import { notify } from "./notices.js";
import { fitted, nyquist, timeChart } from "./plot.js";
import { NO_UNITS, derived, unitsOf } from "./units.js";

// -- a session's result: summary, Nyquist plot, gains side by side, simulated steps

// What the session identified, in words: the point and the static gain, or "nothing identified".
// |F| and the static gain are PV units per MV unit.
function identified(r, units) {
  const point = r.point;
  if (!point) return h("span", { class: "identified none", "data-identified": "none" }, "nothing identified (no point, no gains)");
  const per = units.pv || units.mv ? ` ${derived("PV/MV", units)}` : "";
  const kind = r.static_gain === null || r.static_gain === undefined ? "none found (integrating or not measured)"
    : `${fmt(r.static_gain)}${per}`;
  return h("span", { class: "mono small identified", "data-identified": "point" },
    `identified ω = ${fmt(point.omega)} rad/s, |F| = ${fmt(point.gain)}${per}, ∠F = ${fmt(point.phase_deg)}° · static gain ${kind}`);
}

// The card of a session's result. A failure shows what was identified and why it failed, never success colours;
// a success whether its gains were written (applied) or wait to be (`pending`).
// A session whose loop is not handed back (`restore`, or the record's state) shows that first and no success colour,
// whatever the experiment found.
export async function renderResult(box, session, { title, pending = false, units = NO_UNITS, restore = null }) {
  const r = session.result || {};
  const notRestored = Boolean(restore) || session.state === "not_restored";
  const ok = session.outcome === "success" && !notRestored;
  const warning = ok && CODES.get(session.code)?.warning;
  box.classList.toggle("failed", session.outcome === "failure" || notRestored);
  box.classList.toggle("warn", Boolean(warning));
  const applied = session.applied_at
    ? h("span", { class: "badge ok", id: "applied" }, `applied ${when(session.applied_at)}${session.applied_by ? ` by ${session.applied_by}` : ""}`)
    : ok && pending ? h("span", { class: "badge pending", id: "applied" }, "not applied yet") : null;
  const why = notRestored
    ? h("p", { class: "why bad", id: "why" }, `LOOP NOT RESTORED: the loop is not handed back yet — ${
      restore ? restoreText(restore) : session.message || "the daemon retries"}`)
    : session.outcome === "failure" || warning
    ? h("p", { class: `why ${warning ? "warn" : "bad"}`, id: "why" },
      `${warning ? "Warning" : "Failed"}: ${codeName(session.code)} — ${session.message || CODES.get(session.code)?.message || ""}`)
    : null;
  fill(box,
    h("div", { class: "card-head" }, h("h2", {}, title),
      h("span", { class: "muted small" }, h("a", { href: `#/session/${esc(session.id)}` }, `session ${session.id.slice(0, 8)}`),
        ` · ${when(session.started_at)} · by ${session.user}`)),
    h("div", { class: "summary" }, notRestored ? h("span", { class: "badge notrestored" }, "loop not restored")
      : outcomeBadge(session.outcome, session.code), notRestored ? null : applied,
      ok && session.message && session.message.toLowerCase() !== "ok" ? h("span", {}, session.message) : null,
      identified(r, units)),
    why);
  if (!r.gains) {
    add(box, h("p", { class: "muted", id: "no-gains" }, "No gains from this session: the controller keeps its gains."));
    return;
  }
  const grid = h("div", { class: "result-grid" });
  add(box, grid);
  let analysis = null;
  try {
    analysis = await get(`/sessions/${esc(session.id)}/analysis`);
  } catch (err) {
    add(grid, h("div", { class: "alert warn" }, `Analysis unavailable: ${err instanceof ApiError ? err.text : err.message}`));
  }
  // Each side's gains with their series and parallel forms, as the daemon computed them: the analysis's, else the
  // result's own forms for the new gains (the old ones then show their standard form only).
  const oldGains = analysis?.old?.gains ?? session.gains_before ?? session.saved?.gains ?? null;
  const oldSide = oldGains ? { gains: oldGains, forms: analysis?.old?.forms ?? null } : null;
  const newSide = analysis?.new ?? { gains: r.gains, forms: r.forms ?? null };
  if (analysis) {
    const nq = svgNode("nyquist", "Nyquist plot");
    nq.id = "nyquist";
    const curves = [];
    if (analysis.old?.nyquist) curves.push({ name: "L old", cls: "s-old", re: analysis.old.nyquist.re, im: analysis.old.nyquist.im });
    curves.push({ name: "L new", cls: "s-new", re: analysis.new.nyquist.re, im: analysis.new.nyquist.im });
    const nqOpts = { point: analysis.point, loopPoint: analysis.new.at_point, circle: analysis.ms_circle, curves,
                     circleLabel: `Ms = ${fmt(analysis.ms_target, 3)} circle` };
    const nqBox = h("div", { class: "plot-box nyquist-box" }, nq);
    add(grid, h("div", { class: "panel-box" }, h("h3", {}, "Nyquist: open loop L = C·F"),
      nqBox, h("p", { class: "muted small" }, `model ${analysis.model?.text || analysis.model?.kind || "—"} · Ms old ${analysis.old ? fmt(analysis.old.ms, 3) : "—"}`
        + `, new ${fmt(analysis.new.ms, 3)}${analysis.new.stable === false ? " (unstable!)" : ""}`)));
    fitted(nq, (w) => nyquist(nq, { ...nqOpts, size: Math.min(w, 560) }), 420);
  }
  add(grid, h("div", { class: "panel-box" }, h("h3", {}, "Gains"), gainsTable(oldSide, newSide, units)));
  if (analysis) {
    const steps = h("div", { class: "steps" });
    for (const [key, label] of [["setpoint", "Set-point step"], ["load", "Load step"]]) {
      const svg = svgNode(`step ${key}`, label);
      svg.id = `step-${key}`;
      add(steps, h("div", { class: "panel-box" }, h("h3", {}, `${label} (simulated on the identified model)`), svg));
      const pv = [];
      const mv = [];
      if (analysis.old?.[key]) {
        pv.push({ name: "PV old", cls: "s-old", x: analysis.old[key].t, y: analysis.old[key].pv });
        mv.push({ name: "MV old", cls: "s-old", x: analysis.old[key].t, y: analysis.old[key].mv });
      }
      pv.push({ name: "PV new", cls: "s-new", x: analysis.new[key].t, y: analysis.new[key].pv });
      mv.push({ name: "MV new", cls: "s-new", x: analysis.new[key].t, y: analysis.new[key].mv });
      fitted(svg, (w) => timeChart(svg, { width: w, panels: [{ height: 150, label: "PV", series: pv },
        { height: 90, label: "MV", series: mv }], xLabel: "plant seconds after the step" }), 520);
    }
    add(box, steps);
  }
}


// Old and new gains side by side in the standard, series and parallel forms; a side is {gains, forms} or null.
function gainsTable(oldSide, newSide, units) {
  const tbody = h("tbody");
  for (const group of ROWS) {
    add(tbody, h("tr", { class: "form-row" }, h("th", { colspan: 4 }, group.form)));
    for (const row of group.rows) {
      add(tbody, h("tr", { "data-gain": row[3] && group.form.startsWith("standard") ? row[3] : null },
        h("th", {}, row[0]), h("td", { class: "num old" }, cell(row, oldSide)),
        h("td", { class: "num new" }, cell(row, newSide)), h("td", { class: "unit" }, derived(row[1], units))));
    }
  }
  return h("table", { class: "gains", id: "gains" },
    h("thead", {}, h("tr", {}, h("th", {}, ""), h("th", { class: "num" }, "old"), h("th", { class: "num" }, "new"), h("th", {}, "unit"))),
    tbody);
}

// The loop page's card of the loop's last session. `page.shownSession` is the session it shows (null: none, or
// to be drawn again); `update(loop)` follows the loop's status.
export function resultCard(page) {
  const node = h("section", { class: "card wide result", id: "result" });

  async function show(sid) {
    page.shownSession = sid;
    if (!node.firstChild) fill(node, h("h2", {}, "Result"), h("p", { class: "muted" }, "loading…"));
    try {
      const session = await get(`/sessions/${esc(sid)}`);
      if (page.shownSession !== sid || page.closed) return;
      const loop = page.loop;
      await renderResult(node, session, { title: "Last session", pending: loop?.pending_gains, units: unitsOf(loop),
                                          restore: loop?.restore });
    } catch (err) {
      if (page.shownSession === sid) notify(err, node);
    }
  }

  function update(loop) {
    if (!loop.tbsy && loop.session && loop.session !== page.shownSession) show(loop.session);
    if (loop.tbsy && page.shownSession !== null && loop.session !== page.shownSession) {
      page.shownSession = null;
      fill(node, h("h2", {}, "Result"), h("p", { class: "muted" }, "The experiment is running; the result shows when it ends."));
    }
  }

  return { node, show, update };
}
