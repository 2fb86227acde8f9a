// The working-memories view: one SA's entries (filtered by type), the clicked entry's value live, the last changes.

import { ago, clock, el, shortType } from "./util.js";

const SHOWN_CHANGES = 50;

/** Render a JSON value as highlighted text (keys, strings, numbers, booleans, null). */
function jsonNodes(value) {
  const text = JSON.stringify(value, null, 2) ?? "null";
  const out = [];
  const token = /("(?:\\.|[^"\\])*")(\s*:)?|\b(true|false)\b|\bnull\b|-?\d+(?:\.\d+)?(?:[eE][+-]?\d+)?/g;
  let last = 0;
  for (const m of text.matchAll(token)) {
    out.push(text.slice(last, m.index));
    const cls = m[1] ? (m[2] ? "k" : "s") : m[3] ? "b" : m[0] === "null" ? "z" : "n";
    out.push(el("span", { class: cls }, m[1] && m[2] ? m[1] : m[0]));
    if (m[1] && m[2]) out.push(m[2]);
    last = m.index + m[0].length;
  }
  out.push(text.slice(last));
  return out;
}

export class Memories {
  constructor(api) {
    this.api = api;
    this.sa = "";
    this.type = "";
    this.selected = null; // {sa, id}
    this.listing = null;
    this.changes = [];
    this.pending = null;
    this.valueVersion = null;
    this.active = false; // whether the view is shown
    document.getElementById("wm-type").addEventListener("change", (e) => { this.type = e.target.value; this.load(); });
  }

  /** Shown or hidden: when shown again, the entries and the selected value are brought up to date. */
  show(active) {
    if (active && !this.active) { this.load(); this.refreshValue(); }
    this.active = active;
  }

  /** The SAs are known (every state): draw the SA buttons; choose the first SA once. */
  update(state) {
    const names = state.subarchitectures.map((sa) => sa.name);
    if (!names.includes(this.sa)) { this.sa = names[0] || ""; this.type = ""; this.load(); }
    const buttons = state.subarchitectures.map((sa) => el("button", {
      class: sa.name === this.sa ? "active" : "", "data-wm": sa.name,
      onclick: () => { if (this.sa !== sa.name) { this.sa = sa.name; this.type = ""; this.load(); this.drawChanges(); } },
    }, sa.name, el("span", { class: "count" }, sa.entries)));
    document.getElementById("wm-sas").replaceChildren(...buttons);
    this.now = state.time;
    if (this.listing) this.drawEntries();
  }

  /** New changes arrived: keep them, and reload what they touch (debounced). */
  changed(items) {
    this.changes.push(...items);
    if (this.changes.length > 200) this.changes.splice(0, this.changes.length - 200);
    this.drawChanges();
    // Reloaded only while shown: a busy robot's changes must not keep a hidden tab asking for entries.
    if (this.active && items.some((c) => c.gap || c.subarchitecture === this.sa)) this.later(() => this.load());
    const sel = this.selected;
    if (this.active && sel && items.some((c) => c.subarchitecture === sel.sa && c.id === sel.id)) this.refreshValue();
  }

  /** Fetch the selected value again: one request at a time, and one more after it if it changed meanwhile. */
  async refreshValue() {
    if (this.valueBusy) { this.valueAgain = true; return; }
    this.valueBusy = true;
    try {
      do {
        this.valueAgain = false;
        if (this.selected) await this.showValue(this.selected.sa, this.selected.id);
      } while (this.valueAgain);
    } finally {
      this.valueBusy = false;
    }
  }

  later(fn) {
    if (this.pending) return;
    this.pending = setTimeout(() => { this.pending = null; fn(); }, 250);
  }

  async load() {
    if (!this.sa) return;
    const query = new URLSearchParams({ sa: this.sa, ...(this.type ? { type: this.type } : {}) });
    const ticket = (this.loads = (this.loads || 0) + 1);
    const listing = await this.api(`/api/entries?${query}`);
    // Only the answer to the latest request counts: an older one (another SA or type) may arrive after it.
    if (!listing || ticket !== this.loads) return;
    const before = new Map((this.listing?.entries || []).map((e) => [`${e.subarchitecture}/${e.id}`, e.version]));
    this.fresh = new Set(listing.entries.filter((e) => this.listing && before.get(`${e.subarchitecture}/${e.id}`)
      !== e.version).map((e) => e.id));
    this.listing = listing;
    this.drawEntries();
  }

  drawEntries() {
    const listing = this.listing;
    const select = document.getElementById("wm-type");
    select.replaceChildren(el("option", { value: "" }, "all types"),
      ...listing.types.map((t) => el("option", { value: t, selected: t === this.type }, t)));
    const shown = listing.entries.length;
    const held = this.type ? `${shown} of type ${shortType(this.type)}` : `${listing.total} entries`;
    document.getElementById("wm-count").textContent =
      `${held}${shown < listing.total && !this.type ? `, the ${shown} latest shown` : ""} · revision ${listing.revision}`;
    const rows = listing.entries.map((e) => el("tr", {
      "data-entry-id": e.id, "data-sa": e.subarchitecture,
      class: [this.selected?.id === e.id && this.selected?.sa === e.subarchitecture ? "selected" : "",
              this.fresh?.has(e.id) ? "fresh" : ""].join(" ").trim(),
      onclick: () => this.select(e.subarchitecture, e.id),
    }, el("td", { class: "mono", title: e.id }, e.id), el("td", { title: e.type }, shortType(e.type)),
       el("td", { class: "num" }, e.version), el("td", {}, e.author), el("td", { class: "muted" }, ago(e.modified, this.now))));
    document.querySelector("#entries tbody").replaceChildren(...rows);
    document.getElementById("entries-empty").hidden = rows.length > 0;
    this.fresh = null;
  }

  select(sa, id) {
    this.selected = { sa, id };
    this.valueVersion = null;
    this.refreshValue();
    for (const row of document.querySelectorAll("#entries tbody tr")) {
      row.classList.toggle("selected", row.dataset.entryId === id && row.dataset.sa === sa);
    }
  }

  async showValue(sa, id) {
    const entry = await this.api(`/api/entry?${new URLSearchParams({ sa, id })}`, true);
    if (!this.selected || this.selected.sa !== sa || this.selected.id !== id) return;
    const head = document.getElementById("value-head");
    const pre = document.getElementById("value");
    if (!entry || entry.error) {
      head.replaceChildren(el("b", {}, `${sa} / ${id}`), " ", el("span", { class: "op delete" }, "gone"));
      pre.replaceChildren(entry?.error || "");
      return;
    }
    head.className = "value-head";
    head.replaceChildren(el("b", { class: "mono" }, `${sa} / ${id}`), el("br"),
      el("span", { class: "muted" }, `${entry.type} · version `), el("b", { "data-value-version": entry.version },
        entry.version), el("span", { class: "muted" }, ` · by ${entry.author} · revision ${entry.revision}`));
    pre.replaceChildren(...jsonNodes(entry.value));
    pre.dataset.version = entry.version;
    if (this.valueVersion !== null && this.valueVersion !== entry.version) {
      pre.classList.remove("updated"); void pre.offsetWidth; pre.classList.add("updated");
    }
    this.valueVersion = entry.version;
  }

  drawChanges() {
    const mine = this.changes.filter((c) => c.gap || (c.subarchitecture === this.sa && (!this.type || c.type === this.type)));
    const latest = mine.slice(-SHOWN_CHANGES).reverse();
    document.getElementById("changes-title").textContent =
      `Last ${SHOWN_CHANGES} changes in ${this.sa || "…"}${this.type ? ` (${shortType(this.type)})` : ""}`;
    const rows = latest.map((c) => c.gap
      ? el("tr", {}, el("td", {}, clock(c.time)), el("td"), el("td", {}, el("span", { class: "op gap" }, "gap")),
           el("td", { colspan: 4 }, `${c.subarchitecture}: ${c.reason}`))
      : el("tr", { "data-change": `${c.subarchitecture}/${c.id}@${c.version}` },
           el("td", { class: "mono" }, clock(c.time)), el("td", { class: "num" }, c.revision),
           el("td", {}, el("span", { class: `op ${c.operation}` }, c.operation)),
           el("td", { class: "mono", title: c.id }, c.id), el("td", { title: c.type }, shortType(c.type)),
           el("td", { class: "num" }, c.version), el("td", {}, c.author)));
    document.querySelector("#changes tbody").replaceChildren(...rows);
    document.getElementById("changes-empty").hidden = rows.length > 0;
  }
}
