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
  const rows = entries.slice().reverse().map((e) => {
    const row = document.createElement("tr");
    const ok = e.result === "ok";
    row.className = ok ? "audit-ok" : "audit-refused";
    row.append(td(when(e.at)), td(e.who), td(e.method), td(e.params, "params"),
      td(e.result, ok ? "" : "error"));
    return row;
  });
  replaceChanged(body, rows);  // the same trail read again is not laid out again
}
