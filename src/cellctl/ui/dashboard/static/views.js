// The dashboard's lists and cards: machines, orders, alarms, held parts, events, traffic.
import { act, call } from "./app.js";
import { clockOf, dueTime } from "./clock.js";
import { renderServiceControls } from "./controls.js";
import { CONDITION_LABELS, machineCondition } from "./floor.js";

function byId(id) {
  return document.getElementById(id);
}

function h(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (key === "class") {
      node.className = value;
    } else if (key === "onclick") {
      node.addEventListener("click", value);
    } else {
      node.setAttribute(key, String(value));
    }
  }
  for (const child of children) {
    if (child !== null && child !== undefined) {
      node.append(child instanceof Node ? child : String(child));
    }
  }
  return node;
}

const clock = clockOf;

// The click of an action button: its method is the button's data-method (declared once).
function actOn(event, question, params, where) {
  return act(question, event.currentTarget.dataset.method, params, where);
}

function duration(seconds) {
  if (!Number.isFinite(seconds) || seconds < 0) {
    return "–";
  }
  if (seconds < 60) {
    return `${seconds.toFixed(seconds < 10 ? 1 : 0)} s`;
  }
  const s = Math.round(seconds);
  if (s < 3600) {
    return `${Math.floor(s / 60)} min ${s % 60} s`;
  }
  return `${Math.floor(s / 3600)} h ${Math.floor((s % 3600) / 60)} min`;
}

export function fillSelect(select, values) {
  const keep = select.value;
  select.replaceChildren(...values.map((v) => h("option", { value: v }, v)));
  if (values.includes(keep)) {
    select.value = keep;
  }
}

// -- machine cards --------------------------------------------------------------------------

// A download or cut from the status' progress fields (rate and time left as it gives them).
function progressText(p) {
  const parts = [p.phase];
  if (p.program) {
    parts.push(p.program);
  }
  if (p.blocks) {
    parts.push(`block ${p.block} of ${p.blocks}`);
  }
  // A punch's total is not known before its end (total 0): what came so far, no share.
  parts.push(p.total ? `${p.done} / ${p.total} ${p.unit}` : `${p.done} ${p.unit}`);
  if (p.rate_per_s) {
    const what = p.unit === "bytes" ? "chars/s" : `${p.unit}/s`;
    parts.push(`${p.rate_per_s.toFixed(p.rate_per_s < 10 ? 1 : 0)} ${what}`);
  }
  if (p.time_left_s !== null && p.time_left_s !== undefined) {
    parts.push(`ETA ${duration(p.time_left_s)}`);
  }
  return parts.join(" · ");
}

// A program's name may break after each "_" (between its words), never inside one.
function breakable(text) {
  const out = [];
  for (const piece of text.split(/(?<=_)/)) {
    if (out.length) {
      out.push(document.createElement("wbr"));
    }
    out.push(piece);
  }
  return out;
}

function card(name) {
  const found = document.querySelector(`.card[data-machine="${CSS.escape(name)}"]`);
  if (found) {
    return found;
  }
  const node = h("article", { class: "card", "data-machine": name },
    h("header", {}, h("h3", {}, name), h("span", { class: "badge state" })),
    h("dl", {},
      h("dt", {}, "state"), h("dd", { class: "machine-state" }),
      h("dt", {}, "step"), h("dd", { class: "step" }),
      h("dt", {}, "part"), h("dd", { class: "part" }),
      h("dt", {}, "utilization"), h("dd", { class: "utilization" }),
      h("dt", {}, "last error"), h("dd", { class: "last-error" })),
    h("div", { class: "progress hidden" },
      h("div", { class: "bar" }, h("div", { class: "fill" })),
      h("p", { class: "progress-text small" }),
      h("p", { class: "stall small hidden" },
        h("span", { class: "stall-label" }, "stalled "), h("span", { class: "stall-s" }))),
    h("div", { class: "preview hidden" }));
  byId("machine-cards").append(node);
  return node;
}

export function renderCards(state, snap) {
  const started = snap.cell.started_at;
  for (const m of state.layout.machines) {
    const machine = snap.machines[m.name];
    if (!machine) {
      continue;
    }
    const node = card(m.name);
    const condition = machineCondition(machine);
    node.dataset.condition = condition;
    node.className = `card condition-${condition}`;
    const badge = node.querySelector(".state");
    badge.textContent = CONDITION_LABELS[condition];
    badge.className = `badge state state-${condition}`;
    node.querySelector(".machine-state").textContent =
      machine.in_service ? machine.state : `${machine.state} (out: ${machine.out_reason || "—"})`;
    const step = machine.step;
    node.querySelector(".step").replaceChildren(
      ...breakable(step ? [step.what, step.program].filter((x) => x).join(" ") : "—"));
    node.querySelector(".part").textContent = machine.part || "—";
    node.querySelector(".utilization").textContent =
      `${(100 * machine.utilization).toFixed(1)} % ` +
      `(${duration(machine.busy_s)} busy since ${clock(started)})`;
    const alarms = snap.alarms.filter((a) => a.machine === m.name);
    let last = "none";
    if (machine.error) {
      last = machine.error.code !== null ? `${machine.error.code}: ${machine.error.text}`
        : machine.error.text;
    } else if (alarms.length) {
      last = alarms[alarms.length - 1].text;
    } else if (machine.failures) {
      last = `${machine.failures} failure(s) in a row`;
    }
    node.querySelector(".last-error").textContent = last;
    const box = node.querySelector(".progress");
    const p = machine.progress;
    box.classList.toggle("hidden", !p);
    if (p) {
      const fill = node.querySelector(".fill");
      fill.style.width = `${(100 * p.fraction).toFixed(1)}%`;
      node.querySelector(".progress-text").textContent = progressText(p);
    }
    showStall(node, p);
    if (m.role === "mill") {
      showPreview(state, node, m.name, p);
    }
    renderServiceControls(node, machine);
  }
}

// A drip-feed's stall (the axes stopped, waiting for data) in a field of its own: shown
// where the status gives one (stall_s), with the seconds in .stall-s.
function showStall(node, p) {
  const box = node.querySelector(".stall");
  const known = Boolean(p) && p.stall_s !== null && p.stall_s !== undefined;
  box.classList.toggle("hidden", !known);
  box.classList.toggle("stalled", known && p.stall_s > 0);
  node.querySelector(".stall-s").textContent = known ? duration(p.stall_s) : "";
  box.title = "seconds the machine waited for data this run, its axes stopped";
}

function showPreview(state, node, mill, progress) {
  const box = node.querySelector(".preview");
  const program = progress && progress.program;
  if (!program) {
    box.classList.add("hidden");
    return;
  }
  box.classList.remove("hidden");
  const key = `${mill}/${program}`;
  const found = state.previews[key];
  if (found === undefined) {
    state.previews[key] = null;  // asked for
    call("programs.preview", { machine: mill, program })
      .then((r) => { state.previews[key] = r; })
      .catch((e) => { state.previews[key] = { error: e.message }; });
    return;
  }
  if (found === null) {
    return;
  }
  if (box.dataset.program !== key) {
    box.dataset.program = key;
    if (found.error) {
      box.replaceChildren(h("p", { class: "small error" }, found.error));
    } else {
      const doc = new DOMParser().parseFromString(found.svg, "image/svg+xml");
      const svg = document.importNode(doc.documentElement, true);
      svg.removeAttribute("width");
      svg.removeAttribute("height");
      svg.setAttribute("class", "toolpath");
      box.replaceChildren(svg, ...previewCaption(svg));
    }
  }
  for (const g of box.querySelectorAll(".block-start")) {
    g.classList.toggle("current", Number(g.dataset.block) === Number(progress.block));
  }
}

// The drawing's caption (its first text: program, blocks, distance) as the page's own text,
// readable at a card's width; a click on the drawing shows it at full size.
function previewCaption(svg) {
  const first = svg.querySelector("text");
  svg.addEventListener("click", () => {
    const big = svg.cloneNode(true);
    big.setAttribute("class", "toolpath-full");
    big.setAttribute("width", big.viewBox.baseVal.width);
    byId("toolpath-view").replaceChildren(big);
    byId("toolpath").showModal();
  });
  // The drawing spaces its caption's fields apart; HTML would fold the spaces into one.
  const fields = first ? first.textContent.trim().split(/\s{2,}/) : [];
  return first ? [h("p", { class: "preview-caption small" }, fields.join(" · "),
    " · click the drawing for its full size")] : [];
}

// -- orders -----------------------------------------------------------------------------------

const NOT_STARTED = new Set(["posted", "accepted"]);

export function renderOrders(snap) {
  const rows = snap.orders.map((o) => {
    const parts = Object.entries(o.parts || {}).map(([k, v]) => `${v} ${k}`).join(", ");
    const started = Object.keys(o.parts || {}).some((k) => k !== "waiting");
    const cancel = NOT_STARTED.has(o.state) && !started
      ? h("button", {
        class: "small-button",
        "data-method": "orders.cancel",
        onclick: (e) => actOn(e, `Cancel order ${o.id} (${o.qty} × ${o.part_type})?`,
          { id: o.id }, "order-message"),
      }, "Cancel")
      : null;
    return h("tr", { "data-order": o.id, class: `order-${o.state}` },
      h("td", {}, o.id), h("td", {}, o.part_type), h("td", {}, o.qty), h("td", {}, o.priority),
      h("td", { class: o.blocked ? "blocked" : "", title: o.blocked || "" },
        o.blocked ? `${o.state} · ${o.blocked}` : o.state),
      h("td", {}, parts || "—"), dueCell(o), h("td", {}, cancel));
  });
  replaceRows("order-table", rows, "no orders", 8);
}

// When an order is due, and LATE in words (not only in red) once the status says it is.
function dueCell(o) {
  if (o.due === null || o.due === undefined) {  // none, or a controller from before due times
    return h("td", { class: "due" }, "—");
  }
  if (!o.late) {
    return h("td", { class: "due" }, dueTime(o.due));
  }
  return h("td", { class: "due late" }, dueTime(o.due), " ",
    h("span", { class: "late-badge" }, "LATE"));
}

// -- alarms and held parts ------------------------------------------------------------------

// An alarm is shown unacknowledged (flashing, in the header's badge) until the operator
// acknowledges it, unless it is shelved and its time has not run out (docs/dashboard.md).
let lastAlarms = null;
const heard = new Set();   // unacknowledged alarms the sound already rang for

function shelvedNow(a, now) {
  return Boolean(a.shelved_until && a.shelved_until > now);
}

export function unacked(a, now = Date.now() / 1000) {
  return a.state === "active" && a.acked === null && !shelvedNow(a, now);
}

function alarmState(a, now) {
  const words = [a.acked === null ? "unacknowledged" : "acknowledged"];
  words.push(a.returned === null ? "active" : "returned to normal");
  if (shelvedNow(a, now)) {
    words.push(`shelved until ${clock(a.shelved_until)}`);
  }
  return words.join(", ");
}

function beep() {
  try {
    const audio = new AudioContext();
    const tone = audio.createOscillator();
    tone.frequency.value = 880;
    tone.connect(audio.destination);
    tone.start();
    tone.stop(audio.currentTime + 0.3);
  } catch (e) {
    // no audio output: the badge still flashes
  }
}

export function renderAlarms(snap) {
  lastAlarms = snap.alarms;
  const now = Date.now() / 1000;
  const open = snap.alarms.filter((a) => unacked(a, now));
  const badge = byId("alarm-badge");
  badge.textContent = open.length ? `${open.length} unacknowledged` : "";
  badge.classList.toggle("hidden", !open.length);
  badge.classList.toggle("flashing", open.length > 0);
  const fresh = open.filter((a) => !heard.has(a.id));
  fresh.forEach((a) => heard.add(a.id));
  if (fresh.length && byId("alarm-sound").checked) {
    beep();
  }
  const rows = snap.alarms.map((a) => h("tr", {
    "data-alarm": a.id,
    class: `priority-${a.priority}` + (unacked(a, now) ? " unacked" : ""),
  },
    h("td", {}, a.id), h("td", {}, clock(a.raised)), h("td", {}, a.priority),
    h("td", {}, a.machine), h("td", {}, a.text), h("td", { class: "alarm-state" }, alarmState(a, now)),
    h("td", { class: "actions" },
      a.acked === null ? h("button", {
        class: "small-button",
        "data-method": "alarms.ack",
        onclick: (e) => actOn(e, null, { id: a.id }, "alarm-message"),
      }, "Ack") : null,
      h("button", {
        class: "small-button",
        "data-method": "alarms.shelve",
        onclick: (e) => actOn(e, `Shelve alarm ${a.id} (${a.machine}: ${a.text}) for 1 h?`,
          { id: a.id, seconds: 3600 }, "alarm-message"),
      }, "Shelve 1 h"),
      // Shown again at once: nothing stops, so no confirmation (as Ack).
      shelvedNow(a, now) ? h("button", {
        class: "small-button",
        "data-method": "alarms.unshelve",
        onclick: (e) => actOn(e, null, { id: a.id }, "alarm-message"),
      }, "Unshelve") : null,
      h("button", {
        class: "small-button",
        "data-method": "alarms.clear",
        onclick: (e) => actOn(e, `Clear alarm ${a.id} (${a.machine}: ${a.text})?`,
          { id: a.id }, "alarm-message"),
      }, "Clear"))));
  replaceRows("alarm-table", rows, "no active alarm", 7);
}

// A shelved alarm comes back when its time runs out, with no update from the server.
setInterval(() => {
  if (lastAlarms !== null) {
    renderAlarms({ alarms: lastAlarms });
  }
}, 5000);

export function renderHeld(snap) {
  const held = snap.parts.filter((p) => p.status === "held");
  const rows = held.map((p) => h("tr", { "data-part": p.id },
    h("td", {}, p.id), h("td", {}, p.part_type), h("td", {}, p.location), h("td", {}, p.note),
    h("td", { class: "actions" },
      h("button", {
        class: "small-button",
        "data-method": "parts.release",
        onclick: (e) => actOn(e, `Release part ${p.id}? Its last step counts as done.`,
          { id: p.id, redo: false }, "part-message"),
      }, "Release"),
      h("button", {
        class: "small-button",
        "data-method": "parts.release",
        onclick: (e) => actOn(e, `Release part ${p.id} and run its last step again?`,
          { id: p.id, redo: true }, "part-message"),
      }, "Release & redo"),
      h("button", {
        class: "small-button danger",
        "data-method": "parts.scrap",
        onclick: (e) => actOn(e, scrapQuestion(p),
          { id: p.id, taken_out: (p.may_be_in || []).length > 0 }, "part-message"),
      }, "Scrap"))));
  replaceRows("held-table", rows, "no held part", 5);
}

// As the console asks it (service/operator.py's scrap_question): by the machines the part
// may be in, whose answer is the API's taken_out.
function scrapQuestion(p) {
  const places = p.may_be_in || [];
  if (!places.length) {
    return `Scrap part ${p.id}? This cannot be undone.`;
  }
  const where = places.join(" or ");
  return `Scrap part ${p.id}? It may be in ${where}: take it out first (the cell loads `
    + `${where} again at once). Is it out? This cannot be undone.`;
}

function replaceRows(tableId, rows, empty, columns) {
  // Rebuilding while a dialog is open would be harmless; rebuilding under the pointer is not
  // (a click would land on a new button): identical content is skipped.
  replaceChanged(byId(tableId).querySelector("tbody"), rows.length ? rows
    : [h("tr", { class: "empty" }, h("td", { colspan: columns }, empty))]);
}

// ``node``'s children replaced by ``items`` unless they show the same already (each rebuild
// lays the page out again, and a push comes many times a second while a batch runs).
export function replaceChanged(node, items) {
  const html = items.map((i) => i.outerHTML).join("");
  if (node.dataset.shown !== html) {
    node.dataset.shown = html;
    node.replaceChildren(...items);
  }
}

// -- events and traffic ---------------------------------------------------------------------

export function renderEvents(snap) {
  const items = snap.events.slice(-15).reverse()
    .map((e) => h("li", {}, h("time", {}, clock(e.time)), " ", e.text));
  replaceChanged(byId("event-list"), items);  // a push with no event leaves it as it is
}

export function renderTraffic(rows) {
  const items = rows.slice(-40).map((r) => h("tr", { class: r.dir === ">>" ? "sent" : "received" },
    h("td", {}, clock(r.time)), h("td", {}, r.dir === ">>" ? "→" : "←"),
    h("td", { class: "hex" }, r.hex), h("td", { class: "text" }, r.text)));
  replaceRows("traffic-table", items, "no traffic yet", 4);
}
