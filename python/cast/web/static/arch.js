// The architecture view: SAs as boxes with their components, arrows between SAs weighted by the live traffic.

import { el, langName, rate, svg } from "./util.js";

const STATE_CLASS = { running: "ok", started: "wait", starting: "wait", stopping: "wait", disconnected: "bad" };

// A bridge's mappings (docs/ros.md): which way, the topic, how many a second, and what went wrong last.
function mappingRow(m) {
  const way = m.direction === "to_wm" ? "ROS → WM" : "WM → ROS";
  const errors = m.errors ? ` · ${m.errors} errors` : "";
  const dropped = m.dropped ? ` · ${m.dropped} dropped` : "";
  return el("div", { class: `mapping ${m.errors ? "bad" : ""}`, "data-mapping": m.topic,
                     title: m.last_error ? `last error: ${m.last_error}` : `${m.ros_type} ↔ ${m.entry_type}` },
    `${way} ${m.topic} → ${m.subarchitecture}: ${rate(m.rate_hz)}/s · ${m.delivered}${dropped}${errors}`);
}

function componentRow(c) {
  const restarts = c.restarts > 0 ? `↻ ${c.restarts}` : "";
  const where = [c.kind, c.host ? `on ${c.host}` : "", c.pid ? `pid ${c.pid}` : "", c.privileged ? "privileged" : ""]
    .filter(Boolean).join(" · ");
  return el("div", { class: "comp", "data-component": c.id, title: `${c.id}: ${c.state}` },
    el("span", { class: `dot ${STATE_CLASS[c.state] || ""}` }),
    el("span", { class: "id" }, c.id),
    el("span", { class: `lang ${c.language}` }, langName(c.language)),
    el("span", { class: `restarts ${c.restarts > 0 ? "some" : ""}`, title: "restarts" }, restarts),
    el("span", { class: "sub" }, `${c.state}${where ? " · " + where : ""}`),
    ...(c.mappings || []).map(mappingRow));
}

function saBox(sa, components) {
  const mine = components.filter((c) => c.subarchitecture === sa.name);
  const within = sa.within || {};
  const inside = within.writes_per_s || within.reads_per_s
    ? `inside: ${rate(within.writes_per_s)} w/s · ${rate(within.reads_per_s)} r/s` : "";
  return el("div", { class: "sa", "data-sa": sa.name },
    el("div", { class: "sa-head" }, el("span", { class: "sa-name" }, sa.name)),
    el("div", { class: "sa-stats" }, el("b", {}, sa.entries), " entries · rev ", el("b", {}, sa.revision), " · ",
       el("b", { "data-rate": sa.name }, rate(sa.events_per_s)), " ev/s",
       sa.policy ? el("div", { title: "the task manager's policy" }, `task manager: ${sa.policy}`) : null),
    mine.length ? mine.map(componentRow) : el("div", { class: "comp" }, el("span"), el("span", { class: "sub" }, "no components")),
    inside ? el("div", { class: "sa-within" }, inside) : null);
}

function label(t) {
  const parts = [];
  if (t.writes_per_s) parts.push(`${rate(t.writes_per_s)} w/s`);
  if (t.reads_per_s) parts.push(`${rate(t.reads_per_s)} r/s`);
  if (t.events_per_s) parts.push(`${rate(t.events_per_s)} ev/s`);
  return parts.join(" · ");
}

/** Draw the arrows on top of the laid-out boxes: left to right as arcs above, right to left below. */
function drawArrows(container, traffic) {
  container.querySelector("svg.arrows")?.remove();
  const box = container.getBoundingClientRect();
  const layer = svg("svg", { class: "arrows", width: container.scrollWidth, height: container.scrollHeight });
  const defs = svg("defs");
  for (const [id, colour] of [["head", "#2563eb"], ["head-idle", "#9ca3af"]]) {
    defs.append(svg("marker", { id, viewBox: "0 0 10 10", refX: 9, refY: 5, markerWidth: 7, markerHeight: 7,
                                orient: "auto-start-reverse", markerUnits: "userSpaceOnUse" },
                    svg("path", { d: "M0,0 L10,5 L0,10 z", fill: colour })));
  }
  layer.append(defs);
  const rects = {};
  for (const node of container.querySelectorAll(".sa")) {
    const r = node.getBoundingClientRect();
    rects[node.dataset.sa] = { x: r.left - box.left, y: r.top - box.top, w: r.width, h: r.height };
  }
  const order = Object.keys(rects);
  for (const t of traffic) {
    const a = rects[t.from], b = rects[t.to];
    if (!a || !b) continue;
    const total = t.writes_per_s + t.reads_per_s + t.events_per_s;
    const forward = order.indexOf(t.from) < order.indexOf(t.to);
    const hops = Math.abs(order.indexOf(t.to) - order.indexOf(t.from));
    // Two arrows between the same boxes leave from different points, so they never lie on top of each other.
    const ax = a.x + a.w * (forward ? 0.62 : 0.38), bx = b.x + b.w * (forward ? 0.38 : 0.62);
    const ay = forward ? a.y : a.y + a.h, by = forward ? b.y : b.y + b.h;
    const lift = 34 + 22 * hops;
    const cy = forward ? Math.min(ay, by) - lift * 2 : Math.max(ay, by) + lift * 2;
    const mid = { x: (ax + bx) / 2, y: forward ? Math.min(ay, by) - lift : Math.max(ay, by) + lift };
    const idle = total <= 0;
    const width = idle ? 1.2 : Math.min(9, 1.5 + 2.2 * Math.log10(1 + total));
    const group = svg("g", { "data-arrow": `${t.from}->${t.to}` });
    group.append(svg("path", {
      d: `M${ax},${ay} Q${mid.x},${cy} ${bx},${by}`, fill: "none", stroke: idle ? "#9ca3af" : "#2563eb",
      "stroke-width": width, "stroke-dasharray": idle ? "5 4" : null, "marker-end": `url(#${idle ? "head-idle" : "head"})`,
      opacity: idle ? 0.8 : 0.85,
    }));
    const text = idle ? `idle (${t.writes} w, ${t.reads} r in all)` : label(t);
    group.append(svg("text", { x: mid.x, y: mid.y + (forward ? -6 : 14), "text-anchor": "middle",
                               class: `arrow-label ${idle ? "idle" : ""}` }, `${t.from} → ${t.to}: ${text}`));
    layer.append(group);
  }
  container.prepend(layer);
}

/** Render the whole architecture view from the state. */
export function renderArchitecture(container, state) {
  // Room above the boxes for arrows going right, below for arrows going left, as far as the longest needs.
  const order = state.subarchitectures.map((sa) => sa.name);
  const reach = (forward) => Math.max(0, ...state.traffic
    .filter((t) => (order.indexOf(t.from) < order.indexOf(t.to)) === forward)
    .map((t) => 34 + 22 * Math.abs(order.indexOf(t.to) - order.indexOf(t.from)) + 24));
  container.style.paddingTop = `${Math.max(16, reach(true))}px`;
  container.style.paddingBottom = `${Math.max(16, reach(false))}px`;
  container.replaceChildren(...state.subarchitectures.map((sa) => saBox(sa, state.components)));
  const orphans = state.components.filter((c) => !state.subarchitectures.some((sa) => sa.name === c.subarchitecture));
  if (orphans.length) {
    container.append(saBox({ name: "(no SA)", entries: 0, revision: 0, events_per_s: 0, policy: "" }, orphans
      .map((c) => ({ ...c, subarchitecture: "(no SA)" }))));
  }
  drawArrows(container, state.traffic);
}
