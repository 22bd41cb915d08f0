// cellctl dashboard: the token, the API, the live subscription, and the views' refresh.
//
// The token comes in the URL's fragment (#token=...), is kept in sessionStorage and is sent
// as "Authorization: Bearer" with every request. Live updates come from the API's WebSocket
// (a one-shot token fetched with the header); calls that act go through POST /dashboard/call.
import { refreshAudit } from "./audit.js";
import { timeOfDay, whileShown } from "./clock.js";
import {
  hideCellControls, renderCellControls, wireCellControls,
} from "./controls.js";
import { drawFloor, updateFloor } from "./floor.js";
import { renderGantt, exportGantt } from "./gantt.js";
import {
  renderCards, renderOrders, renderAlarms, renderHeld, renderEvents, renderTraffic, fillSelect,
} from "./views.js";

const TOKEN_KEY = "cellctl.token";
const MODE_LABELS = {
  running: "running",
  paused: "paused",
  stopping: "stopping",
  "emergency-stop": "emergency stop",
  "no-controller": "no controller",
};
const RETRY_MAX_MS = 5000;

export const state = {
  snapshot: null,   // the status object (docs/api.md), kept up to date by the subscription
  layout: null,     // cell.layout
  steps: [],        // steps.list for the Gantt chart
  previews: {},     // "mill/program" -> {svg, blocks} or {error}
  connected: false,
  pushedAt: 0,      // the time of the last update pushed
};

// -- the token ------------------------------------------------------------------------------

async function takeToken() {
  const hash = new URLSearchParams(window.location.hash.slice(1));
  const given = hash.get("token");
  const code = hash.get("code");
  if (given || code) {
    // Out of the address bar (and of the history): the fragment has done its work.
    history.replaceState(null, "", window.location.pathname + window.location.search);
  }
  if (given) {
    sessionStorage.setItem(TOKEN_KEY, given);
  } else if (code) {
    // `cellctl dashboard` opens the page with a code good once, not the token (a browser's
    // command line is read by every user of the host): swapped here for the token.
    try {
      const answer = await fetch("/dashboard/handover", {
        method: "POST",
        headers: { "Content-Type": "application/json" },
        body: JSON.stringify({ code }),
      });
      if (answer.ok) {
        sessionStorage.setItem(TOKEN_KEY, (await answer.json()).token);
      }
    } catch (e) {
      // No answer: the page says it has no token, below.
    }
  }
  return sessionStorage.getItem(TOKEN_KEY) || "";
}

const token = await takeToken();

// -- the API --------------------------------------------------------------------------------

export class ApiError extends Error {
  constructor(message, status) {
    super(message);
    this.status = status;
  }
}

function headers(extra = {}) {
  return { Authorization: `Bearer ${token}`, ...extra };
}

async function answer(response) {
  let body = null;
  try {
    body = await response.json();
  } catch {
    body = null;
  }
  if (response.status === 401) {
    refused("The controller refused this page: the API token is missing or wrong.");
    throw new ApiError("refused: the API token is missing or wrong", 401);
  }
  if (!response.ok || (body && body.error)) {
    const message = body && body.error && body.error.message
      ? body.error.message : `the controller answered HTTP ${response.status}`;
    throw new ApiError(message, response.status);
  }
  return body;
}

export async function get(path) {
  return answer(await fetch(path, { headers: headers(), cache: "no-store" }));
}

export async function call(method, params = {}) {
  const response = await fetch("/dashboard/call", {
    method: "POST",
    headers: headers({ "Content-Type": "application/json" }),
    body: JSON.stringify({ method, params }),
    cache: "no-store",
  });
  return (await answer(response)).result;
}

// -- what the page says ---------------------------------------------------------------------

function byId(id) {
  return document.getElementById(id);
}

let wasRefused = false;

function refused(text) {
  wasRefused = true;
  state.snapshot = null;
  state.connected = false;  // the views go: nothing reads or draws them any more
  byId("content").classList.add("hidden");
  byId("content").replaceChildren();
  byId("refused-text").textContent = text;
  byId("refused").classList.remove("hidden");
  byId("connecting").classList.add("hidden");
  hideCellControls();
  setConnection("refused", "bad");
}

function setConnection(text, kind) {
  const el = byId("connection");
  el.textContent = text;
  el.className = `connection ${kind || ""}`;
}

export function notice(text) {
  const el = byId("notice");
  if (!text) {
    el.classList.add("hidden");
    el.textContent = "";
    return;
  }
  el.textContent = text;
  el.classList.remove("hidden");
}

// -- confirmation ---------------------------------------------------------------------------

export function confirmAction(text) {
  const dialog = byId("confirm");
  byId("confirm-text").textContent = text;
  return new Promise((resolve) => {
    dialog.addEventListener("close", () => resolve(dialog.returnValue === "ok"), { once: true });
    dialog.returnValue = "";
    dialog.showModal();
  });
}

// An action from a button: confirmed, called, its answer (or the refusal) shown in `where`.
// question: what to confirm first; null acts at once (an acknowledgement changes nothing
// but the alarm's "seen" mark).
export async function act(question, method, params, where) {
  if (question !== null && !(await confirmAction(question))) {
    return;
  }
  const out = byId(where);
  out.className = "message";
  out.textContent = "…";
  try {
    const result = await call(method, params);
    out.textContent = (result && result.message) || "done";
    out.classList.add("ok");
  } catch (e) {
    out.textContent = e.message;
    out.classList.add("error");
  }
  await refresh();
  refreshAudit();
}

// -- rendering ------------------------------------------------------------------------------

export function render() {
  const snap = state.snapshot;
  if (!snap || !state.layout) {
    return;
  }
  updateFloor(state.layout, snap);
  renderCards(state, snap);
  renderOrders(snap);
  renderAlarms(snap);
  renderHeld(snap);
  renderEvents(snap);
  renderCellControls(snap);
  const cellState = byId("cell-state");
  const mode = snap.cell.mode;
  cellState.textContent = MODE_LABELS[mode] || mode;
  cellState.className = `badge mode-${mode} ${mode === "running" ? "good" : "warn"}`;
}

// Updates come pushed up to a hundred times a second while the cell works (a block, a
// position); an eye reads some ten. The first is drawn at once, then at most one drawing
// every RENDER_MS, the latest state always drawn last: the page's CPU stays low, no state
// that lasts is missed.
const RENDER_MS = 100;
let renderTimer = null;
let renderedAt = -Infinity;

function renderSoon() {
  if (renderTimer !== null) {
    return;  // a drawing is due: it draws the state as it is then
  }
  const wait = Math.max(0, renderedAt + RENDER_MS - performance.now());
  renderTimer = setTimeout(() => {
    renderTimer = null;
    renderedAt = performance.now();
    render();
  }, wait);
}

export async function refresh() {
  try {
    const status = await get("/api/status");
    // A read answered after a newer push arrived is dropped: the push is the later word.
    if (!state.snapshot || status.cell.time >= state.pushedAt) {
      state.snapshot = status;
      render();
    }
  } catch (e) {
    if (e.status !== 401) {
      notice(`could not read the cell's status: ${e.message}`);
    }
  }
}

async function refreshSteps() {
  if (!state.connected) {
    return;
  }
  const span = Number(byId("gantt-window").value);
  const since = Date.now() / 1000 - span;
  try {
    state.steps = await call("steps.list", { since });
    renderGantt(byId("gantt-chart"), state.layout, state.steps, since);
  } catch (e) {
    byId("gantt-chart").textContent = e.message;
  }
}

async function refreshTraffic() {
  if (!state.connected) {
    return;  // refused, the page's views are gone; or not live yet
  }
  const machine = byId("traffic-machine").value;
  if (!machine || !byId("traffic-follow").checked) {
    return;
  }
  try {
    renderTraffic(await call("traffic.tail", { machine, limit: 40 }));
    byId("traffic-message").textContent = "";
  } catch (e) {
    byId("traffic-message").textContent = e.message;
  }
}

// -- the live subscription ------------------------------------------------------------------

// A pushed update applied to the status held (docs/api.md, "Updates"): the cell and the lists
// whole when they changed, the machines that changed by name, only the new events.
export function applyUpdate(snap, update) {
  for (const key of ["cell", "orders", "parts", "alarms"]) {
    if (key in update) {
      snap[key] = update[key];
    }
  }
  for (const name of update.machines_gone || []) {
    delete snap.machines[name];
  }
  Object.assign(snap.machines, update.machines || {});
  if (update.events) {
    // A status read since the last push may hold some of them already: both are windows on
    // one log, so the longest tail of the held list that starts the update is dropped (as
    // new_events in service/status.py does). Two events of one time are both kept.
    snap.events = [...snap.events, ...newEvents(snap.events, update.events)].slice(-30);
  }
  state.pushedAt = update.time;
}

const sameEvent = (a, b) => a.time === b.time && a.text === b.text;

// The events of `fresh` that `held` does not end with already.
export function newEvents(held, fresh) {
  for (let k = Math.min(held.length, fresh.length); k > 0; k--) {
    const tail = held.slice(-k);
    if (tail.every((e, i) => sameEvent(e, fresh[i]))) {
      return fresh.slice(k);
    }
  }
  return fresh;
}

let retryMs = 500;
let lostAt = null;

async function connect() {
  if (wasRefused) {
    return;
  }
  let ws;
  try {
    const oneshot = await get("/access/oneshot_token");
    const scheme = window.location.protocol === "https:" ? "wss" : "ws";
    ws = new WebSocket(`${scheme}://${window.location.host}/websocket?token=${oneshot.token}`);
  } catch (e) {
    if (e.status === 401) {
      return;
    }
    lost(`cannot reach the controller (${e.message})`);
    return;
  }
  let subscribed = false;
  ws.addEventListener("open", () => {
    ws.send(JSON.stringify({ jsonrpc: "2.0", id: 1, method: "cell.subscribe" }));
  });
  ws.addEventListener("message", async (event) => {
    const message = JSON.parse(event.data);
    if (message.id === 1 && message.result) {
      subscribed = true;
      const again = lostAt !== null;
      retryMs = 500;
      state.snapshot = message.result;
      state.pushedAt = message.result.cell.time;
      if (!state.layout || again) {
        await loadLayout();
      }
      state.connected = true;
      byId("content").classList.remove("hidden");
      byId("connecting").classList.add("hidden");
      refreshAudit();
      const at = timeOfDay(new Date());
      setConnection(again ? `live · reconnected at ${at}` : "live", "good");
      if (again) {
        notice("");
      }
      lostAt = null;
      render();
      refreshSteps();
      refreshTraffic();
    } else if (message.method === "notify_status_update" && state.snapshot) {
      applyUpdate(state.snapshot, message.params);
      renderSoon();
    }
  });
  ws.addEventListener("close", () => {
    state.connected = false;
    lost(subscribed ? "the controller went away" : "the controller refused the live connection");
  });
}

function lost(why) {
  if (wasRefused) {
    return;
  }
  if (lostAt === null) {
    lostAt = Date.now();
  }
  const since = timeOfDay(new Date(lostAt));
  setConnection(`offline since ${since}: reconnecting…`, "bad");
  notice(`${why}: reconnecting by itself (the view shows what was last known).`);
  setTimeout(connect, retryMs);
  retryMs = Math.min(RETRY_MAX_MS, retryMs * 2);
}

async function loadLayout() {
  state.layout = await call("cell.layout");
  state.previews = {};
  byId("cell-name").textContent = state.layout.name;
  document.title = `${state.layout.name} · cellctl`;
  drawFloor(byId("floor-plan"), state.layout);
  fillSelect(byId("order-type"), Object.keys(state.layout.part_types));
  fillSelect(byId("traffic-machine"), state.layout.machines.map((m) => m.name));
}

// -- the order form and toolbars -------------------------------------------------------------

function wire() {
  const form = byId("order-form");
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    const out = byId("order-message");
    out.className = "message";
    const params = {
      part_type: byId("order-type").value,
      qty: Number(byId("order-qty").value),
      priority: Number(byId("order-priority").value || 0),
    };
    // Optional; sent as typed (FRI 18:00): the cell reads it on its own clock, as for
    // `cellctl submit --due`.
    const due = byId("order-due");
    if (due.value.trim()) {
      params.due = due.value.trim();
    }
    try {
      const result = await call(form.dataset.method, params);
      out.textContent = result.message;
      out.classList.add("ok");
      await refresh();
    } catch (e) {
      out.textContent = e.message;
      out.classList.add("error");
      // A refused due time: its field selected (kept as typed), so the next keys replace it.
      if (/\bdue: /.test(e.message)) {
        due.focus();
        due.select();
      }
    }
  });
  byId("gantt-window").addEventListener("change", refreshSteps);
  byId("gantt-svg").addEventListener("click", () => exportGantt(byId("gantt-chart"), "svg"));
  byId("gantt-png").addEventListener("click", () => exportGantt(byId("gantt-chart"), "png"));
  byId("traffic-machine").addEventListener("change", refreshTraffic);
  wireCellControls();
}

function start() {
  wire();
  if (!token) {
    refused("No API token: this page was opened without one.");
    return;
  }
  connect();
  // Read only while the page is shown (whileShown): a hidden dashboard asks the cell nothing.
  whileShown(2000, refreshSteps);
  whileShown(1000, refreshTraffic);
  // Figures that move with the clock alone come with the next change; read them now and
  // then (docs/api.md: "Updates").
  whileShown(5000, () => state.connected && refresh());
  whileShown(3000, () => state.connected && refreshAudit());
}

start();
