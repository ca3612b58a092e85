// The charts of the dashboard and the figure view (services/api/pages.py inlines this
// file into both pages): SVG drawn from curves the API or `macb view` computed.
"use strict";
// matplotlib's tab10 and tab20, as services/api/plot.py's TAB10 and TAB20: the pages
// colour an arm as the PNGs do (tests/test_plot_colors.py checks the lists agree).
const TAB10 = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd",
               "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"];
const TAB20 = ["#1f77b4", "#aec7e8", "#ff7f0e", "#ffbb78", "#2ca02c", "#98df8a", "#d62728",
               "#ff9896", "#9467bd", "#c5b0d5", "#8c564b", "#c49c94", "#e377c2", "#f7b6d2",
               "#7f7f7f", "#c7c7c7", "#bcbd22", "#dbdb8d", "#17becf", "#9edae5"];
// Each arm's colour by its place among `names` (plot.py's arm_colors): tab10 up to 10
// arms, tab20 beyond.
function armColors(names) {
  const colors = names.length <= 10 ? TAB10 : TAB20;
  return Object.fromEntries(names.map((n, i) => [n, colors[i % colors.length]]));
}
function el(tag, attrs, ...children) {
  const ns = ["svg", "path", "line", "text", "g", "rect", "polygon", "circle"].includes(tag)
    ? "http://www.w3.org/2000/svg" : null;
  const e = ns ? document.createElementNS(ns, tag) : document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k === "text") e.textContent = v; else e.setAttribute(k, v);
  }
  for (const c of children) if (c) e.appendChild(c);
  return e;
}

function niceMax(v) {
  if (!(v > 0)) return 1;
  const p = Math.pow(10, Math.floor(Math.log10(v)));
  for (const m of [1, 2, 2.5, 5, 10]) if (m * p >= v) return m * p;
  return 10 * p;
}

function fmt(v) {
  if (Math.abs(v) >= 1000) return (v / 1000).toFixed(v >= 10000 ? 0 : 1) + "k";
  return Number.isInteger(v) ? String(v) : v.toFixed(2);
}

// A curve's arm name (`label` from an API older than arms).
const armName = c => c.name ?? c.label;

// One chart: per curve (episode, mean, lo, hi; `n` seeds per point, optional) a band and
// its mean. `opts` (the figure view's): `color(c, i)`, `dashed(c)` (a control arm's
// line), `seeds`: also each seed's line (c.seeds: [{seed, values}]), and `marks`: the
// values the thesis states ({claim, arm, episode, lo, hi, thesis}), each drawn beside its
// arm's curve as the report's plot draws it (a hollow diamond, its bar the accepted range).
function chart(expId, metric, title, fixed, curves, episodes, opts = {}) {
  const W = 360, H = 204, L = 40, R = 10, T = 8, B = 30;
  const svg = el("svg", { viewBox: `0 0 ${W} ${H}`, "data-metric": metric, role: "img",
                          "aria-label": title });
  let xmax = Math.max(1, episodes || 0), ymax = 0, ymin = 0;  // the runs' whole length
  const marks = (opts.marks || []).filter(m => curves.some(c => armName(c) === m.arm));
  for (const m of marks) xmax = Math.max(xmax, m.episode);
  for (const c of curves) {
    for (const e of c.episode) xmax = Math.max(xmax, e);
    for (const v of c.hi) ymax = Math.max(ymax, v);
  }
  if (fixed) { ymin = fixed[0]; ymax = fixed[1]; } else { ymax = niceMax(ymax * 1.05); }
  const x = e => L + (W - L - R) * e / xmax;
  const y = v => T + (H - T - B) * (1 - (Math.min(Math.max(v, ymin), ymax) - ymin) / (ymax - ymin || 1));
  const axes = el("g", { class: "axes" });
  for (let i = 0; i <= 4; i++) {
    const v = ymin + (ymax - ymin) * i / 4;
    axes.appendChild(el("line", { x1: L, x2: W - R, y1: y(v), y2: y(v), stroke: "#eef0f3" }));
    axes.appendChild(el("text", { x: L - 4, y: y(v) + 3, "text-anchor": "end", text: fmt(v) }));
  }
  for (let i = 0; i <= 4; i++) {
    const e = xmax * i / 4;
    axes.appendChild(el("text", { x: x(e), y: H - B + 14, "text-anchor": "middle",
                                  text: fmt(Math.round(e)) }));
  }
  axes.appendChild(el("text", { x: (L + W - R) / 2, y: H - 2, "text-anchor": "middle",
                                text: "training episodes" }));
  axes.appendChild(el("line", { x1: L, x2: L, y1: T, y2: H - B, stroke: "#9ca3af" }));
  axes.appendChild(el("line", { x1: L, x2: W - R, y1: H - B, y2: H - B, stroke: "#9ca3af" }));
  svg.appendChild(axes);
  const own = armColors(curves.map(armName));  // (unless the page colours the arms)
  const colorOf = (c, i) => (opts.color ? opts.color(c, i) : own[armName(c)]);
  curves.forEach((c, i) => {
    if (!c.episode.length) return;
    const color = colorOf(c, i);
    const upper = c.episode.map((e, j) => `${x(e).toFixed(1)},${y(c.hi[j]).toFixed(1)}`);
    const lower = c.episode.map((e, j) => `${x(e).toFixed(1)},${y(c.lo[j]).toFixed(1)}`).reverse();
    svg.appendChild(el("polygon", { class: "curve-band", points: upper.concat(lower).join(" "),
                                    fill: color, "fill-opacity": 0.15, stroke: "none",
                                    "data-label": armName(c) }));
    const line = vs => c.episode.map((e, j) => `${j ? "L" : "M"}${x(e).toFixed(1)},${y(vs[j]).toFixed(1)}`);
    for (const s of (opts.seeds && c.seeds) || []) {
      svg.appendChild(el("path", {
        class: "curve-seed", d: line(s.values).join(" "), fill: "none", stroke: color,
        "stroke-width": 0.7, "stroke-opacity": 0.55, "data-label": armName(c), "data-seed": s.seed,
        "data-values": s.values.map(v => +v.toPrecision(6)).join(","),
      }));
    }
    const d = line(c.mean);
    svg.appendChild(el("path", {
      class: "curve-mean", d: d.join(" "), fill: "none", stroke: color, "stroke-width": 1.8,
      ...(opts.dashed && opts.dashed(c) ? { "stroke-dasharray": "5,3" } : {}),
      "data-experiment": expId, "data-metric": metric, "data-label": armName(c),
      "data-episodes": c.episode.join(","), "data-values": c.mean.map(v => +v.toPrecision(6)).join(","),
      "data-seeds": (c.n || []).join(","),
    }));
    if (c.episode.length === 1) {
      svg.appendChild(el("circle", { cx: x(c.episode[0]), cy: y(c.mean[0]), r: 2.5, fill: color }));
    }
  });
  for (const m of marks) {
    const i = curves.findIndex(c => armName(c) === m.arm);
    const color = colorOf(curves[i], i);
    const cx = x(m.episode), mid = y((m.lo + m.hi) / 2), r = 3.5;
    const g = el("g", { class: "thesis-mark", "data-arm": m.arm, "data-claim": m.claim,
                        "data-episode": m.episode, "data-lo": m.lo, "data-hi": m.hi,
                        "aria-label": `thesis, claim ${m.claim}: ${m.thesis}` });
    g.appendChild(el("line", { x1: cx, x2: cx, y1: y(m.lo), y2: y(m.hi), stroke: color }));
    for (const v of [m.lo, m.hi]) {
      g.appendChild(el("line", { x1: cx - 3, x2: cx + 3, y1: y(v), y2: y(v), stroke: color }));
    }
    g.appendChild(el("polygon", { points: `${cx},${mid - r} ${cx + r},${mid} ${cx},${mid + r} ${cx - r},${mid}`,
                                  fill: "white", stroke: color, "stroke-width": 1.3 }));
    svg.appendChild(g);
  }
  return el("div", { class: "chart" }, el("h3", { text: title }), svg);
}

