// The "What if" panel: a plan of the running cell (the API's plan.run, as `cellctl plan`),
// with a fault window and orders added from its form. The plan plays the cell's state now on
// a copy, on virtual time: the figures and the Gantt chart of what it would finish, and when.
// A plan of weeks plays for many minutes: it is waited for while it tells how far it has
// gone, as `cellctl plan` waits (docs/plan.md), and the panel says how far.
import { ApiError, get } from "./app.js";

function byId(id) {
  return document.getElementById(id);
}

function when(t) {
  if (t === null || t === undefined) {
    return "not in plan";
  }
  return new Date(t * 1000).toLocaleString([], {
    weekday: "short", hour: "2-digit", minute: "2-digit", second: "2-digit", hour12: false,
  });
}

function span(seconds) {
  const s = Math.round(seconds);
  const pad = (n) => String(n).padStart(2, "0");
  return `${Math.floor(s / 3600)}:${pad(Math.floor(s / 60) % 60)}:${pad(s % 60)}`;
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

// Several entries in one field: separated by commas or semicolons between entries, as
// "wax-robot-base:40, wax-toy-mill-table:2" (a fault's own argument keeps its commas: a fault
// is split at ";" only).
function entries(text, separator) {
  return text.split(separator).map((s) => s.trim()).filter((s) => s);
}

let chartUrl = null;

export function renderPlan(answer) {
  const plans = answer.plan.plans;
  const first = plans[0];
  const poll = first.poll_period ? `, poll ${first.poll_period} s` : "";
  byId("plan-window").textContent =
    `from ${when(first.start)} to ${when(first.until)} (${span(first.until - first.start)})${poll}`;
  const rows = [];
  for (const p of plans) {
    for (const o of p.orders) {
      const verdict = o.verdict === "late" ? `late by ${span(o.late_s)}` : o.verdict;
      const tr = row([p.policy, o.order_id, o.part_type, `${o.made}/${o.qty}`, when(o.finished),
        o.due === null ? "-" : when(o.due), verdict]);
      tr.dataset.order = o.order_id;
      tr.dataset.policy = p.policy;
      rows.push(tr);
    }
  }
  byId("plan-orders").replaceChildren(...rows);
  byId("plan-utilization").textContent = plans.map((p) => `${p.policy}: ` + Object.entries(
    p.utilization).map(([m, u]) => `${m} ${(100 * u).toFixed(1)} %`).join(", ")).join("; ");
  // The chart as an image: an SVG shown through <img> runs nothing.
  if (chartUrl !== null) {
    URL.revokeObjectURL(chartUrl);
  }
  chartUrl = URL.createObjectURL(new Blob([answer.svg], { type: "image/svg+xml" }));
  byId("plan-chart").src = chartUrl;
  byId("plan-chart").classList.remove("hidden");
}

// A number as Python's float() reads one ("0.5", "+.5", "1e2", "1_000"), NaN otherwise.
const DECIMAL = /^[+-]?(\d+(_\d+)*\.?(\d+(_\d+)*)?|\.\d+(_\d+)*)([eE][+-]?\d+(_\d+)*)?$/;

// A string as Python's repr() shows it: in single quotes, unless it holds one and no double.
function quoted(text) {
  if (text.includes("'") && !text.includes('"')) {
    return `"${text.replaceAll("\\", "\\\\")}"`;
  }
  return `'${text.replaceAll("\\", "\\\\").replaceAll("'", "\\'")}'`;
}

// The poll period as typed: seconds, checked as the console checks it (cellctl.plan.when's
// parse_poll), in its words; the limit is the field's data-max (the plan's MAX_POLL_S).
function pollSeconds(text, max) {
  const seconds = DECIMAL.test(text) ? Number(text.replaceAll("_", "")) : NaN;
  if (!(seconds > 0 && seconds <= max)) {  // NaN fails it too
    throw new Error(`poll ${quoted(text)}: seconds, more than 0 and at most ${max}`);
  }
  return seconds;
}

// How far a plan has played, in `cellctl plan`'s words: "playing: 2:13:00 of 8:00:00 machine
// time (28%)"; with several policies, each one's share.
function progressText(played, spanS) {
  const share = (s) => `${Math.floor(100 * Math.min(1, s / Math.max(spanS, 1e-9)))}%`;
  const name = (p) => (p === "default" ? "downstream-first" : p);
  const each = Object.entries(played);
  if (each.length === 1) {
    return `playing: ${span(each[0][1])} of ${span(spanS)} machine time (${share(each[0][1])})`;
  }
  return `playing ${span(spanS)} of machine time: ` +
    each.map(([p, s]) => `${name(p)} ${share(s)}`).join(", ");
}

// plan.run on a WebSocket of its own (POST /dashboard/call says nothing until it answers):
// its progress to told(data) as it plays, waited for while it comes, as `cellctl plan` waits
// (cellctl.service.client.plan_call): given up, in its words, when nothing is heard of it
// for silenceS seconds or once it has taken longer than the plan's own span. Closing the
// socket ends the play (the API ends a plan whose session closed): given up, or the page
// gone, the cell's one play is free again.
async function planWhileHeard(params, silenceS, told) {
  const oneshot = await get("/access/oneshot_token");
  const scheme = window.location.protocol === "https:" ? "wss" : "ws";
  const ws = new WebSocket(`${scheme}://${window.location.host}/websocket?token=${oneshot.token}`);
  return new Promise((resolve, reject) => {
    const started = performance.now();
    let silence = null;
    let ended = false;
    const end = (settle, value) => {
      if (!ended) {
        ended = true;
        clearTimeout(silence);
        ws.close();
        settle(value);
      }
    };
    const giveUp = (words) => end(reject, new ApiError(`plan.run: ${words}`, 0));
    const heard = () => {
      clearTimeout(silence);
      silence = setTimeout(() => giveUp(`nothing heard of the plan for ${silenceS} s: it is ` +
        "stuck (the cell's log may say why)"), silenceS * 1000);
    };
    ws.addEventListener("open", () => {
      ws.send(JSON.stringify({ jsonrpc: "2.0", id: 1, method: "plan.run", params }));
      heard();
    });
    ws.addEventListener("message", (event) => {
      const message = JSON.parse(event.data);
      if (message.method === "notify_progress" && message.params.id === 1) {
        // Heard from, but slower than the cell: past its span (or the silence allowed, if
        // longer) since the call began, as the command line's deadline, it is no plan. (A
        // plan that goes silent is caught by the silence's timer.)
        const limitS = Math.max(Number(message.params.span_s) || 0, silenceS);
        if (performance.now() - started > limitS * 1000) {
          giveUp(`no answer from the control API within ${limitS} s`);
          return;
        }
        heard();
        told(message.params);
      } else if (message.id === 1 && message.error) {
        end(reject, new ApiError(message.error.message, 400));
      } else if (message.id === 1) {
        end(resolve, message.result);
      }
    });
    ws.addEventListener("close", () => giveUp("the controller closed the connection before " +
      "the plan was answered"));
  });
}

async function play(event) {
  event.preventDefault();
  const message = byId("plan-message");
  message.textContent = "";  // the last play's words are not this one's
  const params = {
    shift: byId("plan-shift").value.trim() || "8h",
    add: entries(byId("plan-add").value, /[,;]/),
    fault: entries(byId("plan-fault").value, /;/),
    policy: byId("plan-policy").value,
  };
  // Empty: the plan's own poll period; else seconds, as `cellctl plan --poll` takes them.
  const field = byId("plan-poll");
  const poll = field.value.trim();
  if (poll) {
    try {
      params.poll = pollSeconds(poll, Number(field.dataset.max));
    } catch (e) {
      message.textContent = e.message;
      field.focus();
      return;
    }
  }
  const button = byId("plan-play");
  button.disabled = true;
  message.textContent = "playing the cell ahead …";
  // How long the plan may go unheard, s: the form's data-silence (the command line's 600).
  const silenceS = Number(byId("plan-form").dataset.silence) || 600;
  const played = {};
  const told = (data) => {
    played[data.policy] = data.played_s;
    message.textContent = progressText(played, data.span_s);
  };
  try {
    renderPlan(await planWhileHeard(params, silenceS, told));
    message.textContent = "";
  } catch (e) {
    message.textContent = e.message;
  } finally {
    button.disabled = false;
  }
}

// On the document: the panel is gone while the page is refused (no token), and back after.
document.addEventListener("submit", (event) => {
  if (event.target.id === "plan-form") {
    play(event);
  }
});
