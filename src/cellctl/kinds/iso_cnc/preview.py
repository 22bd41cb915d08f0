"""A G-code program's toolpath as SVG (the kind's preview hook), from the motion model's
steps: rapids dashed, feeds solid, seen from above (X right, Y up)::

    svg, blocks = render_svg(motion.steps(gcode.blocks(text)), title="O1234")

A program of millions of blocks is drawn from at most :data:`MAX_POINTS` points (evenly
thinned), so the picture stays small whatever the program.
"""

from __future__ import annotations

from collections.abc import Sequence
from xml.sax.saxutils import escape

from cellctl.kinds.iso_cnc.motion import Point, Step

MAX_POINTS = 20000
_SIZE = 480.0
_PAD = 12.0


def render_svg(steps: Sequence[Step], title: str = "") -> str:
    """The path of ``steps`` as an SVG document."""
    paths: list[tuple[str, list[Point]]] = []
    total = sum(len(s.points) for s in steps if s.kind in ("rapid", "feed"))
    every = max(1, total // MAX_POINTS)
    count = 0
    for s in steps:
        if s.kind not in ("rapid", "feed") or not s.points:
            continue
        if not paths or paths[-1][0] != s.kind:
            paths.append((s.kind, [s.start]))
        for p in s.points:
            count += 1
            if count % every == 0 or p is s.points[-1]:
                paths[-1][1].append(p)
    xs = [p[0] for _, pts in paths for p in pts] or [0.0]
    ys = [p[1] for _, pts in paths for p in pts] or [0.0]
    x0, x1, y0, y1 = min(xs), max(xs), min(ys), max(ys)
    span = max(x1 - x0, y1 - y0, 1e-6)
    k = (_SIZE - 2 * _PAD) / span

    def xy(p: Point) -> str:
        return f"{_PAD + (p[0] - x0) * k:.2f},{_SIZE - _PAD - (p[1] - y0) * k:.2f}"

    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {_SIZE:g} {_SIZE:g}" '
        f'width="{_SIZE:g}" height="{_SIZE:g}">',
        f"<title>{escape(title)}</title>",
        f'<rect width="{_SIZE:g}" height="{_SIZE:g}" fill="white"/>',
    ]
    for kind, pts in paths:
        style = 'stroke="#c33" stroke-dasharray="4 3"' if kind == "rapid" else 'stroke="#137"'
        out.append(
            f'<polyline class="{kind}" fill="none" {style} stroke-width="1" '
            f'points="{" ".join(xy(p) for p in pts)}"/>'
        )
    out.append("</svg>")
    return "\n".join(out) + "\n"
