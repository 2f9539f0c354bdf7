// Who is logged in (the token's name and role, from GET /whoami) and the header's badge of it.

import { clearToken, getToken } from "./api.js";
import { $, add, fill, h } from "./dom.js";

export const me = { name: null, role: null };
export const canOperate = () => me.role === "operator" || me.role === "admin";

export function renderWho() {
  const box = $("#who");
  fill(box);
  if (!getToken()) return;
  add(box, h("span", { class: `role ${me.role || ""}`, "data-role": me.role || "" }, me.role || "?"),
    me.name ? h("span", { class: "name" }, me.name) : null,
    h("button", { class: "ghost", id: "logout", onclick: logout }, "Log out"));
}

export function logout() {
  forget();
  location.hash = "#/login";
}

// The token is gone (logged out, or refused with a 401): nobody is logged in.
export function forget() {
  clearToken();
  me.name = me.role = null;
  renderWho();
}
