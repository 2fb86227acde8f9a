// The task-manager view: per SA the policy, decision counts, running and waiting tasks, waiting time; the latest
// decisions.

import { clock, duration, el } from "./util.js";

function taskItem(t, now, waiting) {
  const since = waiting ? t.proposed : t.decided || t.proposed;
  const label = waiting ? `waiting ${duration(Math.max(0, now - since))}` : `running ${duration(Math.max(0, now - since))}`;
  return el("li", { "data-task": t.task_id }, el("b", {}, t.name), el("span", {}, `by ${t.component}`),
            t.priority ? el("span", { class: "tag" }, `priority ${t.priority}`) : null, el("span", { class: "muted" }, label));
}

function card(tm, now) {
  const counts = [["proposed", tm.proposed], ["adopted", tm.adopted], ["rejected", tm.rejected],
                  ["retracted", tm.retracted], ["completed", tm.completed]];
  return el("div", { class: "panel tm", "data-tm": tm.subarchitecture },
    el("h3", {}, tm.subarchitecture, " ", el("span", { class: "tag" }, tm.policy)),
    el("div", { class: "counts" }, counts.map(([name, n]) => el("div", { "data-count": name }, el("b", {}, n),
                                                                   el("span", {}, name)))),
    el("div", { class: "wait" }, tm.adopted
      ? `waiting time before adoption: mean ${duration(tm.wait_mean_s)}, p90 ${duration(tm.wait_p90_s)}`
      : "no task adopted yet"),
    el("h4", {}, `running (${tm.running.length})`),
    tm.running.length ? el("ul", {}, tm.running.map((t) => taskItem(t, now, false))) : el("p", { class: "empty" }, "none"),
    el("h4", {}, `waiting (${tm.waiting.length})`),
    tm.waiting.length ? el("ul", {}, tm.waiting.map((t) => taskItem(t, now, true))) : el("p", { class: "empty" }, "none"));
}

function decisionRow(d) {
  const state = d.state === "completed" && d.outcome ? `completed: ${d.outcome}` : d.state;
  return el("tr", { "data-decision": `${d.subarchitecture}/${d.name}/${d.state}` },
    el("td", { class: "mono" }, clock(d.time)), el("td", {}, d.subarchitecture), el("td", { title: d.task_id }, d.name),
    el("td", {}, d.component), el("td", {}, el("span", { class: `state ${d.state}` }, state)),
    el("td", { title: d.reason }, d.reason));
}

/** Render the task managers and the latest decisions from the state. */
export function renderTasks(state) {
  const managed = state.tasks.filter((tm) => tm.proposed || tm.policy);
  document.getElementById("task-managers").replaceChildren(...managed.map((tm) => card(tm, state.time)));
  const rows = state.decisions.slice(0, 60).map(decisionRow);
  document.querySelector("#decisions tbody").replaceChildren(...rows);
  document.getElementById("decisions-empty").hidden = rows.length > 0;
}
