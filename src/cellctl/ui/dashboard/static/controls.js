// One set of controls: the cell's pause, resume and emergency stop in the header, each
// machine's out of / back in automatic service on its card (the CLI's and the console's
// actions, the API's methods).
//
// A control declares its API method once, as data-method (tests/test_cli_scripting.py reads
// them from the shipped files); data-confirm asks first (an action that stops work; {machine}
// names the card's machine), data-reason asks why (data-reason-required: no empty reason).
// The API's answer, or its refusal in its own words, is shown beside the control.
import { call, confirmAction, refresh } from "./app.js";

function byId(id) {
  return document.getElementById(id);
}

// The confirmation dialog, with a reason field when `prompt` is given: the reason typed
// (possibly ""), or null when cancelled.
export function confirmWithReason(text, prompt, required) {
  const label = byId("confirm-reason-label");
  const input = byId("confirm-reason");
  label.classList.toggle("hidden", !prompt);
  byId("confirm-reason-prompt").textContent = prompt || "";
  input.value = "";
  input.required = Boolean(prompt && required);
  const asked = confirmAction(text);
  if (prompt) {
    input.focus();
  }
  return asked.then((ok) => {
    input.required = false;
    return ok ? (prompt ? input.value.trim() : "") : null;
  });
}

// Run the control `button`: confirm (and ask why) as it declares, call its method with
// `params` (+ the reason), show the answer in `out`.
export async function runControl(button, params, out) {
  const method = button.dataset.method;
  const machine = params.machine || "";
  const question = button.dataset.confirm ? button.dataset.confirm.replace("{machine}", machine)
    : null;
  const prompt = button.dataset.reason || null;
  const required = button.hasAttribute("data-reason-required");
  let reason = "";
  if (question !== null || prompt !== null) {
    const answered = await confirmWithReason(question || `${button.textContent}?`, prompt, required);
    if (answered === null) {
      return;
    }
    reason = answered;
  }
  out.className = out.className.replace(/\b(ok|error)\b/g, "").trim();
  out.textContent = "…";
  try {
    const result = await call(method, prompt ? { ...params, reason } : params);
    out.textContent = (result && result.message) || "done";
    out.classList.add("ok");
  } catch (e) {
    out.textContent = e.message;
    out.classList.add("error");
  }
  await refresh();
}

// -- the cell's controls (header) -----------------------------------------------------------

export function wireCellControls() {
  for (const button of document.querySelectorAll("#cell-controls button[data-method]")) {
    button.addEventListener("click", () => runControl(button, {}, byId("control-message")));
  }
}

// Which of pause and resume applies in the cell's mode (both stay in place: no jump).
export function renderCellControls(snap) {
  const mode = snap.cell.mode;
  const box = byId("cell-controls");
  box.classList.remove("hidden");
  const pause = box.querySelector('[data-method="cell.pause"]');
  const resume = box.querySelector('[data-method="cell.resume"]');
  const estop = box.querySelector('[data-method="cell.estop"]');
  pause.disabled = mode !== "running";
  // After an emergency stop the cell stays stopped until its alarm is cleared (the
  // controller's rule): then it is paused, and Resume starts it again.
  resume.disabled = mode !== "paused";
  resume.title = mode === "emergency-stop" ? "clear the emergency stop's alarm first" : "";
  estop.disabled = mode === "no-controller";
}

export function hideCellControls() {
  byId("cell-controls").classList.add("hidden");
}

// -- a machine's service controls (its card) ------------------------------------------------

export function renderServiceControls(card, machine) {
  let box = card.querySelector(".service-controls");
  if (!box) {
    box = byId("service-controls").content.firstElementChild.cloneNode(true);
    const out = box.querySelector(".control-message");
    for (const button of box.querySelectorAll("button[data-method]")) {
      button.addEventListener("click",
        () => runControl(button, { machine: card.dataset.machine }, out));
    }
    card.append(box);
  }
  box.querySelector('[data-method="machines.out_of_service"]')
    .classList.toggle("hidden", !machine.in_service);
  box.querySelector('[data-method="machines.return_to_service"]')
    .classList.toggle("hidden", machine.in_service);
}
