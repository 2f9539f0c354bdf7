// Messages to the operator: an error in words next to what caused it (or as a toast), and banners (a lost stream).

import { ApiError } from "./api.js";
import { $, fill, h } from "./dom.js";

export function notify(error, where = null) {
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

export function banner(id, text) {
  const box = $("#banners");
  let node = box.querySelector(`[data-banner="${id}"]`);
  if (!text) { node?.remove(); return; }
  if (!node) { node = h("div", { class: "banner", "data-banner": id, role: "status" }); box.appendChild(node); }
  node.textContent = text;
}
