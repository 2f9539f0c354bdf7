// The loop page (#/loop/ID): the head with the live readouts, the tuning state, the actions, the trend, the loop's
// health and the last session's result — one view per card, each redrawn from one record of the page's state when it changes.

import { eventStream, get } from "./api.js";
import { actionsCard } from "./actions-card.js";
import { esc, fill, h, main } from "./dom.js";
import { healthCard } from "./health-card.js";
import { banner, notify } from "./notices.js";
import { resultCard } from "./result-card.js";
import { loopHead, statusCard } from "./status-card.js";
import { trendCard } from "./trend-card.js";

export function loopView(id) {
  // The page's state: the loop's status as the daemon last sent it (live values patched in from the samples), the
  // session the result card shows, and whether the view is gone.
  const page = { id, loop: null, shownSession: null, closed: false };
  const head = loopHead(id);
  const status = statusCard();
  const actions = actionsCard(page, (loop) => {
    page.loop = loop;
    page.shownSession = null; // the result card shows the session as applied
    update();
  }, () => update());
  const trend = trendCard(page);
  const result = resultCard(page);
  const health = healthCard(page, actions);
  fill(main(), head.node, h("div", { class: "row" }, status.node, actions.node), trend.node, health.node, result.node);

  function update() {
    if (!page.loop || page.closed) return;
    // (health after actions: its "tune now" follows the TUNE button's state)
    for (const view of [head, status, actions, health, result]) view.update(page.loop);
  }

  // Samples come many a second: the trend and the live readouts are redrawn at most every 0.2 s.
  let redraw = null;
  function schedule() {
    if (redraw) return;
    redraw = setTimeout(() => {
      redraw = null;
      if (page.closed) return;
      trend.draw();
      if (page.loop) { head.live(page.loop); status.live(page.loop); }
    }, 200);
  }

  function sample(s) {
    trend.sample(s);
    const loop = page.loop;
    if (loop) {
      for (const k of ["pv", "sp", "mv", "mode"]) if (s[k] !== undefined) loop[k] = s[k];
      if (loop.tbsy && s.stage) Object.assign(loop, { stage: s.stage, progress: s.progress, ite: s.ite });
    }
    schedule();
  }

  function replay(r) {
    trend.replay(r);
    // After a daemon restart the status names no session yet, the replay its newest one (from the history): the
    // result card shows that one, as it would have before the restart.
    const loop = page.loop;
    if (r.session && loop && !loop.session && !loop.tbsy && page.shownSession !== r.session) result.show(r.session);
    schedule();
  }

  function state(data) {
    const loop = page.loop;
    if (data.tbsy && loop?.tbsy === false && loop.session !== data.session) trend.clear(); // a new experiment
    // The experiment's samples end here and the monitor's resume later: no line drawn across the pause.
    if (loop?.tbsy && !data.tbsy) trend.gap();
    // Applied meanwhile (here or elsewhere): the result card says so.
    if (loop?.pending_gains && !data.pending_gains && !data.tbsy && data.session === page.shownSession) page.shownSession = null;
    // Not handed back, or back now: the result card says which (the session's record changes too).
    if (Boolean(loop?.restore) !== Boolean(data.restore)) page.shownSession = null;
    // A state event lacks nothing the page needs; keep the live values the samples brought meanwhile.
    page.loop = { ...loop, ...data };
    update();
    schedule();
  }

  let stream = null;
  (async () => {
    try {
      page.loop = await get(`/loops/${esc(id)}`);
    } catch (err) {
      notify(err, status.node);
      return;
    }
    actions.setDefaults(page.loop);
    update();
    if (page.closed) return;
    stream = eventStream(`/loops/${esc(id)}/events`, {
      state,
      sample,
      replay,
      // The loop's health summary changed (when the stream sends it apart from the state).
      health({ loop: _, ...summary }) {
        if (!page.loop) return;
        page.loop = { ...page.loop, health: summary };
        update();
      },
      status(connected, detail) {
        if (connected) trend.gap();
        banner("stream", connected ? null : `Live stream lost — reconnecting… (${detail || "connection closed"})`);
        trend.stale(!connected);
      },
    });
  })();
  return () => {
    page.closed = true;
    trend.close();
    health.close();
    stream?.close();
    clearTimeout(redraw);
    banner("stream", null);
  };
}
