// The operator page: login, loop overview, loop page (live trend, TUNE/TBRK/apply, result), history, session.
// Plain ES modules, no build step; routes in the URL's hash: #/, #/loop/ID, #/loop/ID/history, #/session/SID.

import { ApiError, clearToken, eventStream, get, getToken, onUnauthorized, post, setToken, whoami } from "./api.js";
import { PARAMS, ROWS, cell, changes, fmt, paramText } from "./gains.js";
import { clockTicks, cssWidth, el, fitted, nyquist, timeChart } from "./plot.js";
import { NO_UNITS, axis, derived, mvText, pvText, quantity, unitsOf } from "./units.js";

// ---------------------------------------------------------------- helpers

function h(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === undefined || v === null || v === false) continue;
    if (k === "class") node.className = v;
    else if (k.startsWith("on")) node.addEventListener(k.slice(2), v);
    else if (k === "dataset") Object.assign(node.dataset, v);
    else if (k === "style") node.style.cssText = v; // CSSOM: allowed by the page's Content-Security-Policy
    else node.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children.flat(Infinity)) {
    if (c === null || c === undefined || c === false) continue;
    node.appendChild(typeof c === "string" || typeof c === "number" ? document.createTextNode(String(c)) : c);
  }
  return node;
}

const svgNode = (cls, label) => el("svg", { class: cls, role: "img", "aria-label": label });

// append / replaceChildren without the nulls of conditional children (the DOM would print "null").
const clean = (children) => children.flat(Infinity).filter((c) => c !== null && c !== undefined && c !== false);
const add = (node, ...children) => node.append(...clean(children));
const fill = (node, ...children) => node.replaceChildren(...clean(children));

const $ = (sel, root = document) => root.querySelector(sel);
const main = () => $("#main");
const esc = (s) => encodeURIComponent(s);

// Meaning of ite when the experiment has ended: GET /api/v1/codes (value → {name, message, warning}), loaded once
// after login.
const CODES = new Map();
async function loadCodes() {
  if (CODES.size) return;
  try {
    for (const c of await get("/codes")) CODES.set(c.value, c);
  } catch (err) {
    if (err.status !== 401) notify(err); // the page still shows each session's own message
  }
}
// "code 3 NO_OSCILLATION" (the name when the daemon gave the table).
function codeName(code) {
  const c = CODES.get(code);
  return c ? `code ${code} ${c.name}` : `code ${code}`;
}

const STAGES = { noise: "measuring noise", relay: "relay experiment", done: "designing" };

function when(iso) {
  if (!iso) return "—";
  const d = new Date(iso);
  if (Number.isNaN(d.getTime())) return iso;
  const pad = (n) => String(n).padStart(2, "0");
  return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
}

function clock(unix) {
  const d = new Date(unix * 1000);
  const pad = (n) => String(n).padStart(2, "0");
  return `${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
}

// The loop's state in words and a CSS class: tuning, notrestored, failed, warn, ok, idle.
function statusOf(loop) {
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
function withMessage(code, message) {
  return !message || code.toLowerCase().endsWith(` ${message.toLowerCase()}`) ? code : `${code}: ${message}`;
}

// A loop the daemon could not hand back yet: what it restores, since when, how often it tried and why it failed.
function restoreText(r) {
  return `the daemon retries handing it back to ${r.mode} at MV ${fmt(r.mv)} · ${r.attempts} attempt${r.attempts === 1 ? "" : "s"} `
    + `since ${when(r.since)} · last error: ${r.last_error}`;
}

// The prominent box of a loop not handed back (overview row and loop page), with what the operator can do.
function restoreBox(loop) {
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
function timeLeft(loop) {
  const plant = Math.max(0, loop.ite);
  const speed = loop.speed || 1;
  const wall = `about ${duration(plant / speed)} left`;
  return speed === 1 ? wall : `${wall} (ite ${Math.round(plant)} plant s at ${fmt(speed, 3)}× real time)`;
}

function duration(seconds) {
  if (seconds < 90) return `${Math.round(seconds)} s`;
  if (seconds < 5400) return `${Math.round(seconds / 60)} min`;
  return `${fmt(seconds / 3600, 2)} h`;
}

function flags(loop) {
  const ite = loop.tbsy ? `${fmt(Math.max(0, loop.ite), 3)} s` : String(Math.round(loop.ite));
  return h("span", { class: "flags" },
    h("span", { class: `flag ${loop.tbsy ? "on" : ""}`, "data-flag": "tbsy" }, `TBSY ${loop.tbsy ? 1 : 0}`),
    h("span", { class: `flag ${loop.te ? "on bad" : ""}`, "data-flag": "te" }, `TE ${loop.te ? 1 : 0}`),
    h("span", { class: "flag ite", "data-flag": "ite" }, `ite ${ite}`));
}

// Only while tuning: a finished or failed session has no "progress" to show (the badge and code say how it ended).
function progressBar(loop) {
  const pct = Math.round(100 * (loop.progress || 0));
  return h("div", { class: "progress running", role: "progressbar", "aria-valuenow": pct,
                    "aria-valuemin": 0, "aria-valuemax": 100 },
    h("div", { class: "bar", style: `width:${pct}%` }), h("span", {}, `${pct} %`));
}

function modeBadge(mode) {
  if (!mode) return h("span", { class: "mode unknown" }, "—");
  return h("span", { class: `mode ${mode === "AUTO" ? "auto" : "man"}` }, mode);
}

function outcomeBadge(outcome, code) {
  if (!outcome) return h("span", { class: "badge idle" }, "—");
  const ok = outcome === "success";
  return h("span", { class: `badge ${ok ? "ok" : "failed"}` },
    ok ? "success" : `failure${code !== null && code !== undefined ? ` (${code})` : ""}`);
}

// ---------------------------------------------------------------- messages and banners

function notify(error, where = null) {
  const text = error instanceof ApiError ? error.text : String(error.message || error);
  const box = where || $("#toasts");
  const node = h("div", { class: "alert error", role: "alert" }, h("span", {}, text),
    h("button", { class: "close", title: "dismiss", onclick: () => node.remove() }, "×"));
  if (where) fill(where, node);
  else {
    box.appendChild(node);
    setTimeout(() => node.remove(), 12000);
  }
  return node;
}

function banner(id, text) {
  const box = $("#banners");
  let node = box.querySelector(`[data-banner="${id}"]`);
  if (!text) { node?.remove(); return; }
  if (!node) { node = h("div", { class: "banner", "data-banner": id, role: "status" }); box.appendChild(node); }
  node.textContent = text;
}

// ---------------------------------------------------------------- session of the page (who is logged in)

const me = { name: null, role: null };
const canOperate = () => me.role === "operator" || me.role === "admin";

function renderWho() {
  const box = $("#who");
  fill(box);
  if (!getToken()) return;
  add(box, h("span", { class: `role ${me.role || ""}`, "data-role": me.role || "" }, me.role || "?"),
    me.name ? h("span", { class: "name" }, me.name) : null,
    h("button", { class: "ghost", id: "logout", onclick: logout }, "Log out"));
}

function logout() {
  clearToken();
  me.name = me.role = null;
  renderWho();
  location.hash = "#/login";
}

onUnauthorized((err) => {
  clearToken();
  me.name = me.role = null;
  renderWho();
  loginMessage = err.text;
  if (location.hash !== "#/login") location.hash = "#/login";
  else route();
});

// ---------------------------------------------------------------- views

let loginMessage = null;

function loginView() {
  const input = h("input", { type: "password", id: "token", name: "token", autocomplete: "off", spellcheck: "false",
                             placeholder: "paste the API token", required: true });
  const msg = h("div", { class: "form-msg", id: "login-msg" });
  if (loginMessage) { notify(new Error(loginMessage), msg); loginMessage = null; }
  const form = h("form", { class: "card login", id: "login", onsubmit: async (ev) => {
    ev.preventDefault();
    const token = input.value.trim();
    if (!token) return;
    try {
      const who = await whoami(token);
      setToken(token);
      Object.assign(me, who);
      renderWho();
      if (!location.hash || location.hash === "#/login") location.hash = "#/";
      else route();
    } catch (err) {
      notify(err.status === 401 ? new Error("This token is not known to the daemon (401).") : err, msg);
    }
  } },
  h("h1", {}, "Log in"),
  h("p", { class: "muted" }, "Paste an API token. It is kept in this browser tab's session storage only and sent as ",
    h("code", {}, "Authorization: Bearer"), " to the daemon. A viewer token sees everything and can press nothing."),
  h("label", { for: "token" }, "Token"), input,
  h("button", { type: "submit", class: "primary" }, "Log in"), msg);
  fill(main(), form);
  input.focus();
  return () => {};
}

// -- overview

function overviewView() {
  const tbody = h("tbody");
  const table = h("table", { class: "loops", id: "loops" },
    h("thead", {}, h("tr", {},
      h("th", {}, "Loop"), h("th", {}, "Mode"), h("th", { class: "num" }, "PV"), h("th", { class: "num" }, "SP"),
      h("th", { class: "num" }, "MV"), h("th", {}, "Tuning (TBSY / TE / ite)"), h("th", {}, "Last tuning"),
      h("th", {}, "Gains"))),
    tbody);
  fill(main(), h("section", { class: "card wide" },
    h("div", { class: "card-head" }, h("h1", {}, "Loops"), h("span", { class: "muted", id: "updated" }, "")), table));
  const rows = new Map();

  function row(loop) {
    const st = statusOf(loop);
    const u = unitsOf(loop);
    const tr = h("tr", { "data-loop": loop.id, class: `st-${st.cls}` },
      h("td", {}, h("a", { href: `#/loop/${esc(loop.id)}`, class: "loop-id" }, loop.id),
        h("div", { class: "muted small" }, loop.description || ""),
        loop.monitor_error ? h("div", { class: "bad small" }, `monitor: ${loop.monitor_error}`) : null),
      h("td", { "data-col": "mode", "data-label": "Mode" }, modeBadge(loop.mode)),
      h("td", { class: "num", "data-col": "pv", "data-label": "PV" }, pvText(loop.pv, u)),
      h("td", { class: "num", "data-col": "sp", "data-label": "SP" }, pvText(loop.sp, u)),
      h("td", { class: "num", "data-col": "mv", "data-label": "MV" }, mvText(loop.mv, u)),
      h("td", { "data-col": "status", "data-label": "Tuning" }, statusCell(loop, st)),
      h("td", { "data-col": "last", "data-label": "Last tuning" }, loop.last_tuned_at ? h("div", {}, when(loop.last_tuned_at)) : h("div", { class: "muted" }, "never"),
        loop.last_outcome ? outcomeBadge(loop.last_outcome) : null),
      h("td", { "data-col": "gains", "data-label": "Gains" }, gainsBrief(loop.current_gains || null, u),
        loop.pending_gains ? h("div", {}, h("span", { class: "badge pending" }, "new gains to apply")) : null));
    return tr;
  }

  function statusCell(loop, st) {
    return [h("div", { class: "status-line" }, h("span", { class: `badge ${st.cls}` }, st.badge), flags(loop)),
      loop.restore ? restoreBox(loop) : h("div", { class: "small" }, st.text), loop.tbsy ? progressBar(loop) : null];
  }

  // A live value in place (the row stays: a link being clicked is not replaced under the pointer).
  function refresh(loop) {
    const tr = rows.get(loop.id);
    if (!tr) return;
    const u = unitsOf(loop);
    $("[data-col=pv]", tr).textContent = pvText(loop.pv, u);
    $("[data-col=sp]", tr).textContent = pvText(loop.sp, u);
    $("[data-col=mv]", tr).textContent = mvText(loop.mv, u);
    fill($("[data-col=mode]", tr), modeBadge(loop.mode));
    if (loop.tbsy) fill($("[data-col=status]", tr), statusCell(loop, statusOf(loop)));
    $("#updated").textContent = `updated ${clock(Date.now() / 1000)}`;
  }

  // One event stream for every loop (GET /events): each loop's state when it opens and on every change, its
  // live values (the newest sample, at most one per loop every 0.5 s) in between. No polling.
  const loops = new Map();
  function show(loop) {
    loops.set(loop.id, loop);
    const tr = row(loop);
    const old = rows.get(loop.id);
    if (old) old.replaceWith(tr);
    else tbody.appendChild(tr);
    rows.set(loop.id, tr);
    $("#updated").textContent = `updated ${clock(Date.now() / 1000)}`;
  }
  const stream = eventStream("/events", {
    state: show,
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
  return () => { stream.close(); banner("overview", null); };
}

// K (in the loop's MV/PV units when it names them), Ti and Td in a few characters.
function gainsBrief(g, units = NO_UNITS) {
  if (!g) return h("span", { class: "muted" }, "—");
  const k = units.pv || units.mv ? ` ${derived("MV/PV", units)}` : "";
  return h("span", { class: "mono small" }, `K ${fmt(g.pk, 3)}${k} · Ti ${g.pti === null ? "∞" : `${fmt(g.pti, 3)} s`}`
    + (g.ptd ? ` · Td ${fmt(g.ptd, 3)} s` : ""));
}

// -- loop page

function loopTabs(id, active) {
  return h("nav", { class: "tabs" },
    h("a", { href: `#/loop/${esc(id)}`, class: active === "live" ? "active" : "" }, "Live"),
    h("a", { href: `#/loop/${esc(id)}/history`, class: active === "history" ? "active" : "", id: "tab-history" }, "History"));
}

const TREND_WINDOW = 600; // wall seconds kept in the trend (more to keep the whole of the last experiment)
const TREND_MAX = 30000; // samples kept
// The trend of each loop seen since the page was opened (kept when the operator looks at another view).
const trends = new Map();

function loopView(id) {
  let loop = null;
  let shownSession = null;
  let stream = null;
  let redraw = null;
  let closed = false;
  if (!trends.has(id)) trends.set(id, { time: [], pv: [], sp: [], mv: [], relay: [] });
  const trend = trends.get(id);
  // Wall times of the experiment's first and last samples in the trend (null: none), so the window keeps it.
  let experiment = null;
  // A break in the lines where samples were missed (another view, a lost stream).
  const gap = () => {
    const n = trend.time.length;
    if (!n || trend.pv[n - 1] === null) return;
    trend.time.push(trend.time[n - 1]);
    for (const k of ["pv", "sp", "mv", "relay"]) trend[k].push(null);
  };

  const head = h("section", { class: "loop-head" });
  // Built once and moved into each new head: a click on a tab is never lost to an update that would replace the
  // tab between the mouse's press and release (no click event then).
  const tabs = loopTabs(id, "live");
  const status = h("section", { class: "card status", id: "status" });
  const actions = h("section", { class: "card actions", id: "actions" });
  const trendSvg = svgNode("trend", "trend of PV, SP and MV");
  trendSvg.id = "trend";
  const trendCard = h("section", { class: "card wide" },
    h("div", { class: "card-head" }, h("h2", {}, "Trend"), h("span", { class: "muted small", id: "trend-info" }, "waiting for samples…")),
    trendSvg);
  const result = h("section", { class: "card wide result", id: "result" });
  fill(main(), head, h("div", { class: "row" }, status, actions), trendCard, result);

  // The form, built once (so typing is not lost on updates); its defaults from the loop when the API gives them.
  const form = tuneForm(id, () => loop);
  const actionMsg = h("div", { class: "form-msg", id: "action-msg" });
  const tbrk = h("button", { type: "button", class: "danger", id: "tbrk", onclick: async () => {
    fill(actionMsg);
    try { await post(`/loops/${esc(id)}/break`); } catch (err) { notify(err, actionMsg); }
  } }, "TBRK — abort");
  const apply = h("button", { type: "button", class: "secondary", id: "apply", onclick: () => confirmApply() }, "Apply gains…");
  const applyBox = h("div", { class: "apply-box", id: "apply-box" });
  const roleNote = h("p", { class: "muted small", id: "role-note" });
  add(actions, h("h2", {}, "Actions"), form.node, h("div", { class: "buttons" }, tbrk, apply), applyBox, actionMsg, roleNote);
  form.onError = (err) => notify(err, actionMsg);
  form.onStart = () => fill(actionMsg);

  // The confirmation lists every parameter that changes, the controller's value now → the designed one.
  function confirmApply() {
    const g = loop?.gains;
    if (!g) return;
    fill(actionMsg);
    const diff = changes(loop.current_gains, g);
    const changed = diff.filter((d) => d.changed);
    const same = diff.filter((d) => !d.changed);
    fill(applyBox, h("div", { class: "confirm", id: "apply-dialog" },
      h("p", {}, `Write these gains to the controller of ${id}?`),
      h("table", { class: "changes", id: "apply-changes" },
        h("thead", {}, h("tr", {}, h("th", {}, ""), h("th", { class: "num" }, "now"), h("th", {}, ""),
          h("th", { class: "num" }, "new"))),
        h("tbody", {}, changed.map((d) => h("tr", { "data-param": d.key },
          h("th", {}, paramLabel(d.label, d.unit, unitsOf(loop))), h("td", { class: "num old" }, d.before === undefined ? "unknown" : paramText(d.key, d.before, d.unit)),
          h("td", { class: "arrow" }, "→"), h("td", { class: "num new" }, paramText(d.key, d.after, d.unit)))))),
      same.length ? h("p", { class: "muted small" }, `unchanged: ${same.map((d) => `${d.label} = ${paramText(d.key, d.after, d.unit)}`).join(", ")}`) : null,
      loop.current_gains ? null : h("p", { class: "muted small" }, "The controller's gains have not been read yet."),
      h("div", { class: "buttons" },
        h("button", { type: "button", class: "primary", id: "apply-confirm", onclick: async () => {
          fill(applyBox);
          try {
            const body = loop?.session ? { session: loop.session } : {};
            const answer = await post(`/loops/${esc(id)}/apply`, body);
            fill(actionMsg, h("div", { class: "alert ok", id: "apply-done" },
              `Gains of session ${String(answer?.session || "").slice(0, 8)} written to the controller.`));
            loop = await get(`/loops/${esc(id)}`);
            shownSession = null; // the result card shows the session as applied
            update();
          } catch (err) { notify(err, actionMsg); }
        } }, "Confirm"),
        h("button", { type: "button", class: "ghost", id: "apply-cancel", onclick: () => fill(applyBox) }, "Cancel"))));
  }

  function update() {
    if (!loop || closed) return;
    const u = unitsOf(loop);
    fill(head, 
      h("div", { class: "title" }, h("a", { href: "#/", class: "muted small" }, "← all loops"),
        h("h1", {}, loop.id, " ", h("span", { class: "desc" }, loop.description || "")),
        h("div", { class: "muted small" }, `link ${loop.link}`, loop.group ? ` · exclusion group ${loop.group}` : "")),
      h("div", { class: "readouts" },
        readout("Mode", modeBadge(loop.mode)), readout("PV", pvText(loop.pv, u), "pv"),
        readout("SP", pvText(loop.sp, u), "sp"), readout("MV", mvText(loop.mv, u), "mv")),
      tabs);
    const st = statusOf(loop);
    status.className = `card status st-${st.cls}`;
    fill(status, h("h2", {}, "Tuning state"),
      h("div", { class: "status-line" }, h("span", { class: `badge big ${st.cls}`, id: "badge" }, st.badge), flags(loop)),
      loop.restore ? restoreBox(loop) : null,
      h("div", { class: "stage", id: "stage" }, loop.tbsy ? `Stage: ${STAGES[loop.stage] || "starting"}` : st.text),
      loop.tbsy ? progressBar(loop) : null,
      h("div", { class: "muted small", id: "message" }, loop.message ? `message: ${loop.message}` : ""),
      loop.monitor_error ? h("div", { class: "bad small" }, `monitor: ${loop.monitor_error}`) : null,
      currentGains(loop.current_gains, u),
      h("dl", { class: "kv small" },
        h("dt", {}, "last tuning"), h("dd", {}, loop.last_tuned_at ? when(loop.last_tuned_at) : "—", " ",
          loop.last_outcome ? outcomeBadge(loop.last_outcome) : ""),
        h("dt", {}, "session"), h("dd", { class: "mono" }, loop.session ? loop.session.slice(0, 8) : "—")));
    // Buttons: enabled only when the state allows and the token may operate.
    const operate = canOperate();
    form.setEnabled(operate && !loop.tbsy, !operate ? "needs an operator token" : loop.tbsy ? "the loop is tuning" : "");
    tbrk.disabled = !(operate && loop.tbsy);
    tbrk.title = !operate ? "needs an operator token" : loop.tbsy ? "abort the experiment and restore the loop" : "nothing runs";
    const pending = loop.pending_gains && !loop.restore; // the daemon writes nothing to a loop not handed back
    apply.disabled = !(operate && !loop.tbsy && pending);
    if (loop.restore) form.setEnabled(false, "the loop is not handed back yet (LOOP NOT RESTORED)");
    apply.title = !operate ? "needs an operator token" : loop.tbsy ? "the loop is tuning"
      : loop.restore ? "the loop is not handed back yet"
      : !pending ? "no new gains to apply" : "write the new gains to the controller";
    if (apply.disabled) fill(applyBox);
    roleNote.textContent = operate ? "" : `Logged in with a ${me.role || "viewer"} token: you can watch, not act.`;
    if (!loop.tbsy && loop.session && loop.session !== shownSession) showResult(loop.session);
    if (loop.tbsy && shownSession !== null && loop.session !== shownSession) {
      shownSession = null;
      fill(result, h("h2", {}, "Result"), h("p", { class: "muted" }, "The experiment is running; the result shows when it ends."));
    }
  }

  async function showResult(sid) {
    shownSession = sid;
    if (!result.firstChild) fill(result, h("h2", {}, "Result"), h("p", { class: "muted" }, "loading…"));
    try {
      const session = await get(`/sessions/${esc(sid)}`);
      if (shownSession !== sid || closed) return;
      await renderResult(result, session, { title: "Last session", pending: loop?.pending_gains, units: unitsOf(loop),
                                            restore: loop?.restore });
    } catch (err) {
      if (shownSession === sid) notify(err, result);
    }
  }

  // One sample into the trend: a break in the lines where the experiment's samples give way to the monitor's.
  function push(time, pv, sp, mv, relay) {
    const n = trend.time.length;
    if (n && trend.pv[n - 1] !== null && (trend.relay[n - 1] === null) !== (relay === null)) gap();
    trend.time.push(time);
    trend.pv.push(pv);
    trend.sp.push(sp);
    trend.mv.push(mv);
    trend.relay.push(relay);
    if (relay !== null) experiment = experiment ? [experiment[0], time] : [time, time];
  }

  // Samples older than the window go, unless they are of the last experiment (kept whole while it is recent).
  function trim(now) {
    const span = experiment ? experiment[1] - experiment[0] : 0;
    const keep = Math.max(TREND_WINDOW, 2 * span);
    const cut = trend.time.findIndex((x) => x >= now - keep);
    const drop = Math.max(cut, trend.time.length - TREND_MAX);
    if (drop > 0) for (const k of Object.keys(trend)) trend[k].splice(0, drop);
    if (experiment && trend.time[0] > experiment[1]) experiment = null;
  }

  // The daemon's trend when the stream opens (the running or last session from its start, then the monitor):
  // it replaces what the page held.
  function replay(r) {
    for (const k of Object.keys(trend)) trend[k].length = 0;
    experiment = null;
    for (let i = 0; i < r.time.length; i++) push(r.time[i], r.pv[i], r.sp[i], r.mv[i], r.relay[i]);
    if (r.time.length) trim(r.time[r.time.length - 1]);
    // After a daemon restart the status names no session yet, the replay its newest one (from the history): the
    // result card shows that one, as it would have before the restart.
    if (r.session && loop && !loop.session && !loop.tbsy && shownSession !== r.session) showResult(r.session);
    schedule();
  }

  function sample(s) {
    const t = typeof s.time === "number" ? s.time : Date.now() / 1000;
    push(t, s.pv ?? null, s.sp ?? null, s.mv ?? null, s.relay ?? null);
    trim(t);
    if (loop) {
      if (s.pv !== undefined) loop.pv = s.pv;
      if (s.sp !== undefined) loop.sp = s.sp;
      if (s.mv !== undefined) loop.mv = s.mv;
      if (s.mode !== undefined) loop.mode = s.mode;
      if (loop.tbsy && s.stage) {
        loop.stage = s.stage;
        loop.progress = s.progress;
        loop.ite = s.ite;
      }
    }
    schedule();
  }

  function schedule() {
    if (redraw) return;
    redraw = setTimeout(() => {
      redraw = null;
      if (closed) return;
      drawTrend();
      updateLive();
    }, 200);
  }

  // Cheap updates from samples: readouts, progress, ite (the full update runs on state events).
  function updateLive() {
    if (!loop) return;
    for (const k of ["pv", "sp", "mv"]) {
      const node = head.querySelector(`[data-readout="${k}"]`);
      if (node) node.textContent = k === "mv" ? mvText(loop.mv, unitsOf(loop)) : pvText(loop[k], unitsOf(loop));
    }
    if (loop.tbsy) {
      const st = statusOf(loop);
      const bar = status.querySelector(".progress");
      if (bar) bar.replaceWith(progressBar(loop));
      const fl = status.querySelector(".flags");
      if (fl) fl.replaceWith(flags(loop));
      $("#stage", status).textContent = `Stage: ${STAGES[loop.stage] || "starting"} · ${st.text.split("· ")[1] || ""}`;
    }
  }

  const trendWidth = () => cssWidth(trendSvg) || 960;
  const resized = new ResizeObserver(() => {
    if (!closed && trend.time.length && Number(trendSvg.dataset.width) !== trendWidth()) drawTrend();
  });
  resized.observe(trendSvg);

  function drawTrend() {
    const n = trend.time.length;
    $("#trend-info").textContent = n ? `${n} samples · last ${clock(trend.time[n - 1])}` : "waiting for samples…";
    if (!n) return;
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
    timeChart(trendSvg, { width: trendWidth(), xRange: [x0, x1], panels, xTick: clock, xTicks: clockTicks,
                          xLabel: "time (clock)" });
    trendSvg.dataset.samples = n;
    trendSvg.dataset.first = trend.time[0];
    trendSvg.dataset.experimentStart = experiment ? experiment[0] : "";
    trendSvg.dataset.width = trendWidth();
  }

  async function start() {
    try {
      loop = await get(`/loops/${esc(id)}`);
    } catch (err) {
      notify(err, status);
      return;
    }
    form.setDefaults(loop);
    update();
    stream = eventStream(`/loops/${esc(id)}/events`, {
      state(data) {
        const startedNew = data.tbsy && loop?.tbsy === false && loop.session !== data.session;
        if (startedNew) { for (const k of Object.keys(trend)) trend[k].length = 0; experiment = null; }
        // The experiment's samples end here and the monitor's resume later: no line drawn across the pause.
        if (loop?.tbsy && !data.tbsy) gap();
        // Applied meanwhile (here or elsewhere): the result card says so.
        if (loop?.pending_gains && !data.pending_gains && !data.tbsy && data.session === shownSession) shownSession = null;
        // Not handed back, or back now: the result card says which (the session's record changes too).
        if (Boolean(loop?.restore) !== Boolean(data.restore)) shownSession = null;
        // A state event lacks nothing the page needs; keep the live values the samples brought meanwhile.
        loop = { ...loop, ...data };
        update();
        schedule();
      },
      sample,
      replay,
      status(connected, detail) {
        if (connected) gap();
        banner("stream", connected ? null : `Live stream lost — reconnecting… (${detail || "connection closed"})`);
        trendCard.classList.toggle("stale", !connected);
      },
    });
  }
  start();
  return () => {
    closed = true;
    resized.disconnect();
    stream?.close();
    clearTimeout(redraw);
    banner("stream", null);
  };
}

function readout(label, value, key) {
  return h("div", { class: "readout" }, h("div", { class: "label" }, label),
    h("div", { class: "value", "data-readout": key || label.toLowerCase() }, value));
}

// A parameter's label with its unit when that is in the loop's MV/PV units ("K (%/°C)"); seconds stay with values.
function paramLabel(label, unit, units) {
  return /MV|PV/.test(unit) && (units.pv || units.mv) ? `${label} (${derived(unit, units)})` : label;
}

// The controller's gains now (as last read from it by the monitor, a session's end or an apply).
function currentGains(g, units) {
  return h("div", { class: "current-gains", id: "current-gains" },
    h("h3", {}, "Controller now (read from the device)"),
    g ? h("dl", { class: "kv small params" }, PARAMS.map(([key, label, unit]) => [
      h("dt", {}, paramLabel(label, unit, units)), h("dd", { class: "mono", "data-current": key }, paramText(key, g[key], unit))]))
      : h("p", { class: "muted small" }, "not read yet"));
}

// The TUNE form: controller, amp, hysteresis, phase, Ms, apply; only filled fields are sent (others: loop default).
function tuneForm(id, getLoop) {
  const fields = {
    controller: h("select", { name: "controller", id: "f-controller" }, h("option", { value: "PI" }, "PI"), h("option", { value: "PID" }, "PID")),
    amp: h("input", { name: "amp", id: "f-amp", type: "number", step: "any", inputmode: "decimal" }),
    hysteresis: h("input", { name: "hysteresis", id: "f-hysteresis", type: "number", step: "any", placeholder: "auto (3σ of noise)" }),
    phase: h("input", { name: "phase", id: "f-phase", type: "number", step: "any" }),
    ms: h("input", { name: "ms", id: "f-ms", type: "number", step: "any" }),
    apply: h("select", { name: "apply", id: "f-apply" }, h("option", { value: "" }, "loop default"),
      h("option", { value: "true" }, "yes, on success"), h("option", { value: "false" }, "no, I apply them")),
  };
  // Disabled until the loop's status is known (and the form holds its defaults): see setEnabled.
  const button = h("button", { type: "submit", class: "primary", id: "tune", disabled: true }, "TUNE");
  const row = (label, field, unit, hint) => h("label", { class: "field", "data-field": field.name },
    h("span", { class: "label" }, label), field, h("span", { class: "unit", "data-unit": field.name }, unit || ""), hint ? h("span", { class: "hint" }, hint) : null);
  const obj = { onError: null, onStart: null };
  const node = h("form", { class: "tune-form", id: "tune-form", novalidate: true, onsubmit: async (ev) => {
    ev.preventDefault();
    for (const f of Object.values(fields)) f.closest(".field").classList.remove("invalid");
    obj.onStart?.();
    const body = {};
    if (fields.controller.value) body.controller = fields.controller.value;
    for (const k of ["amp", "hysteresis", "phase", "ms"]) {
      const raw = fields[k].value.trim();
      if (raw !== "") body[k] = Number(raw);
      else if (fields[k].validity.badInput) body[k] = fields[k].value; // let the API name it
    }
    if (fields.apply.value) body.apply = fields.apply.value === "true";
    button.disabled = true;
    try {
      await post(`/loops/${esc(id)}/tune`, body);
    } catch (err) {
      if (err instanceof ApiError) {
        for (const f of err.fields) fields[f]?.closest(".field").classList.add("invalid");
      }
      obj.onError?.(err);
      button.disabled = Boolean(getLoop()?.tbsy) || !canOperate();
    }
  } },
  row("Controller", fields.controller, ""),
  row("Relay amplitude", fields.amp, "MV"),
  row("Hysteresis", fields.hysteresis, "PV"),
  row("Phase lag", fields.phase, "°", "90–170"),
  row("Ms", fields.ms, "", "1.05–4"),
  row("Write gains", fields.apply, ""),
  h("div", { class: "buttons" }, button));
  obj.node = node;
  obj.setEnabled = (on, why) => {
    button.disabled = !on;
    button.title = why || "start the relay experiment";
    for (const f of Object.values(fields)) f.disabled = !canOperate();
  };
  obj.setDefaults = (loop) => {
    const d = loop.defaults;
    const u = unitsOf(loop);
    $("[data-unit=amp]", node).textContent = u.mv || "MV";
    $("[data-unit=hysteresis]", node).textContent = u.pv || "PV";
    fields.controller.value = d.controller;
    fields.amp.value = d.amp;
    fields.hysteresis.value = d.hysteresis ?? "";
    fields.phase.value = d.phase;
    fields.ms.value = d.ms;
    fields.apply.value = d.apply ? "true" : "false";
  };
  return obj;
}

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
async function renderResult(box, session, { title, pending = false, units = NO_UNITS, restore = null }) {
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
  const oldGains = analysis?.old?.gains ?? session.gains_before ?? session.saved?.gains ?? null;
  const newGains = analysis?.new?.gains ?? r.gains;
  if (analysis) {
    const nq = svgNode("nyquist", "Nyquist plot");
    nq.id = "nyquist";
    const curves = [];
    if (analysis.old?.nyquist) curves.push({ name: "L old", cls: "s-old", re: analysis.old.nyquist.re, im: analysis.old.nyquist.im });
    curves.push({ name: "L new", cls: "s-new", re: analysis.new.nyquist.re, im: analysis.new.nyquist.im });
    const loopPoint = openLoopAt(analysis.new.gains, analysis.point);
    const nqOpts = { point: analysis.point, loopPoint, circle: analysis.ms_circle, curves,
                     circleLabel: `Ms = ${fmt(analysis.ms_target, 3)} circle` };
    const nqBox = h("div", { class: "plot-box nyquist-box" }, nq);
    add(grid, h("div", { class: "panel-box" }, h("h3", {}, "Nyquist: open loop L = C·F"),
      nqBox, h("p", { class: "muted small" }, `model ${analysis.model?.text || analysis.model?.kind || "—"} · Ms old ${analysis.old ? fmt(analysis.old.ms, 3) : "—"}`
        + `, new ${fmt(analysis.new.ms, 3)}${analysis.new.stable === false ? " (unstable!)" : ""}`)));
    fitted(nq, (w) => nyquist(nq, { ...nqOpts, size: Math.min(w, 560) }), 420);
  }
  add(grid, h("div", { class: "panel-box" }, h("h3", {}, "Gains"), gainsTable(oldGains, newGains, units)));
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

// L(jω₀) = C(jω₀)·F(jω₀): the designed controller (standard form, derivative filter N, feedback path) times the
// identified point; null without gains.
function openLoopAt(g, point) {
  if (!g || !point) return null;
  const w = point.omega;
  let cre = 1;
  let cim = g.pti ? -1 / (g.pti * w) : 0;
  if (g.ptd) { // Td·jω / (1 + Td·jω/N)
    const a = g.ptd * w;
    const n = g.pnd || Infinity;
    const den = 1 + (a / n) ** 2;
    cre += (a * a / n) / den;
    cim += a / den;
  }
  cre *= g.pk;
  cim *= g.pk;
  return { re: cre * point.re - cim * point.im, im: cre * point.im + cim * point.re };
}

function gainsTable(oldG, newG, units) {
  const tbody = h("tbody");
  for (const group of ROWS) {
    add(tbody, h("tr", { class: "form-row" }, h("th", { colspan: 4 }, group.form)));
    for (const row of group.rows) {
      add(tbody, h("tr", { "data-gain": row[3] && group.form.startsWith("standard") ? row[3] : null },
        h("th", {}, row[0]), h("td", { class: "num old" }, cell(row, oldG, group.form)),
        h("td", { class: "num new" }, cell(row, newG, group.form)), h("td", { class: "unit" }, derived(row[1], units))));
    }
  }
  return h("table", { class: "gains", id: "gains" },
    h("thead", {}, h("tr", {}, h("th", {}, ""), h("th", { class: "num" }, "old"), h("th", { class: "num" }, "new"), h("th", {}, "unit"))),
    tbody);
}

// -- history of a loop

const HISTORY_REFRESH_MS = 5000;

function historyView(id) {
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

// -- one session in full

// The units of loop `id` from its status; none when the daemon no longer has the loop (an old session's).
async function loopUnits(id) {
  try {
    return unitsOf(await get(`/loops/${esc(id)}`));
  } catch (err) {
    if (err.status === 404) return NO_UNITS;
    throw err;
  }
}

function sessionView(sid) {
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

// ---------------------------------------------------------------- router

let cleanup = () => {};

async function route() {
  cleanup();
  cleanup = () => {};
  fill($("#toasts"));
  const hash = location.hash || "#/";
  if (!getToken()) {
    cleanup = loginView();
    return;
  }
  if (!me.role) {
    try {
      Object.assign(me, await whoami(getToken()));
    } catch (err) {
      if (err.status === 401) return; // onUnauthorized handles it
      notify(err);
    }
    renderWho();
  }
  await loadCodes();
  const parts = hash.slice(2).split("/").map(decodeURIComponent);
  if (parts[0] === "login") cleanup = loginView();
  else if (parts[0] === "loop" && parts[1] && parts[2] === "history") cleanup = historyView(parts[1]);
  else if (parts[0] === "loop" && parts[1]) cleanup = loopView(parts[1]);
  else if (parts[0] === "session" && parts[1]) cleanup = sessionView(parts[1]);
  else cleanup = overviewView();
  document.title = `autotuner · ${parts[1] || "loops"}`;
}

window.addEventListener("hashchange", route);
route();
