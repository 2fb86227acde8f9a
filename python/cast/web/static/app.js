// The page: one live stream (server-sent events) feeds three views; the hash (#architecture, #memories, #tasks)
// says which one shows.

import { renderArchitecture } from "./arch.js";
import { lineChart } from "./charts.js";
import { Memories } from "./memories.js";
import { renderTasks } from "./tasks.js";
import { duration, rate } from "./util.js";

const VIEWS = ["architecture", "memories", "tasks"];
let state = null;

function banner(text) {
  const node = document.getElementById("banner");
  node.textContent = text || "";
  node.hidden = !text;
}

/** GET a JSON path of the API; null (and a banner) when signed out; the error body too if asked. */
async function api(path, withErrors = false) {
  let response;
  try {
    response = await fetch(path, { credentials: "same-origin", cache: "no-store" });
  } catch {
    return null;
  }
  if (response.status === 401 || response.status === 403) {
    banner("Not signed in (the view was restarted?): open the newest login link `cast web` printed.");
    return null;
  }
  if (!response.ok && !withErrors) return null;
  return response.json();
}

const memories = new Memories(api);

function status(kind, text) {
  document.getElementById("status-dot").className = `dot ${kind}`;
  document.getElementById("status-text").textContent = text;
}

function renderRates(s) {
  const colours = ["#2563eb", "#16a34a", "#d97706", "#7c3aed", "#dc2626", "#0891b2", "#4b5563"];
  const charts = s.subarchitectures.map((sa, i) => lineChart({
    title: `${sa.name}: events/s`, testid: `events-${sa.name}`, format: rate,
    series: [{ name: sa.name, color: colours[i % colours.length], points: s.rates.events_per_s[sa.name] || [] }],
  }));
  const latency = s.rates.latency;
  charts.push(lineChart({
    title: "write → event latency", testid: "latency", format: duration,
    series: [{ name: "p50", color: "#0891b2", points: latency.map((p) => [p.t, p.p50_s]) },
             { name: "p90", color: "#7c3aed", points: latency.map((p) => [p.t, p.p90_s]) }],
  }));
  document.getElementById("rates").replaceChildren(...charts);
}

function render() {
  if (!state) return;
  document.getElementById("system-name").textContent = `system '${state.system}'`;
  document.getElementById("system-where").textContent =
    `${state.subarchitectures.length} SAs · ${state.components.length} components · ${state.endpoint}`;
  if (state.error) status("bad", `cannot read the system: ${state.error}`);
  else if (!state.connected) status("wait", "reconnecting to the servers");
  else status("ok", "live");
  banner(state.metrics_enabled ? "" : "A server counts nothing (cast serve --no-metrics): traffic and rates stay at 0.");
  memories.update(state);
  const view = currentView();
  if (view === "architecture") {
    renderArchitecture(document.getElementById("arch"), state);
    renderRates(state);
  } else if (view === "tasks") {
    renderTasks(state);
  }
}

function currentView() {
  const name = location.hash.slice(1);
  return VIEWS.includes(name) ? name : "architecture";
}

function showView() {
  const view = currentView();
  for (const name of VIEWS) {
    document.getElementById(`view-${name}`).classList.toggle("active", name === view);
    document.querySelector(`nav a[data-view="${name}"]`).classList.toggle("active", name === view);
  }
  memories.show(view === "memories");
  render();
}

function connect() {
  const events = new EventSource("/api/events");
  events.addEventListener("state", (e) => {
    state = JSON.parse(e.data);
    document.body.dataset.stateTime = String(state.time);
    render();
  });
  events.addEventListener("changes", (e) => memories.changed(JSON.parse(e.data)));
  events.addEventListener("error", async () => {
    status("wait", "reconnecting to the web view");
    if (events.readyState === EventSource.CLOSED) {
      // A refused stream is not retried by the browser: find out why, and try again later.
      await api("/api/state");
      setTimeout(connect, 3000);
    }
  });
}

window.addEventListener("hashchange", showView);
window.addEventListener("resize", () => { if (currentView() === "architecture") render(); });
showView();
connect();
