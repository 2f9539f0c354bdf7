// One session in full (#/session/SID): its settings, the loop's saved state, the trace and the result.

import { get } from "./api.js";
import { loopTabs, outcomeBadge, when } from "./display.js";
import { add, esc, fill, h, main, svgNode } from "./dom.js";
import { fmt } from "./gains.js";
import { notify } from "./notices.js";
import { fitted, timeChart } from "./plot.js";
import { renderResult } from "./result-card.js";
import { NO_UNITS, axis, mvText, pvText, quantity, unitsOf } from "./units.js";

// The units of loop `id` from its status; none when the daemon no longer has the loop (an old session's).
export async function loopUnits(id) {
  try {
    return unitsOf(await get(`/loops/${esc(id)}`));
  } catch (err) {
    if (err.status === 404) return NO_UNITS;
    throw err;
  }
}

export function sessionView(sid) {
  const box = h("section", { class: "card wide result", id: "result" });
  const head = h("section", { class: "loop-head" });
  const traceSvg = svgNode("trend", "trace of the session");
  traceSvg.id = "trace";
  const traceTitle = h("h2", {}, "Trace");
  const traceCard = h("section", { class: "card wide" }, traceTitle, traceSvg);
  const info = h("section", { class: "card wide" });
  fill(main(), head, info, traceCard, box);
  let closed = false;
  (async () => {
    try {
      const s = await get(`/sessions/${esc(sid)}`);
      const u = await loopUnits(s.loop);
      if (closed) return;
      fill(head, h("div", { class: "title" }, h("a", { href: `#/loop/${esc(s.loop)}/history`, class: "muted small" }, `← history of ${s.loop}`),
        h("h1", {}, s.loop, " ", h("span", { class: "desc" }, `session ${s.id.slice(0, 8)}`))), loopTabs(s.loop, "history"));
      const req = s.request || {};
      const exp = s.result?.experiment;
      fill(info, h("h2", {}, "Session"), h("dl", { class: "kv grid4" },
        h("dt", {}, "who"), h("dd", {}, s.user),
        h("dt", {}, "started"), h("dd", {}, when(s.started_at)),
        h("dt", {}, "finished"), h("dd", {}, when(s.finished_at)),
        h("dt", {}, "state"), h("dd", {}, s.state === "not_restored" ? h("span", { class: "badge notrestored" }, "loop not restored") : s.state),
        h("dt", {}, "outcome"), h("dd", {}, s.state === "not_restored" ? null : outcomeBadge(s.outcome, s.code), " ", s.message || ""),
        h("dt", {}, "settings"), h("dd", { class: "mono small" }, `${req.controller || "?"} · amp ${quantity(req.amp, u.mv)} · hyst ${req.hysteresis === null ? "auto" : quantity(req.hysteresis, u.pv)}`
          + ` · phase ${fmt(req.phase)}° · Ms ${fmt(req.ms)} · apply ${req.apply ? "yes" : "no"}`),
        h("dt", {}, "saved loop"), h("dd", { class: "mono small" }, s.saved ? `${s.saved.mode} · SP ${pvText(s.saved.sp, u)} · MV ${mvText(s.saved.mv, u)}` : "—"),
        h("dt", {}, "experiment"), h("dd", { class: "mono small" }, exp ? `${fmt(exp.duration)} s · ${exp.periods ?? "—"} periods · ${exp.samples} samples` : "—")));
      const tr = s.trace;
      if (tr && tr.t.length) {
        // The history keeps a whole experiment up to its limit, evenly thinned past it: say which.
        const all = !exp || tr.t.length >= exp.samples;
        fill(traceTitle, all ? "Trace (every sample)" : `Trace (${tr.t.length} of ${exp.samples} samples, evenly thinned)`);
        fitted(traceSvg, (w) => timeChart(traceSvg, { width: w, panels: [
          { height: 170, label: axis("PV", u.pv), yAtLeast: u.pv_range,
            series: [{ name: "PV", cls: "s-pv", x: tr.t, y: tr.pv }, ...(tr.sp ? [{ name: "SP", cls: "s-sp", x: tr.t, y: tr.sp, step: true }] : [])] },
          { height: 110, label: axis("MV", u.mv), yAtLeast: u.mv_range,
            series: [{ name: "MV", cls: "s-mv", x: tr.t, y: tr.mv, step: true }] },
        ], xLabel: "plant seconds from the start" }), 960);
      } else {
        add(traceCard, h("p", { class: "muted" }, "No trace recorded."));
      }
      await renderResult(box, s, { title: "Result", units: u });
    } catch (err) {
      notify(err, info);
    }
  })();
  return () => { closed = true; };
}
