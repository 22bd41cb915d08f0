// The Shift panel: the figures of `cellctl report shift` (the API's report.shift) over the
// last 8 hours, or since the journal's first step: OEE per machine after ISO 22400, parts,
// alarms by cause, downtime by reason. Read every SHIFT_MS while connected and shown.
import { call, state } from "./app.js";
import { whileShown } from "./clock.js";

const SHIFT_MS = 10000;

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

function row(cells) {
  const tr = document.createElement("tr");
  for (const text of cells) {
    const td = document.createElement("td");
    td.textContent = text;
    tr.append(td);
  }
  return tr;
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
