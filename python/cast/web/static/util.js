// Small helpers shared by the views: building elements, formatting numbers and times.

/** An element with attributes (class, data-*, title, ...) and children (strings or nodes). */
export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (value === undefined || value === null || value === false) continue;
    if (key === "class") node.className = value;
    else if (key === "style") node.style.cssText = value; // CSSOM: allowed by the page's CSP, a style attribute is not
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else node.setAttribute(key, value === true ? "" : String(value));
  }
  for (const child of children.flat(Infinity)) {
    if (child === undefined || child === null || child === false) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}

/** An SVG element with attributes. */
export function svg(tag, attrs = {}, ...children) {
  const node = document.createElementNS("http://www.w3.org/2000/svg", tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (value !== undefined && value !== null) node.setAttribute(key, String(value));
  }
  for (const child of children) node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  return node;
}

/** A rate with two significant digits at most (0.42, 3.1, 27, 1.2k). */
export function rate(x) {
  if (!x) return "0";
  if (x >= 1000) return `${(x / 1000).toFixed(1)}k`;
  if (x >= 10) return x.toFixed(0);
  if (x >= 1) return x.toFixed(1);
  return x.toFixed(2);
}

/** Seconds as milliseconds or seconds, for people (0.8 ms, 12 ms, 1.4 s). */
export function duration(s) {
  if (s === null || s === undefined) return "–";
  if (s < 0.001) return `${(s * 1000).toFixed(2)} ms`;
  if (s < 1) return `${(s * 1000).toFixed(s < 0.01 ? 1 : 0)} ms`;
  return `${s.toFixed(1)} s`;
}

/** A wall-clock time (seconds since the epoch) as HH:MM:SS.mmm. */
export function clock(t) {
  if (!t) return "";
  const d = new Date(t * 1000);
  const two = (n) => String(n).padStart(2, "0");
  return `${two(d.getHours())}:${two(d.getMinutes())}:${two(d.getSeconds())}.${String(d.getMilliseconds()).padStart(3, "0")}`;
}

/** How long ago a time was, short (4 s ago, 3 min ago). */
export function ago(t, now) {
  if (!t) return "";
  const s = Math.max(0, now - t);
  if (s < 60) return `${s.toFixed(0)} s ago`;
  if (s < 3600) return `${(s / 60).toFixed(0)} min ago`;
  return `${(s / 3600).toFixed(1)} h ago`;
}

/** The last part of a full message name (castdemo.SceneObject -> SceneObject). */
export function shortType(type) {
  return type.includes(".") ? type.slice(type.lastIndexOf(".") + 1) : type;
}

/** A language's badge text. */
export function langName(lang) {
  return { python: "Python", cpp: "C++", java: "Java", ros: "ROS bridge" }[lang] || lang || "?";
}

/** Bytes for people. */
export function size(n) {
  for (const [unit, scale] of [["GiB", 1 << 30], ["MiB", 1 << 20], ["KiB", 1 << 10]]) {
    if (n >= scale) return `${(n / scale).toFixed(1)} ${unit}`;
  }
  return `${n} B`;
}
