// Table cells that can hold their height: while the pointer is over the overview's table no row may change height,
// or the row under the pointer moves (a click aimed at one loop lands on another). A cell's contents are in a box of
// their own (`.cell`); held, the box keeps the height of its cell's content area, and what grows beyond is clipped
// (style.css, `.held`) until released. In an automatic table layout a row's new contents change every column's
// width, and so the height of rows whose contents did not change: holding the rows that changed is not enough.

import { h } from "./dom.js";

// A cell (`tag` td or th) with its contents in a box that can be held.
export const boxed = (tag, attrs, ...children) => h(tag, attrs, h("div", { class: "cell" }, ...children));

// The box of a boxed cell.
export const boxOf = (cell) => cell.firstChild;

// Whether two boxes hold equal contents (their own held heights aside).
export const sameContents = (a, b) => a.childNodes.length === b.childNodes.length
  && [...a.childNodes].every((n, i) => n.isEqualNode(b.childNodes[i]));

// Every box in the rows of `root` (a table, or one row) held at its height to the bottom of its cell's content
// area now; cells not laid out (hidden) are left as they are. All is measured before anything is set.
export function hold(root) {
  const rows = root.matches("tr") ? [root] : [...root.querySelectorAll("tr")];
  for (const [box, px] of rows.flatMap(heldHeights)) box.style.height = `${px}px`;
}

export function release(root) {
  for (const box of root.querySelectorAll(".cell")) box.style.height = "";
}

// A row's boxes with the heights to hold them at (CSS px). The space below a cell's content area (its padding and
// its share of a border, which differs between border models) is where the row's tallest box ends above its cell.
// Rectangles are in the viewport's pixels, a zoomed page's (the 4K HMI's) not CSS px; layout rounds lengths to
// 1/64 px, so the length set is 1/128 px over the measure, or the row would lose 1/64 px a cell.
function heldHeights(tr) {
  const cells = [...tr.cells].filter((cell) => cell.getClientRects().length);
  const rects = cells.map((cell) => ({ box: boxOf(cell).getBoundingClientRect(), cell: cell.getBoundingClientRect() }));
  const below = Math.min(...rects.map((r) => r.cell.bottom - r.box.bottom));
  return cells.map((cell, i) => {
    const box = boxOf(cell);
    const room = rects[i].cell.bottom - below - rects[i].box.top;
    return [box, (room + 1 / 128) / (box.currentCSSZoom ?? 1)];
  });
}
