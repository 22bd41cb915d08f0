// The audit trail (audit.list, open to viewers): who did what, when, and how it ended,
// newest first. Read now and then, and after each action of this page.
import { call } from "./app.js";
import { replaceChanged } from "./views.js";

const SHOWN = 50;

function td(text, className = "") {
  const node = document.createElement("td");
  node.textContent = text;
  if (className) {
    node.className = className;
  }
  return node;
}

function when(seconds) {
  return new Date(seconds * 1000).toLocaleTimeString("en-GB", { hour12: false });
}

// How long an acting call took, as `cellctl audit` says it: "" for an entry written whole
// (a refusal) or one whose end is unknown (interrupted); one still running, its time so far.
function took(entry, now) {
  if (typeof entry.ended === "number") {
    return `${Math.max(0, entry.ended - entry.at).toFixed(1)} s`;
  }
  if (entry.result === "running") {
    return `${Math.max(0, now - entry.at).toFixed(0)} s so far`;
  }
  return "";
}

export async function refreshAudit() {
  const body = document.querySelector("#audit-table tbody");
  const out = document.getElementById("audit-message");
  let entries;
  try {
    entries = await call("audit.list", { limit: SHOWN });
  } catch (e) {
    out.textContent = e.message;
    out.className = "message error";
    return;
  }
  out.textContent = entries.length ? "" : "nothing done through the API yet";
  out.className = "message";
  const now = Date.now() / 1000;
  const rows = entries.slice().reverse().map((e) => {
    const row = document.createElement("tr");
    // A call under way is neither done nor refused: shown plainly, with its time so far.
    const ok = e.result === "ok";
    const running = e.result === "running";
    row.className = ok ? "audit-ok" : running ? "audit-running" : "audit-refused";
    row.append(td(when(e.at)), td(took(e, now)), td(e.who), td(e.method),
      td(e.params, "params"), td(e.result, ok || running ? "" : "error"));
    return row;
  });
  replaceChanged(body, rows);  // the same trail read again is not laid out again
}
