// Hand-written SVG plots (no library): stacked time charts sharing an x axis, and a Nyquist plot.
// Styling is in style.css through the classes given to the series (s-pv, s-sp, s-mv, ...).

const NS = "http://www.w3.org/2000/svg";

export function el(tag, attrs = {}, parent = null, text = null) {
  const node = document.createElementNS(NS, tag);
  for (const [k, v] of Object.entries(attrs)) if (v !== undefined && v !== null) node.setAttribute(k, v);
  if (text !== null) node.textContent = text;
  if (parent) parent.appendChild(node);
  return node;
}

function clear(svg) { while (svg.firstChild) svg.removeChild(svg.firstChild); }

// Round tick values covering [min, max], about `count` of them.
export function ticks(min, max, count = 5) {
  if (!(max > min)) return [min];
  const raw = (max - min) / count;
  const mag = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 2.5, 5, 10].map((m) => m * mag).find((s) => s >= raw) || raw;
  const out = [];
  for (let v = Math.ceil(min / step) * step; v <= max + step * 1e-9; v += step) out.push(Math.abs(v) < step * 1e-9 ? 0 : v);
  return out;
}

// Ticks of a clock axis (unix seconds): whole seconds, minutes or hours, about `count` of them.
export function clockTicks(min, max, count = 5) {
  const raw = (max - min) / Math.max(1, count);
  const step = [1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200, 21600].find((s) => s >= raw) || 43200;
  const out = [];
  for (let v = Math.ceil(min / step) * step; v <= max; v += step) out.push(v);
  return out;
}

// At least three labelled ticks (a short panel still shows its scale), else `ticks` as asked.
function enoughTicks(min, max, count) {
  let out = ticks(min, max, count);
  for (let c = count * 2; out.length < 3 && c <= count * 8; c *= 2) out = ticks(min, max, c);
  return out;
}

function label(v) {
  const a = Math.abs(v);
  const s = a !== 0 && (a >= 1e5 || a < 1e-3) ? v.toExponential(1) : Number(v.toPrecision(4)).toString();
  return s.replace("-", "−");
}

function extent(series, key, fallback) {
  let lo = Infinity;
  let hi = -Infinity;
  for (const s of series) {
    for (const v of s[key]) {
      if (v === null || !Number.isFinite(v)) continue;
      if (v < lo) lo = v;
      if (v > hi) hi = v;
    }
  }
  if (!Number.isFinite(lo)) return fallback;
  if (hi - lo < 1e-9) { const d = Math.max(Math.abs(hi) * 0.05, 0.5); return [lo - d, hi + d]; }
  const pad = (hi - lo) * 0.08;
  return [lo - pad, hi + pad];
}

// The data's extent (null: no data) and a display range together; [0, 1] with neither.
function covering(data, range) {
  if (!range) return data || [0, 1];
  if (!data) return [range[0], range[1]];
  return [Math.min(range[0], data[0]), Math.max(range[1], data[1])];
}

// At most ~4 points per pixel column (first, min, max, last), in time order.
function decimate(xs, ys, x0, x1, columns) {
  const n = xs.length;
  if (n <= columns * 4) return xs.map((x, i) => [x, ys[i]]);
  const out = [];
  const w = (x1 - x0) / columns;
  let col = null;
  let bucket = [];
  const flush = () => {
    if (!bucket.length) return;
    let lo = bucket[0];
    let hi = bucket[0];
    for (const p of bucket) { if (p[1] < lo[1]) lo = p; if (p[1] > hi[1]) hi = p; }
    const pts = [bucket[0], lo, hi, bucket[bucket.length - 1]].sort((a, b) => a[0] - b[0]);
    let last = null;
    for (const p of pts) if (p !== last) { out.push(p); last = p; }
    bucket = [];
  };
  for (let i = 0; i < n; i++) {
    const c = Math.floor((xs[i] - x0) / w);
    if (c !== col) { flush(); col = c; }
    bucket.push([xs[i], ys[i]]);
  }
  flush();
  return out;
}

function pathOf(points, sx, sy, step) {
  let d = "";
  let pen = false;
  let prevY = null;
  for (const [x, y] of points) {
    if (y === null || !Number.isFinite(y)) { pen = false; continue; }
    const px = sx(x).toFixed(1);
    const py = sy(y).toFixed(1);
    if (!pen) d += `M${px},${py}`;
    else if (step) d += `H${px}V${py}`;
    else d += `L${px},${py}`;
    pen = true;
    prevY = py;
  }
  return prevY === null ? "" : d;
}

// Stacked panels sharing the x axis.
// opts: {width, xRange:[a,b]?, xLabel, xTick(v)→text,
//        panels:[{height, label, yRange?, yAtLeast?, series:[{name, cls, x:[], y:[], step?}],
//                 marks?:{name (none: not in the legend), cls, x:[]}}]}
// marks draws a short tick at each of its x on the panel's top and bottom edges and a faint line between (events
// such as the zero crossings of the control error), with its name in the legend. yRange fixes a panel's y axis; yAtLeast ([low, high], a loop's configured display range) is covered whatever the
// data, and widened to data outside it (a value is never drawn off the panel).
export function timeChart(svg, opts) {
  clear(svg);
  const width = opts.width || 800;
  const left = 56;
  const right = 12;
  const top = 8;
  const gap = 10;
  const bottom = 34;
  const panels = opts.panels;
  const headH = 16; // a row above each panel: its label (left) and legend (right)
  const total = top + panels.reduce((a, p) => a + headH + p.height + gap, 0) - gap + bottom;
  svg.setAttribute("viewBox", `0 0 ${width} ${total}`);
  svg.setAttribute("preserveAspectRatio", "xMidYMid meet");
  const all = panels.flatMap((p) => p.series);
  const [x0, x1] = opts.xRange || extent(all.map((s) => ({ x: s.x })), "x", [0, 1]);
  const plotW = width - left - right;
  const sx = (x) => left + ((x - x0) / (x1 - x0 || 1)) * plotW;
  const xt = opts.xTicks ? opts.xTicks(x0, x1, Math.max(2, Math.round(plotW / 110)))
    : ticks(x0, x1, Math.max(2, Math.round(plotW / 90)));
  let y = top;
  const clipId = `clip${Math.random().toString(36).slice(2, 8)}`;
  panels.forEach((panel, index) => {
    const h = panel.height;
    y += headH;
    const [y0, y1] = panel.yRange || covering(extent(panel.series, "y", null), panel.yAtLeast);
    const sy = (v) => y + h - ((v - y0) / (y1 - y0 || 1)) * h;
    const g = el("g", { class: "panel", "data-panel": panel.label }, svg);
    el("rect", { class: "plot-bg", x: left, y, width: plotW, height: h }, g);
    const cid = `${clipId}-${index}`;
    el("rect", { x: left, y, width: plotW, height: h }, el("clipPath", { id: cid }, g));
    for (const v of panel.yTicks || enoughTicks(y0, y1, Math.max(2, Math.round(h / 40)))) {
      el("line", { class: "grid", x1: left, x2: left + plotW, y1: sy(v), y2: sy(v) }, g);
      el("text", { class: "tick", x: left - 6, y: sy(v) + 4, "text-anchor": "end" }, g, label(v));
    }
    for (const v of xt) el("line", { class: "grid", x1: sx(v), x2: sx(v), y1: y, y2: y + h }, g);
    el("text", { class: "axis-label", x: left, y: y - 4 }, g, panel.label);
    const lines = el("g", { "clip-path": `url(#${cid})` }, g);
    if (panel.marks) {
      const m = panel.marks;
      const marks = el("g", { class: `marks ${m.cls}`, "data-marks": m.cls, "data-count": m.x.length }, lines);
      const sparse = m.x.length <= plotW / 8; // lines across the panel only where they leave the data visible
      for (const x of m.x) {
        const px = sx(x);
        if (sparse) el("line", { class: "mark-line", x1: px, x2: px, y1: y, y2: y + h }, marks);
        el("path", { class: "mark-tick", d: `M${px - 4},${y}h8l-4,6zM${px - 4},${y + h}h8l-4,-6z` }, marks);
      }
    }
    for (const s of panel.series) {
      const pts = decimate(s.x, s.y, x0, x1, plotW);
      const d = pathOf(pts, sx, sy, s.step);
      if (d) el("path", { class: `line ${s.cls}`, d, "data-series": s.name, "data-points": pts.length }, lines);
    }
    // Legend, above the panel on the right: a short line of the series' style and its name.
    let lx = left + plotW;
    const legend = panel.marks?.name ? [...panel.series, { name: panel.marks.name, cls: `mark ${panel.marks.cls}` }] : panel.series;
    for (const s of [...legend].reverse()) {
      if (!s.name) continue;
      el("text", { class: `legend ${s.cls}`, x: lx, y: y - 4, "text-anchor": "end" }, g, s.name);
      lx -= 7.6 * s.name.length + 6;
      el("line", { class: `line ${s.cls}`, x1: lx - 18, x2: lx, y1: y - 8, y2: y - 8 }, g);
      lx -= 40;
    }
    y += h + gap;
  });
  const axisY = y - gap;
  for (const v of xt) {
    const text = opts.xTick ? opts.xTick(v) : label(v);
    const half = 3.4 * text.length; // about half the label's width: keep it inside the chart
    const x = Math.min(Math.max(sx(v), left + half), width - right - half);
    el("text", { class: "tick", x, y: axisY + 15, "text-anchor": "middle" }, svg, text);
  }
  if (opts.xLabel) el("text", { class: "axis-label", x: left + plotW, y: axisY + 30, "text-anchor": "end" }, svg, opts.xLabel);
}

// One signal against another (x and y in time order), as points joined by a thin line: the MV–PV figure of a
// sticking valve. opts: {width, height, xLabel, yLabel, x:[], y:[], name, cls}.
export function xyPlot(svg, opts) {
  clear(svg);
  const width = opts.width || 420;
  const height = opts.height || Math.round(width * 0.75);
  const [left, right, top, bottom] = [56, 12, 22, 34];
  svg.setAttribute("viewBox", `0 0 ${width} ${height}`);
  const pts = { x: opts.x, y: opts.y };
  const [x0, x1] = extent([{ v: pts.x }], "v", [0, 1]);
  const [y0, y1] = extent([{ v: pts.y }], "v", [0, 1]);
  const plotW = width - left - right;
  const plotH = height - top - bottom;
  const sx = (v) => left + ((v - x0) / (x1 - x0 || 1)) * plotW;
  const sy = (v) => top + plotH - ((v - y0) / (y1 - y0 || 1)) * plotH;
  el("rect", { class: "plot-bg", x: left, y: top, width: plotW, height: plotH }, svg);
  for (const v of enoughTicks(x0, x1, Math.max(2, Math.round(plotW / 90)))) {
    el("line", { class: "grid", x1: sx(v), x2: sx(v), y1: top, y2: top + plotH }, svg);
    el("text", { class: "tick", x: sx(v), y: top + plotH + 15, "text-anchor": "middle" }, svg, label(v));
  }
  for (const v of enoughTicks(y0, y1, Math.max(2, Math.round(plotH / 40)))) {
    el("line", { class: "grid", x1: left, x2: left + plotW, y1: sy(v), y2: sy(v) }, svg);
    el("text", { class: "tick", x: left - 6, y: sy(v) + 4, "text-anchor": "end" }, svg, label(v));
  }
  el("text", { class: "axis-label", x: left, y: top - 8 }, svg, opts.yLabel);
  el("text", { class: "axis-label", x: left + plotW, y: top + plotH + 30, "text-anchor": "end" }, svg, opts.xLabel);
  const path = pathOf(pts.x.map((x, i) => [x, pts.y[i]]), sx, sy, false);
  if (path) el("path", { class: `line xy ${opts.cls}`, d: path, "data-series": opts.name, "data-points": pts.x.length }, svg);
}

// Nyquist plot of open loops with the identified point, the critical point and the Ms circle.
// opts: {size, point:{re, im}|null, circle:{center_re, radius}|null,
//        curves:[{name, cls, re:[], im:[]}]}
export function nyquist(svg, opts) {
  clear(svg);
  const size = opts.size || 420;
  const pad = 34;
  // Legend below the plot, one item a row: it never covers the curves, the circle or the points.
  const items = [...opts.curves.map((c) => [c.cls, "line", c.name])];
  if (opts.circle) items.push(["ms-circle", "circle", opts.circleLabel || "Ms circle"]);
  if (opts.point) items.push(["point", "dot", "identified point F(jω₀)"]);
  if (opts.loopPoint) items.push(["loop-point", "square", "L(jω₀) = C(jω₀)·F(jω₀), new gains"]);
  const legendH = 10 + 18 * items.length;
  svg.setAttribute("viewBox", `0 0 ${size} ${size + legendH}`);
  // The view: the critical point, the origin, the Ms circle and the point, with room around them.
  let xs = [-1, 0];
  let ys = [0];
  if (opts.circle) {
    const { center_re: c, radius: r } = opts.circle;
    xs.push(c - r, c + r);
    ys.push(-r, r);
  }
  for (const pt of [opts.point, opts.loopPoint]) if (pt) { xs.push(pt.re); ys.push(pt.im); }
  let lo = Math.min(...xs);
  let hi = Math.max(...xs);
  let bottomY = Math.min(...ys);
  let topY = Math.max(...ys);
  const spanRaw = Math.max(hi - lo, topY - bottomY, 1);
  const span = spanRaw * 1.7;
  const cx = (lo + hi) / 2;
  const cy = (bottomY + topY) / 2 - spanRaw * 0.15;
  const [re0, re1, im0, im1] = [cx - span / 2, cx + span / 2, cy - span / 2, cy + span / 2];
  const inner = size - 2 * pad;
  const sx = (v) => pad + ((v - re0) / (re1 - re0)) * inner;
  const sy = (v) => pad + inner - ((v - im0) / (im1 - im0)) * inner;
  el("rect", { class: "plot-bg", x: pad, y: pad, width: inner, height: inner }, svg);
  const clipId = `nq${Math.random().toString(36).slice(2, 8)}`;
  el("rect", { x: pad, y: pad, width: inner, height: inner }, el("clipPath", { id: clipId }, svg));
  const n = Math.max(3, Math.round(inner / 70));
  for (const v of ticks(re0, re1, n)) {
    el("line", { class: v === 0 ? "axis" : "grid", x1: sx(v), x2: sx(v), y1: pad, y2: pad + inner }, svg);
    el("text", { class: "tick", x: sx(v), y: pad + inner + 14, "text-anchor": "middle" }, svg, label(v));
  }
  for (const v of ticks(im0, im1, n)) {
    el("line", { class: v === 0 ? "axis" : "grid", x1: pad, x2: pad + inner, y1: sy(v), y2: sy(v) }, svg);
    el("text", { class: "tick", x: pad - 4, y: sy(v) + 4, "text-anchor": "end" }, svg, label(v));
  }
  el("text", { class: "axis-label", x: pad + inner, y: pad - 8, "text-anchor": "end" }, svg, "Re");
  el("text", { class: "axis-label", x: pad, y: pad - 8 }, svg, "Im");
  const g = el("g", { "clip-path": `url(#${clipId})` }, svg);
  const scale = inner / (re1 - re0);
  if (opts.circle) {
    el("circle", { class: "ms-circle", "data-role": "ms-circle", cx: sx(opts.circle.center_re), cy: sy(0),
                   r: opts.circle.radius * scale }, g);
  }
  for (const c of opts.curves) {
    // A point far outside the window (or not finite) breaks the line, as a missing sample does.
    const pts = c.re.map((r, i) => {
      const far = !Number.isFinite(r) || Math.abs(r) > 1e3 * span || Math.abs(c.im[i]) > 1e3 * span;
      return [r, far ? null : c.im[i]];
    });
    const d = pathOf(pts, sx, sy, false);
    if (d) el("path", { class: `line ${c.cls}`, d, "data-series": c.name }, g);
  }
  // The critical point −1.
  const k = 6;
  el("path", { class: "critical", "data-role": "critical", d: `M${sx(-1) - k},${sy(0)}h${2 * k}M${sx(-1)},${sy(0) - k}v${2 * k}` }, g);
  el("text", { class: "tick", x: sx(-1) + 4, y: sy(0) + 14 }, g, "−1");
  if (opts.point) {
    el("circle", { class: "point", "data-role": "point", cx: sx(opts.point.re), cy: sy(opts.point.im), r: 5 }, g);
    el("text", { class: "point-label", x: sx(opts.point.re) + 8, y: sy(opts.point.im) + 14 }, g, "F(jω₀)");
  }
  if (opts.loopPoint) {
    const [x, y] = [sx(opts.loopPoint.re), sy(opts.loopPoint.im)];
    el("rect", { class: "loop-point", "data-role": "loop-point", x: x - 4.5, y: y - 4.5, width: 9, height: 9 }, g);
    el("text", { class: "loop-point-label", x: x - 8, y: y - 6, "text-anchor": "end" }, g, "L(jω₀)");
  }
  let ly = size + 8;
  for (const [cls, mark, name] of items) {
    const x = pad;
    if (mark === "line") el("line", { class: `line ${cls}`, x1: x, x2: x + 22, y1: ly + 5, y2: ly + 5 }, svg);
    else if (mark === "circle") el("circle", { class: cls, cx: x + 11, cy: ly + 5, r: 6 }, svg);
    else if (mark === "dot") el("circle", { class: cls, cx: x + 11, cy: ly + 5, r: 5 }, svg);
    else el("rect", { class: cls, x: x + 6.5, y: ly + 0.5, width: 9, height: 9 }, svg);
    el("text", { class: "legend-text", x: x + 30, y: ly + 9 }, svg, name);
    ly += 18;
  }
}

// Draw `svg` at its own width in CSS pixels (`draw(width)`), and again whenever that width changes: the plot's
// text stays at its CSS size on a phone and on a 4K screen instead of being scaled with a fixed viewBox.
// The width of `node` in its own CSS pixels (getBoundingClientRect counts the zoom of a 4K screen's style in).
export function cssWidth(node) {
  return Math.round(node.getBoundingClientRect().width / (node.currentCSSZoom || 1));
}

export function fitted(svg, draw, fallback = 800) {
  let drawn = null;
  const run = () => {
    const measured = cssWidth(svg);
    if (!measured && drawn !== null) return; // taken off the page (another view): nothing to redraw
    const w = measured || fallback;
    if (w === drawn) return;
    drawn = w;
    draw(w);
  };
  new ResizeObserver(run).observe(svg);
  run();
  return { redraw() { drawn = null; run(); } };
}
