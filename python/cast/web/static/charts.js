// Small line charts in SVG: the last minute of a few series, with the newest value in the corner.

import { el, svg } from "./util.js";

const W = 280, H = 76, PAD_L = 4, PAD_R = 4, PAD_T = 6, PAD_B = 14, SPAN = 60;

/**
 * A chart card: title, newest value, and lines for each series ({name, color, points: [[t, y|null]...]})
 * with t in seconds before now (-60..0). format(y) renders values for the corner and the scale.
 */
export function lineChart({ title, series, format, testid }) {
  const values = series.flatMap((s) => s.points.map((p) => p[1]).filter((y) => y !== null));
  const top = Math.max(...values, 0) * 1.15 || 1;
  const x = (t) => PAD_L + ((t + SPAN) / SPAN) * (W - PAD_L - PAD_R);
  const y = (v) => PAD_T + (1 - v / top) * (H - PAD_T - PAD_B);
  const chart = svg("svg", { viewBox: `0 0 ${W} ${H}`, preserveAspectRatio: "none" });
  chart.append(svg("line", { x1: PAD_L, x2: W - PAD_R, y1: y(0), y2: y(0), stroke: "#dde1e7" }));
  chart.append(svg("line", { x1: PAD_L, x2: W - PAD_R, y1: y(top / 1.15), y2: y(top / 1.15), stroke: "#eef0f3",
                             "stroke-dasharray": "3 3" }));
  chart.append(svg("text", { x: PAD_L, y: H - 2, class: "axis" }, "−60 s"));
  chart.append(svg("text", { x: W - PAD_R, y: H - 2, class: "axis", "text-anchor": "end" }, "now"));
  chart.append(svg("text", { x: W - PAD_R, y: y(top / 1.15) - 2, class: "axis", "text-anchor": "end" },
                   values.length ? format(top / 1.15) : ""));
  for (const s of series) {
    // A null value breaks the line (nothing was measured in that interval).
    let path = "", pen = "M";
    const shown = s.points.filter(([t]) => t >= -SPAN);
    shown.forEach(([t, v], i) => {
      if (v === null) { pen = "M"; return; }
      path += `${pen}${x(t).toFixed(1)},${y(v).toFixed(1)} `;
      pen = "L";
      // A value with no neighbour to join (the intervals around it measured nothing) is a dot.
      const alone = (i === 0 || shown[i - 1][1] === null) && (i === shown.length - 1 || shown[i + 1][1] === null);
      if (alone) chart.append(svg("circle", { cx: x(t).toFixed(1), cy: y(v).toFixed(1), r: 2, fill: s.color }));
    });
    if (path) chart.append(svg("path", { d: path, fill: "none", stroke: s.color, "stroke-width": 1.8,
                                        "vector-effect": "non-scaling-stroke" }));
  }
  const newest = series.map((s) => [...s.points].reverse().find((p) => p[1] !== null)).map((p) => (p ? p[1] : null));
  const now = newest[newest.length - 1];
  const key = series.length > 1
    ? el("div", { class: "series-key" }, series.map((s) => [el("i", { style: `background:${s.color}` }), s.name]))
    : null;
  return el("div", { class: "chart", "data-chart": testid },
    el("div", { class: "chart-head" }, el("span", {}, title),
       el("span", { class: "now" }, now === null || now === undefined ? "–" : format(now))),
    chart, key);
}
