// The operator page: login, loop overview, loop page (live trend, TUNE/TBRK/apply, result), history, session.
// Plain ES modules, no build step; routes in the URL's hash: #/, #/loop/ID, #/loop/ID/history, #/session/SID.
// This module logs in and routes; each view is a module of its own (overview.js, loop-page.js, history.js,
// session-page.js).

import { getToken, onUnauthorized, setToken, whoami } from "./api.js";
import { loadCodes } from "./display.js";
import { $, fill, h, main } from "./dom.js";
import { historyView } from "./history.js";
import { loopView } from "./loop-page.js";
import { notify } from "./notices.js";
import { overviewView } from "./overview.js";
import { sessionView } from "./session-page.js";
import { forget, me, renderWho } from "./who.js";

let loginMessage = null; // why the login shows again (a 401), shown once on it

onUnauthorized((err) => {
  forget();
  loginMessage = err.text;
  if (location.hash !== "#/login") location.hash = "#/login";
  else route();
});

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
