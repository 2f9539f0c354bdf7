// Building the page's DOM: elements from a tag, attributes and children (nulls skipped), and small helpers.

import { el } from "./plot.js";

export function h(tag, attrs = {}, ...children) {
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

export const svgNode = (cls, label) => el("svg", { class: cls, role: "img", "aria-label": label });

// append / replaceChildren without the nulls of conditional children (the DOM would print "null").
const clean = (children) => children.flat(Infinity).filter((c) => c !== null && c !== undefined && c !== false);
export const add = (node, ...children) => node.append(...clean(children));
export const fill = (node, ...children) => node.replaceChildren(...clean(children));

export const $ = (sel, root = document) => root.querySelector(sel);
export const main = () => $("#main");
export const esc = (s) => encodeURIComponent(s);
