// The loop page's head (the loop's name, the live readouts of mode, PV, SP and MV, the tabs) and its tuning-state
// card (TBSY/TE/ite, the stage and progress, the controller's gains now, the last tuning).

import { STAGES, loopTabs, modeBadge, outcomeBadge, paramLabel, progressBar, readout, restoreBox, statusOf,
  tuningFlags, when } from "./display.js";
import { $, fill, h } from "./dom.js";
import { PARAMS, paramText } from "./gains.js";
import { mvText, pvText, unitsOf } from "./units.js";

export function loopHead(id) {
  // Its links (← all loops, the tabs) never leave the page; an update refills the text around them. Chromium sends
  // no click when the pressed element left the document before the release, even if it is back by then: a state
  // event redrawing the head (the tabs moved into the new one) between the press and the release lost a click.
  const heading = h("h1", {});
  const link = h("div", { class: "muted small" });
  const readouts = h("div", { class: "readouts" });
  const node = h("section", { class: "loop-head" },
    h("div", { class: "title" }, h("a", { href: "#/", class: "muted small" }, "← all loops"), heading, link),
    readouts, loopTabs(id, "live"));
  return {
    node,
    update(loop) {
      const u = unitsOf(loop);
      fill(heading, loop.id, " ", h("span", { class: "desc" }, loop.description || ""));
      fill(link, `link ${loop.link}`, loop.group ? ` · exclusion group ${loop.group}` : "");
      fill(readouts, readout("Mode", modeBadge(loop.mode)), readout("PV", pvText(loop.pv, u), "pv"),
        readout("SP", pvText(loop.sp, u), "sp"), readout("MV", mvText(loop.mv, u), "mv"));
    },
    // The readouts from the newest sample (cheap: no rebuild).
    live(loop) {
      for (const k of ["pv", "sp", "mv"]) {
        const value = node.querySelector(`[data-readout="${k}"]`);
        if (value) value.textContent = k === "mv" ? mvText(loop.mv, unitsOf(loop)) : pvText(loop[k], unitsOf(loop));
      }
    },
  };
}

export function statusCard() {
  const node = h("section", { class: "card status", id: "status" });
  return {
    node,
    update(loop) {
      const st = statusOf(loop);
      node.className = `card status st-${st.cls}`;
      fill(node, h("h2", {}, "Tuning state"),
        h("div", { class: "status-line" }, h("span", { class: `badge big ${st.cls}`, id: "badge" }, st.badge), tuningFlags(loop)),
        loop.restore ? restoreBox(loop) : null,
        h("div", { class: "stage", id: "stage" }, loop.tbsy ? `Stage: ${STAGES[loop.stage] || "starting"}` : st.text),
        loop.tbsy ? progressBar(loop) : null,
        h("div", { class: "muted small", id: "message" }, loop.message ? `message: ${loop.message}` : ""),
        loop.monitor_error ? h("div", { class: "bad small" }, `monitor: ${loop.monitor_error}`) : null,
        currentGains(loop.current_gains, unitsOf(loop)),
        h("dl", { class: "kv small" },
          h("dt", {}, "last tuning"), h("dd", {}, loop.last_tuned_at ? when(loop.last_tuned_at) : "—", " ",
            loop.last_outcome ? outcomeBadge(loop.last_outcome) : ""),
          h("dt", {}, "session"), h("dd", { class: "mono" }, loop.session ? loop.session.slice(0, 8) : "—")));
    },
    // Progress, TBSY/TE/ite and the stage from the newest sample while tuning (the full update runs on state events).
    live(loop) {
      if (!loop.tbsy) return;
      const st = statusOf(loop);
      node.querySelector(".progress")?.replaceWith(progressBar(loop));
      node.querySelector(".flags")?.replaceWith(tuningFlags(loop));
      $("#stage", node).textContent = `Stage: ${STAGES[loop.stage] || "starting"} · ${st.text.split("· ")[1] || ""}`;
    },
  };
}

// The controller's gains now (as last read from it by the monitor, a session's end or an apply).
function currentGains(g, units) {
  return h("div", { class: "current-gains", id: "current-gains" },
    h("h3", {}, "Controller now (read from the device)"),
    g ? h("dl", { class: "kv small params" }, PARAMS.map(([key, label, unit]) => [
      h("dt", {}, paramLabel(label, unit, units)), h("dd", { class: "mono", "data-current": key }, paramText(key, g[key], unit))]))
      : h("p", { class: "muted small" }, "not read yet"));
}
