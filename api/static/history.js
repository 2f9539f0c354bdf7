// A loop's history (#/loop/ID/history): its sessions, newest first, refreshed while open.

import { get } from "./api.js";
import { gainsBrief, loopTabs, outcomeBadge, when } from "./display.js";
import { add, esc, fill, h, main } from "./dom.js";
import { fmt } from "./gains.js";
import { notify } from "./notices.js";
import { loopUnits } from "./session-page.js";
import { derived } from "./units.js";

const HISTORY_REFRESH_MS = 5000;

export function historyView(id) {
  const box = h("section", { class: "card wide" });
  fill(main(), h("section", { class: "loop-head" },
    h("div", { class: "title" }, h("a", { href: "#/", class: "muted small" }, "← all loops"), h("h1", {}, id, " ", h("span", { class: "desc" }, "history"))),
    loopTabs(id, "history")), box);
  let closed = false;
  let shown = null;
  // Refreshed while open: a session that ends (or a read that failed) shows up without a reload.
  const load = async () => {
    try {
      const sessions = await get(`/loops/${esc(id)}/history?limit=200`);
      const u = await loopUnits(id);
      const key = JSON.stringify(sessions);
      if (closed || key === shown) return;
      shown = key;
      const tbody = h("tbody");
      for (const s of sessions) {
        const p = s.result?.point;
        const g = s.result?.gains;
        add(tbody, h("tr", { "data-session": s.id, class: "clickable", onclick: () => { location.hash = `#/session/${esc(s.id)}`; } },
          h("td", {}, h("a", { href: `#/session/${esc(s.id)}` }, when(s.started_at))),
          h("td", {}, s.user),
          h("td", {}, s.state === "running" ? h("span", { class: "badge tuning" }, "running")
            : s.state === "not_restored" ? h("span", { class: "badge notrestored" }, "loop not restored") : outcomeBadge(s.outcome, s.code),
            h("div", { class: "small muted" }, s.message || (s.state === "interrupted" ? "interrupted" : ""))),
          h("td", { class: "mono small" }, s.request?.controller || "—"),
          h("td", { class: "mono small" }, p ? `${fmt(p.omega, 3)} rad/s · ${fmt(p.gain, 3)}${u.pv || u.mv ? ` ${derived("PV/MV", u)}` : ""}`
            + ` ∠${fmt(p.phase_deg, 3)}°` : "—"),
          h("td", {}, gainsBrief(s.gains_before, u)),
          h("td", {}, gainsBrief(g || null, u)),
          h("td", {}, s.applied_at ? h("span", { class: "badge ok" }, `applied${s.applied_by ? ` by ${s.applied_by}` : ""}`)
            : s.request?.apply && s.outcome === "success" ? h("span", { class: "badge ok" }, "written") : h("span", { class: "muted small" }, "—"))));
      }
      fill(box, h("div", { class: "card-head" }, h("h2", {}, `${sessions.length} session${sessions.length === 1 ? "" : "s"}`)),
        sessions.length ? h("div", { class: "scroll-x" }, h("table", { class: "history", id: "history" },
          h("thead", {}, h("tr", {}, h("th", {}, "Started"), h("th", {}, "Who"), h("th", {}, "Outcome"), h("th", {}, "Type"),
            h("th", {}, "Identified point"), h("th", {}, "Gains before"), h("th", {}, "Gains designed"), h("th", {}, "Applied"))),
          tbody)) : h("p", { class: "muted" }, "No sessions yet."));
    } catch (err) {
      shown = null;
      notify(err, box);
    }
  };
  load();
  const timer = setInterval(load, HISTORY_REFRESH_MS);
  return () => { closed = true; clearInterval(timer); };
}
