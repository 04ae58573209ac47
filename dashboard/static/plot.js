// Time plots drawn as SVG: the x axis is the agents' clock (ms since the epoch, shown in UTC), one
// band per panel sharing it. Our own code; no third-party library.
"use strict";
const Plot = (() => {
  const NS = "http://www.w3.org/2000/svg";
  // Tick steps (ms): the first giving at most about 8 ticks across the span is used.
  const STEPS = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000, 10000, 15000, 30000, 60000,
                 120000, 300000, 600000, 900000, 1800000, 3600000];
  const LEFT = 84, RIGHT = 12, TOP = 6, AXIS = 34, GAP = 8;

  function node(name, attrs, parent, text) {
    const e = document.createElementNS(NS, name);
    for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, String(v));
    if (text !== undefined) e.textContent = text;
    if (parent) parent.appendChild(e);
    return e;
  }

  // "HH:MM:SS" (UTC), with milliseconds when the ticks are closer than a second.
  const timeLabel = (ms, step) => new Date(ms).toISOString().substring(11, step < 1000 ? 23 : 19);

  const fmt = (v) => Math.abs(v) >= 1e5 || (v !== 0 && Math.abs(v) < 1e-2) ? v.toExponential(2) : String(+v.toFixed(2));

  // Per pixel column the first, min, max and last sample: a long recording keeps its peaks.
  function decimate(xs, ys, width) {
    if (xs.length <= 4 * width) return [xs.slice(), ys];  // a copy: callers extend it
    const ox = [], oy = [];
    let col = -1, lo = 0, hi = 0, first = 0, last = 0, x0 = 0;
    const flush = () => { ox.push(x0, x0, x0, x0); oy.push(first, lo, hi, last); };
    for (let i = 0; i < xs.length; i++) {
      const c = Math.floor(xs[i]);
      if (c !== col) { if (col >= 0) flush(); col = c; x0 = xs[i]; first = lo = hi = last = ys[i]; }
      else { lo = Math.min(lo, ys[i]); hi = Math.max(hi, ys[i]); last = ys[i]; }
    }
    if (col >= 0) flush();
    return [ox, oy];
  }

  function pathOf(xs, ys, hold) {
    let d = "";
    for (let i = 0; i < xs.length; i++) {
      const x = xs[i].toFixed(1), y = ys[i].toFixed(1);
      // hold: a status holds its value until the next publication (sample and hold)
      d += i === 0 ? "M" + x + " " + y : hold ? "H" + x + "V" + y : "L" + x + " " + y;
    }
    return d;
  }

  // draw(svg, t, panels, opts): t are agent times (ms since the epoch), one per sample; a panel is
  // {name, series: [{name, values, colour}]} or {name, runs: [[first index, label, colour class]]}.
  // opts: {hold: bool (status samples: step lines), marker: ms (a red line), t1: ms (right end)}.
  // The element gets .plotted = {t0, t1, left, width, ts, xs} (the first series' samples) for tests.
  function draw(svg, t, panels, opts = {}) {
    const W = svg.clientWidth || +svg.getAttribute("width") || 1000;
    const H = svg.clientHeight || +svg.getAttribute("height") || 330;
    svg.replaceChildren();
    svg.setAttribute("viewBox", "0 0 " + W + " " + H);
    const width = W - LEFT - RIGHT;
    svg.dataset.samples = String(t.length);
    if (!t.length) { node("text", { x: LEFT, y: 20, class: "empty" }, svg, "no samples yet"); svg.plotted = null; return; }
    const t0 = t[0], t1 = Math.max(opts.t1 === undefined ? t[t.length - 1] : opts.t1, t0 + 1);
    const x = (v) => LEFT + (v - t0) / (t1 - t0) * width;
    const xs = t.map(x);
    const band = (H - TOP - AXIS - GAP * (panels.length - 1)) / panels.length;
    panels.forEach((p, k) => {
      const top = TOP + k * (band + GAP);
      const g = node("g", { class: "panel", "data-name": p.name }, svg);
      node("rect", { x: LEFT, y: top, width: width, height: band, class: "frame" }, g);
      node("text", { x: 4, y: top + 12, class: "name" }, g, p.name);
      if (p.runs) {
        p.runs.forEach(([i, label, cls], r) => {
          const end = r + 1 < p.runs.length ? xs[p.runs[r + 1][0]] : LEFT + width;
          node("rect", { x: xs[i], y: top, width: Math.max(end - xs[i], 0.5), height: band,
                         class: "run" + (cls ? " d-" + cls : ""), "data-label": label }, g)
            .appendChild(node("title", {}, null, label));
          if (end - xs[i] > 60) node("text", { x: xs[i] + 3, y: top + band / 2 + 4, class: "run-label" }, g, label);
        });
        return;
      }
      const all = p.series.flatMap((s) => s.values.filter((v) => v !== null && v !== undefined));
      let lo = Math.min(...all), hi = Math.max(...all);
      if (!isFinite(lo)) { lo = -1; hi = 1; }
      if (hi === lo) { hi += 1; lo -= 1; }
      const y = (v) => top + band - (v - lo) / (hi - lo) * band;
      node("text", { x: 4, y: top + 26, class: "lim" }, g, fmt(hi));
      node("text", { x: 4, y: top + band - 2, class: "lim" }, g, fmt(lo));
      p.series.forEach((s, j) => {
        const [dx, dy] = decimate(xs, s.values.map(y), width);
        if (opts.hold && dx.length) { dx.push(LEFT + width); dy.push(dy[dy.length - 1]); }
        node("path", { d: pathOf(dx, dy, opts.hold), stroke: s.colour, class: "line", "data-name": s.name }, g);
        if (p.series.length > 1) node("text", { x: LEFT + 6 + 110 * j, y: top + 12, style: "fill: " + s.colour, class: "key" }, g, s.name);
      });
    });
    // the time axis: the agents' clock, UTC
    const axisY = H - AXIS + 4;
    const step = STEPS.find((s) => (t1 - t0) / s <= 8) || STEPS[STEPS.length - 1];
    const ax = node("g", { class: "axis" }, svg);
    node("line", { x1: LEFT, x2: LEFT + width, y1: axisY, y2: axisY }, ax);
    for (let v = Math.ceil(t0 / step) * step; v <= t1; v += step) {
      node("line", { x1: x(v), x2: x(v), y1: TOP, y2: axisY + 4, class: "grid" }, ax);
      node("text", { x: x(v), y: axisY + 16, class: "tick", "data-ms": v }, ax, timeLabel(v, step));
    }
    node("text", { x: 4, y: axisY + 16, class: "axis-title" }, ax, "agent time (UTC)");
    if (opts.marker !== undefined) {
      node("line", { x1: x(opts.marker), x2: x(opts.marker), y1: 0, y2: axisY, class: "marker" }, svg);
    }
    svg.plotted = { t0: t0, t1: t1, left: LEFT, width: width, ts: t.slice(), xs: xs };
  }

  return { draw, timeLabel };
})();
