// A loop's health as the daemon assessed it (GET /loops/{id}/health, the status's `health` summary; docs/health.md):
// the words and badges the overview's column and the loop page's health card share. The page ranks, flags and
// recommends nothing itself: severity, rank, flags and recommendation are the daemon's.

import { h } from "./dom.js";

// What each recommendation asks of the operator.
export const ADVICE = {
  retune: "retune the loop",
  check_valve: "check the valve — retuning would not help (and may make it worse)",
  check_sensor: "check the PV sensor",
  put_in_auto: "put the loop in AUTO",
  none: "nothing to do",
};

// The flags' names in words.
export const FLAG_WORDS = {
  manual: "manual", saturated: "saturated", oscillating: "oscillating", stiction: "valve stiction",
  sluggish: "sluggish", noisy: "noisy", frozen_pv: "frozen PV", poor_tracking: "poor tracking",
};

// The badge of a summary (null: never assessed): the severity when assessed, else the state.
export function healthBadge(summary) {
  if (!summary) return h("span", { class: "badge hl-unknown", "data-health": "none" }, "not assessed");
  if (summary.state === "pending") return h("span", { class: "badge hl-pending", "data-health": "pending" }, "collecting");
  if (summary.state === "off") return h("span", { class: "badge hl-off", "data-health": "off" }, "off");
  const sev = summary.severity;
  return h("span", { class: `badge hl-${sev}`, "data-health": sev, title: `severity ${sev}` },
    sev === "none" ? "healthy" : sev);
}

// One flag as a chip, coloured by its severity when known.
export function flagChip(name, severity = null) {
  return h("span", { class: `hflag${severity ? ` hl-${severity}` : ""}`, "data-hflag": name }, FLAG_WORDS[name] || name);
}

// The recommendation in words ("none" says nothing to do).
export function advice(recommendation) {
  return h("span", { class: `advice rec-${recommendation}`, "data-recommendation": recommendation },
    ADVICE[recommendation] || recommendation);
}

// The overview's cell: badge, flags, recommendation — or what the assessment waits for.
export function healthCell(summary) {
  if (!summary || summary.state !== "ok") {
    return [h("div", { class: "status-line" }, healthBadge(summary)),
      summary?.reason ? h("div", { class: "small muted" }, summary.reason)
        : summary?.state === "off" ? h("div", { class: "small muted" }, "health monitoring off for this loop") : null];
  }
  return [h("div", { class: "status-line" }, healthBadge(summary), ...summary.flags.map((f) => flagChip(f))),
    summary.recommendation !== "none" ? h("div", { class: "small" }, advice(summary.recommendation)) : null,
    summary.reason ? h("div", { class: "small muted reason", title: summary.reason }, summary.reason) : null];
}
