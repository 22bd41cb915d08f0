// The Shift panel: the figures of `cellctl report shift` (the API's report.shift) over the
// last 8 hours, or since the journal's first step: OEE per machine after ISO 22400, parts,
// alarms by cause, downtime by reason, the controller's time and events, and what the window
// leaves to the next shift (parts held, alarms open). Read every SHIFT_MS while connected
// and shown. Its words are the text report's (src/cellctl/ui/report_cli.py), so a shift lead
// reads the same lines on the page and on paper.
import { call, state } from "./app.js";
import { timeOfDay, whileShown } from "./clock.js";

const SHIFT_MS = 10000;
// The controller's states as the text report names them, and their keys in the report.
const STATES = [
  ["running", "running_s"], ["paused", "paused_s"], ["stopped", "stopped_s"],
  ["not known", "not_known_s"],
];
// The controller's events listed at most (the latest), as in the text report's table.
const EVENT_LINES = 12;
// The event the report adds where a controller ended without a word (cellctl.cell.shift).
const ENDED_UNHEARD = "ended unheard";

function byId(id) {
  return document.getElementById(id);
}

// A ratio not known yet (null: no step ended, no time in steps) reads as the report's dash.
function pct(x) {
  return x === null || x === undefined ? "\u2014" : `${(100 * x).toFixed(1)} %`;
}

function span(seconds) {
  if (seconds < 60) {
    return `${seconds.toFixed(1)} s`;
  }
  const s = Math.round(seconds);
  const pad = (n) => String(n).padStart(2, "0");
  return `${Math.floor(s / 3600)}:${pad(Math.floor(s / 60) % 60)}:${pad(s % 60)}`;
}

function hhmm(t) {
  return new Date(t * 1000).toLocaleTimeString([], { hour12: false });
}

// A time with its day (MM-DD HH:MM:SS, as the text report's lists): a part may be held, an
// alarm open, since a day before the window, and a time of day alone would hide that.
function dayTime(t) {
  const d = new Date(t * 1000);
  const two = (n) => String(n).padStart(2, "0");
  return `${two(d.getMonth() + 1)}-${two(d.getDate())} ${timeOfDay(d)}`;
}

function row(cells) {
  const tr = document.createElement("tr");
  for (const text of cells) {
    const td = document.createElement("td");
    td.textContent = text;
    tr.append(td);
  }
  return tr;
}

// "no part", "1 part", "2 parts" (the text report's count).
function count(n, thing) {
  return n === 0 ? `no ${thing}` : `${n} ${thing}${n > 1 ? "s" : ""}`;
}

// A controller event in the text report's words: "resumed by token:eve (engineer)",
// "paused: emergency stop pressed".
function eventWords(e) {
  if (e.event === ENDED_UNHEARD) {
    return "ended without stopping (a crash, a kill?): last heard of then";
  }
  return `${e.event}${e.by ? ` by ${e.by}` : ""}${e.why ? `: ${e.why}` : ""}`;
}

// Where an alarm open at the window's end stood then, in the text report's words.
function alarmStanding(a) {
  const condition = a.active ? "still active" : "returned to normal";
  if (!a.acknowledged) {
    return `${condition}, not acknowledged`;
  }
  return `${condition}, acknowledged${a.acked_by ? ` by ${a.acked_by}` : ""}`;
}

// The parts held and the alarms open at the window's end: what the next shift reads first.
function renderHandover(report) {
  const held = report.held_at_end;
  const alarms = report.open_alarms_at_end;
  const unacked = alarms.filter((a) => !a.acknowledged).length;
  let opened = `${count(alarms.length, "alarm")} open`;
  if (alarms.length) {
    opened += unacked ? ` (${unacked} not acknowledged)` : " (all acknowledged)";
  }
  byId("shift-handover").textContent =
    `at the window's end: ${count(held.length, "part")} held, ${opened}`;
  byId("shift-held").replaceChildren(...held.map((p) => {
    const tr = row([p.part, p.part_type, p.location, dayTime(p.since), p.why]);
    tr.dataset.part = p.part;
    return tr;
  }));
  byId("shift-open-alarms").replaceChildren(...alarms.map((a) => {
    const tr = row([a.id, dayTime(a.raised), a.priority, a.machine, a.code, a.text,
      alarmStanding(a)]);
    tr.dataset.alarm = a.id;
    // Not acknowledged by the window's end: marked as the Alarms panel marks one.
    tr.classList.toggle("unacked", !a.acknowledged);
    return tr;
  }));
  // An empty table says nothing the line above does not: only a list is shown.
  byId("shift-held-box").classList.toggle("hidden", !held.length);
  byId("shift-open-alarms-box").classList.toggle("hidden", !alarms.length);
}

// The window's time by the controller's state (they add up to the window), and its events.
function renderController(report) {
  const split = STATES
    .filter(([, key]) => key !== "not_known_s" || report[key] > 0)  // said when there is some
    .map(([name, key]) => `${name} ${span(report[key])}`);
  byId("shift-controller").textContent = `controller: ${split.join(", ")}`;
  const events = report.controller_events;
  const items = events.slice(-EVENT_LINES).map((e) => {
    const li = document.createElement("li");
    const time = document.createElement("time");
    time.textContent = dayTime(e.time);
    li.append(time, " ", eventWords(e));
    li.dataset.event = e.event;
    return li;
  });
  if (events.length > EVENT_LINES) {
    const more = document.createElement("li");
    more.className = "small";
    more.textContent =
      `(${events.length - EVENT_LINES} earlier events: cellctl report shift --json lists them)`;
    items.unshift(more);
  }
  byId("shift-events").replaceChildren(...items);
}

export function renderShift(report) {
  byId("shift-window").textContent =
    `${hhmm(report.start)} to ${hhmm(report.end)} (${span(report.end - report.start)}, ` +
    `time scale ${report.time_scale})`;
  byId("shift-machines").replaceChildren(...report.machines.map((m) => {
    const tr = row([m.machine, pct(m.availability), pct(m.performance), pct(m.quality),
      pct(m.oee), span(m.production_s), span(m.down_s), `${m.steps_good} / ${m.steps_ended}`]);
    tr.dataset.machine = m.machine;
    return tr;
  }));
  byId("shift-parts").textContent = `parts good ${report.parts_good}, held ` +
    `${report.parts_held}, scrapped ${report.parts_scrapped}`;
  const alarms = report.alarms_by_cause.map((a) => `${a.count} × ${a.code} (${a.priority})`);
  byId("shift-alarms").textContent = `alarms by cause: ${alarms.join(", ") || "none"}`;
  const downs = report.downtime_by_reason.map(
    (d) => `${d.machine} ${d.reason} ${span(d.seconds)}`);
  byId("shift-downtime").textContent = `downtime by reason: ${downs.join("; ") || "none"}`;
  renderHandover(report);
  renderController(report);
}

async function refreshShift() {
  if (!state.connected) {
    return;
  }
  try {
    renderShift(await call("report.shift"));
    byId("shift-message").textContent = "";
  } catch (e) {
    byId("shift-message").textContent = e.message;
  }
}

whileShown(SHIFT_MS, refreshShift);
setTimeout(() => document.hidden || refreshShift(), 1000);  // once connected, if shown
