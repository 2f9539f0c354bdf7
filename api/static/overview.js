// The loop overview (#/): every loop's values, health, tuning state, last tuning and gains, live from one event
// stream; sorted as configured or by the daemon's health rank (worst first).

import { eventStream } from "./api.js";
import { clock, gainsBrief, modeBadge, outcomeBadge, progressBar, restoreBox, statusOf, tuningFlags,
  when } from "./display.js";
import { $, esc, fill, h, main } from "./dom.js";
import { healthCell } from "./health.js";
import { boxOf, boxed, hold, release, sameContents } from "./hold.js";
import { banner } from "./notices.js";
import { mvText, pvText, unitsOf } from "./units.js";

const cell = (attrs, ...children) => boxed("td", attrs, ...children);
const head = (text, attrs = {}) => boxed("th", attrs, text);

// Whether the overview is sorted by health: kept while the page is open (coming back from a loop keeps the order).
let byHealth = false;

export function overviewView() {
  const tbody = h("tbody");
  const table = h("table", { class: "loops", id: "loops" },
    h("thead", {}, h("tr", {},
      head("Loop"), head("Mode"), head("PV", { class: "num" }), head("SP", { class: "num" }), head("MV", { class: "num" }),
      head("Health"), head("Tuning (TBSY / TE / ite)"), head("Last tuning"), head("Gains"))),
    tbody);
  const sortButton = h("button", { type: "button", class: "ghost sort", id: "sort-health", onclick: () => {
    byHealth = !byHealth;
    sort();
  } });
  fill(main(), h("section", { class: "card wide" },
    h("div", { class: "card-head" }, h("h1", {}, "Loops"),
      h("div", { class: "head-tools" }, sortButton, h("span", { class: "muted", id: "updated" }, ""))), table));
  const rows = new Map();
  const order = []; // the loops' ids as the daemon lists them (the config's order)
  // While the pointer is over the table no row moves (a row moving under it turned a click aimed at one loop into a
  // click on another): sorted by health, a new rank waits until the pointer leaves; and no row changes height,
  // its cells held (hold.js) until the pointer leaves, or held anew for a new width of the page.
  let pointed = false;
  const point = (over) => {
    pointed = over;
    table.classList.toggle("held", over);
    if (over) hold(table);
    else release(table);
  };
  const resized = () => { if (pointed) { release(table); hold(table); } };
  table.addEventListener("pointerenter", () => point(true));
  table.addEventListener("pointerleave", () => { point(false); if (byHealth) sort(); });
  window.addEventListener("resize", resized);

  // Worst first by the daemon's rank (then loop id, as GET /loop-health), or as configured.
  function sort() {
    sortButton.textContent = byHealth ? "Sorted: worst health first" : "Sort by health";
    sortButton.setAttribute("aria-pressed", byHealth ? "true" : "false");
    sortButton.title = byHealth ? "back to the configured order" : "the loops with the worst health first";
    const rank = (id) => loops.get(id)?.health?.rank ?? -Infinity;
    const ids = byHealth ? [...order].sort((a, b) => rank(b) - rank(a) || (a < b ? -1 : a > b ? 1 : 0)) : order;
    // Moved only when out of place: a row being clicked is not taken from under the pointer for nothing.
    ids.forEach((id, i) => { if (tbody.children[i] !== rows.get(id)) tbody.insertBefore(rows.get(id), tbody.children[i] || null); });
  }

  function row(loop) {
    const st = statusOf(loop);
    const u = unitsOf(loop);
    const tr = h("tr", { "data-loop": loop.id, class: `st-${st.cls}` },
      cell({}, h("a", { href: `#/loop/${esc(loop.id)}`, class: "loop-id" }, loop.id),
        h("div", { class: "muted small" }, loop.description || ""),
        loop.monitor_error ? h("div", { class: "bad small" }, `monitor: ${loop.monitor_error}`) : null),
      cell({ "data-col": "mode", "data-label": "Mode" }, modeBadge(loop.mode)),
      cell({ class: "num", "data-col": "pv", "data-label": "PV" }, pvText(loop.pv, u)),
      cell({ class: "num", "data-col": "sp", "data-label": "SP" }, pvText(loop.sp, u)),
      cell({ class: "num", "data-col": "mv", "data-label": "MV" }, mvText(loop.mv, u)),
      cell({ "data-col": "health", "data-label": "Health" }, healthCell(loop.health ?? null)),
      cell({ "data-col": "status", "data-label": "Tuning" }, statusCell(loop, st)),
      cell({ "data-col": "last", "data-label": "Last tuning" }, loop.last_tuned_at ? h("div", {}, when(loop.last_tuned_at)) : h("div", { class: "muted" }, "never"),
        loop.last_outcome ? outcomeBadge(loop.last_outcome) : null),
      cell({ "data-col": "gains", "data-label": "Gains" }, gainsBrief(loop.current_gains || null, u),
        loop.pending_gains ? h("div", {}, h("span", { class: "badge pending" }, "new gains to apply")) : null));
    return tr;
  }

  function statusCell(loop, st) {
    return [h("div", { class: "status-line" }, h("span", { class: `badge ${st.cls}` }, st.badge), tuningFlags(loop)),
      loop.restore ? restoreBox(loop) : h("div", { class: "small" }, st.text), loop.tbsy ? progressBar(loop) : null];
  }

  // A live value in place (the row stays: a link being clicked is not replaced under the pointer).
  function refresh(loop) {
    const tr = rows.get(loop.id);
    if (!tr) return;
    const u = unitsOf(loop);
    $("[data-col=pv] > .cell", tr).textContent = pvText(loop.pv, u);
    $("[data-col=sp] > .cell", tr).textContent = pvText(loop.sp, u);
    $("[data-col=mv] > .cell", tr).textContent = mvText(loop.mv, u);
    fill($("[data-col=mode] > .cell", tr), modeBadge(loop.mode));
    if (loop.tbsy) fill($("[data-col=status] > .cell", tr), statusCell(loop, statusOf(loop)));
    $("#updated").textContent = `updated ${clock(Date.now() / 1000)}`;
  }

  // The row drawn anew for a loop's new state or health (`tr`) into the row on the page (`old`): only the cells
  // whose contents changed are refilled (into the cell's box, which keeps any height held), and the loop's link is
  // never taken out of the page (a press on it that spans a health event, every few seconds a loop, would
  // otherwise open nothing).
  function merge(old, tr) {
    old.className = tr.className;
    old.dataset.rank = tr.dataset.rank;
    [...tr.cells].forEach((td, i) => {
      const box = boxOf(old.cells[i]);
      const now = boxOf(td);
      if (sameContents(box, now)) return;
      const link = $("a.loop-id", box);
      if (!link) return box.replaceChildren(...now.childNodes);
      while (link.nextSibling) link.nextSibling.remove();
      link.after(...[...now.childNodes].slice(1)); // the same loop: the same link
    });
  }

  // One event stream for every loop (GET /events): each loop's state when it opens and on every change, its
  // live values (the newest sample, at most one per loop every 0.5 s) in between. No polling.
  const loops = new Map();
  function show(loop) {
    loops.set(loop.id, loop);
    const tr = row(loop);
    const old = rows.get(loop.id);
    tr.dataset.rank = String(loop.health?.rank ?? "");
    const rankChanged = old && tr.dataset.rank !== old.dataset.rank;
    if (old) merge(old, tr);
    else {
      tbody.appendChild(tr);
      order.push(loop.id);
      rows.set(loop.id, tr);
      if (pointed) hold(tr);
    }
    if (byHealth && (!old || rankChanged) && !pointed) sort();
    $("#updated").textContent = `updated ${clock(Date.now() / 1000)}`;
  }
  sort();
  const stream = eventStream("/events", {
    state: show,
    // A loop's health summary changed (a new assessment, pending after a tuning, …).
    health(summary) {
      const loop = loops.get(summary.loop);
      if (!loop) return;
      const { loop: _, ...health } = summary;
      show({ ...loop, health });
    },
    live(s) {
      const loop = loops.get(s.loop);
      if (!loop) return;
      for (const k of ["pv", "sp", "mv", "mode"]) if (s[k] !== undefined) loop[k] = s[k];
      if (loop.tbsy && s.stage) Object.assign(loop, { stage: s.stage, progress: s.progress, ite: s.ite });
      refresh(loop);
    },
    status(connected, detail) {
      banner("overview", connected ? null : `Live stream lost — reconnecting… (${detail || "connection closed"})`);
      tbody.classList.toggle("stale", !connected);
    },
  });
  return () => { stream.close(); banner("overview", null); window.removeEventListener("resize", resized); };
}
