// A live Gantt chart of the journal's steps: one row per machine, robot transfers and cuts
// coloured by part type, the waits between them, exportable as SVG and PNG. Colours are SVG
// attributes (not the page's stylesheet) so an exported file looks the same.
import { clockOf } from "./clock.js";

const NS = "http://www.w3.org/2000/svg";
const COLOURS = ["#4e79a7", "#f28e2b", "#59a14f", "#e15759", "#76b7b2", "#edc948"];
const LEFT = 90;
const WIDTH = 1000;
const ROW = 34;
const TOP = 30;

function el(name, attrs, parent) {
  const node = document.createElementNS(NS, name);
  for (const [key, value] of Object.entries(attrs)) {
    node.setAttribute(key, String(value));
  }
  parent.appendChild(node);
  return node;
}

function label(parent, x, y, content, extra = {}) {
  el("text", { x, y, ...extra }, parent).textContent = content;
}

export function renderGantt(container, layout, steps, since) {
  if (!layout) {
    return;
  }
  const now = Date.now() / 1000;
  const machines = [layout.robot, ...layout.mills].filter((m) => m);
  const types = Object.keys(layout.part_types);
  const earliest = steps.reduce((t, s) => Math.min(t, s.started), now - 10);
  const t0 = Math.max(since, earliest - 1);
  const span = Math.max(now - t0, 10);
  const x = (t) => LEFT + ((t - t0) / span) * (WIDTH - LEFT - 50);
  const height = TOP + ROW * machines.length + 60;
  const svg = document.createElementNS(NS, "svg");
  for (const [key, value] of Object.entries({
    xmlns: NS, viewBox: `0 0 ${WIDTH} ${height}`, width: WIDTH, height,
    "font-family": "sans-serif", "font-size": 12, class: "gantt",
  })) {
    svg.setAttribute(key, String(value));
  }
  el("rect", { width: WIDTH, height, fill: "white" }, svg);
  label(svg, LEFT, 18, `${layout.name}: steps since ${clockOf(t0)}`,
    { "font-size": 13 });
  machines.forEach((machine, row) => {
    const y = TOP + row * ROW;
    label(svg, 8, y + 21, machine);
    el("line", { x1: LEFT, y1: y + ROW - 2, x2: WIDTH - 50, y2: y + ROW - 2, stroke: "#ddd" }, svg);
    const mine = steps.filter((s) => s.machine === machine).sort((a, b) => a.started - b.started);
    let free = null;
    for (const s of mine) {
      const end = s.ended ?? now;
      if (free !== null && s.started > free) {
        const wait = el("rect", {
          x: x(free), y: y + 12, width: Math.max(0.5, x(s.started) - x(free)), height: ROW - 24,
          fill: "#e8e8e8", class: "wait",
        }, svg);
        el("title", {}, wait).textContent = `waiting ${(s.started - free).toFixed(1)} s`;
      }
      free = Math.max(free ?? end, end);
      const colour = s.state === "finished" || s.ended === null
        ? COLOURS[Math.max(0, types.indexOf(s.part_type)) % COLOURS.length] : "#999999";
      const bar = el("rect", {
        x: x(s.started), y: y + 4, width: Math.max(1, x(end) - x(s.started)), height: ROW - 10,
        fill: colour, stroke: s.ended === null ? "#000000" : "white",
        "stroke-dasharray": s.ended === null ? "3 2" : "none",
        class: `step ${s.kind}`, "data-step": s.id,
      }, svg);
      el("title", {}, bar).textContent =
        `${s.part_id} ${s.kind} ${s.program} ${(end - s.started).toFixed(1)} s ${s.state}`;
    }
  });
  const axis = TOP + ROW * machines.length + 16;
  for (let i = 0; i <= 10; i += 1) {
    const t = t0 + (span * i) / 10;
    label(svg, x(t), axis, clockOf(t),
      { "text-anchor": "middle", "font-size": 10 });
  }
  types.forEach((type, i) => {
    const lx = LEFT + i * 200;
    el("rect", { x: lx, y: axis + 14, width: 12, height: 12, fill: COLOURS[i % COLOURS.length] },
      svg);
    label(svg, lx + 16, axis + 24, type);
  });
  const lx = LEFT + types.length * 200;
  el("rect", { x: lx, y: axis + 14, width: 12, height: 12, fill: "#e8e8e8" }, svg);
  label(svg, lx + 16, axis + 24, "waiting");
  container.replaceChildren(svg);
}

function download(blob, name) {
  const url = URL.createObjectURL(blob);
  const a = document.createElement("a");
  a.href = url;
  a.download = name;
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

export function exportGantt(container, kind) {
  const svg = container.querySelector("svg");
  if (!svg) {
    return;
  }
  const text = new XMLSerializer().serializeToString(svg);
  const stamp = new Date().toISOString().slice(0, 19).replace(/[:T]/g, "-");
  const blob = new Blob([text], { type: "image/svg+xml" });
  if (kind === "svg") {
    download(blob, `gantt-${stamp}.svg`);
    return;
  }
  const url = URL.createObjectURL(blob);
  const image = new Image();
  image.addEventListener("load", () => {
    const canvas = document.createElement("canvas");
    canvas.width = Number(svg.getAttribute("width"));
    canvas.height = Number(svg.getAttribute("height"));
    canvas.getContext("2d").drawImage(image, 0, 0);
    URL.revokeObjectURL(url);
    canvas.toBlob((png) => download(png, `gantt-${stamp}.png`), "image/png");
  });
  image.src = url;
}
