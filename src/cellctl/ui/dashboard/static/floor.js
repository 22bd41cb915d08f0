// The cell floor: an SVG plan from cell.layout (conveyor, robot, each mill with its door and
// vise), machines coloured by state, every part drawn where the journal says it is.
const NS = "http://www.w3.org/2000/svg";
const WIDTH = 800;
const HEIGHT = 430;
const CONVEYOR = { x: 20, y: 350, w: 430, h: 46 };
const OUT = { x: 560, y: 340, w: 220, h: 66 };
const ROBOT = { x: 400, y: 250, r: 46 };

// What each machine condition is called on the page (the status' `condition` field).
export const CONDITION_LABELS = {
  offline: "offline",
  "not-ready": "not ready",
  idle: "idle",
  busy: "busy",
  alarm: "alarm",
  "out-of-service": "out of service",
};
const CONDITION_CLASSES = Object.keys(CONDITION_LABELS).map((c) => `state-${c}`);

// A machine's condition, as the status says it (a machine not in the status: offline).
export function machineCondition(machine) {
  return machine && machine.condition in CONDITION_LABELS ? machine.condition : "offline";
}

// The places a robot transfer goes between: the part's route in the layout names them
// (conveyor, the route's mills, conveyor), and the transfer program is one leg of it.
export function transferPlaces(layout, snap, step) {
  if (!step || step.what !== "transfer" || !step.program) {
    return [];
  }
  const part = (snap.parts || []).find((p) => p.id === step.part_id);
  const types = part && layout.part_types[part.part_type]
    ? [layout.part_types[part.part_type]] : Object.values(layout.part_types);
  for (const type of types) {
    const leg = type.transfers.indexOf(step.program);
    if (leg >= 0) {
      const stops = ["conveyor", ...type.route.map((r) => r.mill), "conveyor"];
      return [stops[leg], stops[leg + 1]];
    }
  }
  return [];
}

// A machine's step for the eye (its fields: what, program, part), else its state's words.
export function stepText(machine) {
  const step = machine.step;
  if (!step) {
    return machine.state;
  }
  return [step.what, step.program, step.part_id].filter((x) => x).join(" ");
}

function el(name, attrs = {}, parent = null) {
  const node = document.createElementNS(NS, name);
  for (const [key, value] of Object.entries(attrs)) {
    node.setAttribute(key, String(value));
  }
  if (parent) {
    parent.appendChild(node);
  }
  return node;
}

function text(parent, x, y, content, cls = "label") {
  const node = el("text", { x, y, class: cls }, parent);
  node.textContent = content;
  return node;
}

// Where each mill stands, its door and its vise.
function millBoxes(layout) {
  const n = Math.max(layout.mills.length, 1);
  const span = (WIDTH - 60) / n;
  const w = Math.min(260, span - 30);
  return layout.mills.map((name, i) => {
    const x = 30 + i * span + (span - w) / 2;
    return { name, x, y: 24, w, h: 160, vise: { x: x + w / 2, y: 24 + 100 } };
  });
}

export function drawFloor(container, layout) {
  const svg = el("svg", {
    viewBox: `0 0 ${WIDTH} ${HEIGHT}`,
    class: "floor",
    role: "img",
    "aria-label": `plan of ${layout.name}`,
  });
  const places = {};
  for (const box of millBoxes(layout)) {
    const g = el("g", { class: "machine mill state-offline", "data-machine": box.name }, svg);
    el("rect", { x: box.x, y: box.y, width: box.w, height: box.h, rx: 8, class: "body" }, g);
    text(g, box.x + 10, box.y + 22, box.name, "label name");
    text(g, box.x + 10, box.y + 40, "", "label small status");
    // The program on a line of its own: a long name stays inside the mill's box.
    text(g, box.x + 10, box.y + 56, "", "label small status-program");
    el("rect", {
      x: box.vise.x - 40, y: box.vise.y - 6, width: 80, height: 24, rx: 3, class: "vise",
    }, g);
    text(g, box.vise.x + 46, box.vise.y + 12, "vise", "label small");
    el("rect", {
      x: box.x + box.w / 2 - 50, y: box.y + box.h - 5, width: 100, height: 10, class: "door",
    }, g);
    text(g, box.x + box.w / 2 + 56, box.y + box.h + 5, "door", "label small door-label");
    places[box.name] = { x: box.vise.x, y: box.vise.y + 2, dx: 22 };
  }

  if (layout.robot) {  // a DNC shop's machines have none
    const robot = el("g", { class: "machine robot state-offline", "data-machine": layout.robot },
      svg);
    el("circle", { cx: ROBOT.x, cy: ROBOT.y, r: ROBOT.r, class: "body" }, robot);
    el("line", {
      x1: ROBOT.x, y1: ROBOT.y, x2: ROBOT.x + 70, y2: ROBOT.y - 30, class: "arm",
    }, robot);
    text(robot, ROBOT.x - ROBOT.r - 8, ROBOT.y - ROBOT.r - 6, layout.robot, "label name");
    text(robot, ROBOT.x - 60, ROBOT.y + ROBOT.r + 18, "", "label small status");
    places[layout.robot] = { x: ROBOT.x + 70, y: ROBOT.y - 30, dx: 22 };
  }

  const conveyor = el("g", { class: "conveyor" }, svg);
  el("rect", { ...rect(CONVEYOR), rx: 6, class: "belt" }, conveyor);
  for (let x = CONVEYOR.x + 20; x < CONVEYOR.x + CONVEYOR.w; x += 40) {
    el("line", { x1: x, y1: CONVEYOR.y + 4, x2: x, y2: CONVEYOR.y + CONVEYOR.h - 4, class: "slat" },
      conveyor);
  }
  text(conveyor, CONVEYOR.x, CONVEYOR.y - 8, "conveyor", "label name");
  places.conveyor = { x: CONVEYOR.x + CONVEYOR.w - 24, y: CONVEYOR.y + CONVEYOR.h / 2, dx: -28 };

  const out = el("g", { class: "outfeed" }, svg);
  el("rect", { ...rect(OUT), rx: 6, class: "tray" }, out);
  text(out, OUT.x, OUT.y - 8, "out", "label name");
  text(out, OUT.x + 14, OUT.y + 40, "", "label done-count");
  places.out = { x: OUT.x + 24, y: OUT.y + OUT.h / 2, dx: 26 };

  el("g", { class: "parts" }, svg);
  svg.dataset.places = JSON.stringify(places);
  container.replaceChildren(svg);
}

function rect(r) {
  return { x: r.x, y: r.y, width: r.w, height: r.h };
}

export function updateFloor(layout, snap) {
  const svg = document.querySelector("#floor-plan svg");
  if (!svg) {
    return;
  }
  const places = JSON.parse(svg.dataset.places);
  const robot = snap.machines[layout.robot];
  const open = transferPlaces(layout, snap, robot && robot.step);
  for (const g of svg.querySelectorAll(".machine")) {
    const name = g.dataset.machine;
    const machine = snap.machines[name];
    const condition = machineCondition(machine);
    g.classList.remove(...CONDITION_CLASSES);
    g.classList.add(`state-${condition}`);
    g.dataset.condition = condition;
    const status = g.querySelector(".status");
    const program = g.querySelector(".status-program");
    status.textContent = machine ? `${CONDITION_LABELS[condition]} · ${stepText(machine)}` : "";
    if (program) {
      const step = machine && machine.step;
      program.textContent = step && step.program ? step.program : "";
      if (step) {
        status.textContent = `${CONDITION_LABELS[condition]} · ` +
          [step.what, step.part_id].filter((x) => x).join(" ");
      }
    }
    if (g.classList.contains("mill")) {
      // The robot's transfer reaches into the mills at its two ends: their doors are open.
      g.classList.toggle("door-open", open.includes(name));
      g.classList.toggle("clamped", condition === "busy");
    }
  }
  const done = (snap.orders || []).reduce((n, o) => n + ((o.parts || {}).done || 0), 0);
  svg.querySelector(".done-count").textContent = `${done} part(s) done`;

  const layer = svg.querySelector(".parts");
  const seen = new Set();
  const count = {};
  for (const part of snap.parts || []) {
    const where = places[part.location] ? part.location : "conveyor";
    const slot = count[where] || 0;
    count[where] = slot + 1;
    const place = places[where];
    const x = place.x + slot * place.dx;
    const y = place.y;
    let g = layer.querySelector(`[data-part-id="${CSS.escape(part.id)}"]`);
    if (!g) {
      g = el("g", { class: "part", "data-part-id": part.id }, layer);
      el("circle", { r: 11 }, g);
      const label = el("text", { y: 4, class: "part-label" }, g);
      label.textContent = String(part.seq_in_order);
      el("title", {}, g);
    }
    g.setAttribute("data-location", part.location);
    g.setAttribute("class", `part status-${part.status} type-${typeIndex(layout, part.part_type)}`);
    g.querySelector("title").textContent =
      `${part.id} (${part.part_type}) at ${part.location}: ${part.status} ${part.note || ""}`;
    g.style.transform = `translate(${x}px, ${y}px)`;
    seen.add(part.id);
  }
  for (const g of [...layer.children]) {
    if (!seen.has(g.dataset.partId)) {
      g.remove();
    }
  }
}

function typeIndex(layout, partType) {
  return Math.max(0, Object.keys(layout.part_types).indexOf(partType)) % 6;
}
