"""Draw a DYNALAN toolpath: an XY view and a Z profile, block boundaries marked.

Usage::

    svg_text = render_svg(result.toolpath, title="BASE.DYN")
    png_bytes = render_png(result.toolpath, title="BASE.DYN")

Feed moves are drawn solid in their block's colour, rapid moves dashed grey; each block's start
is a numbered marker in the XY view and a vertical line in the Z profile (Z against the
distance travelled). Pure: returns text or bytes, writes nothing.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from xml.sax.saxutils import escape

from PIL import Image, ImageDraw

from cellctl.kinds.dyna2400.dynalan.machine import MoveKind
from cellctl.kinds.dyna2400.dynalan.toolpath import Toolpath

WIDTH = 960
XY_HEIGHT = 600
PROFILE_HEIGHT = 220
MARGIN = 50
BLOCK_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf")
RAPID_COLOUR = "#9a9a9a"


@dataclass(frozen=True)
class _Segment:
    kind: MoveKind
    block: int
    points: tuple[tuple[float, float], ...]  # XY view, pixels
    profile: tuple[tuple[float, float], ...]  # Z profile, pixels


def _layout(path: Toolpath) -> tuple[list[_Segment], list[tuple[int, float, float, float]]]:
    """Segments in pixels, and block starts as (block, x, y, profile x)."""
    low, high = path.bounds()
    span_x = max(high[0] - low[0], 1e-6)
    span_y = max(high[1] - low[1], 1e-6)
    scale = min((WIDTH - 2 * MARGIN) / span_x, (XY_HEIGHT - 2 * MARGIN) / span_y)
    top = MARGIN + 20

    def xy(x: float, y: float) -> tuple[float, float]:
        return MARGIN + (x - low[0]) * scale, top + (high[1] - y) * scale

    total = sum(tm.move.length for tm in path.moves) or 1.0
    span_z = max(high[2] - low[2], 1e-6)
    p_top = top + (span_y * scale) + 60
    p_height = PROFILE_HEIGHT - 60

    def prof(distance: float, z: float) -> tuple[float, float]:
        return (
            MARGIN + distance / total * (WIDTH - 2 * MARGIN),
            p_top + (high[2] - z) / span_z * p_height,
        )

    segments: list[_Segment] = []
    starts: list[tuple[int, float, float, float]] = []
    distance = 0.0
    block = 0
    run: tuple[MoveKind, int] | None = None  # the (kind, block) the open polylines draw
    pts: list[tuple[float, float]] = []
    profile: list[tuple[float, float]] = []

    def close() -> None:
        if run is not None:
            segments.append(_Segment(run[0], run[1], _drawn(pts), _drawn(profile)))

    for tm in path.moves:
        move = tm.move
        if tm.block != block:
            block = tm.block
            sx, sy = xy(move.start[0], move.start[1])
            starts.append((block, sx, sy, prof(distance, 0.0)[0]))
        if move.kind is MoveKind.DWELL:
            continue
        first = xy(move.path[0][0], move.path[0][1])
        if run != (move.kind, tm.block) or not pts or _apart(pts[-1], first):
            # One polyline per run of moves of a kind in a block, end to end: a program of
            # 100,000 short moves is a drawing of a few elements, not 100,000.
            close()
            run, pts, profile = (move.kind, tm.block), [first], [prof(distance, move.path[0][2])]
        pts.extend(xy(p[0], p[1]) for p in move.path[1:])
        for a, b in zip(move.path, move.path[1:], strict=False):
            distance += ((b[0] - a[0]) ** 2 + (b[1] - a[1]) ** 2 + (b[2] - a[2]) ** 2) ** 0.5
            profile.append(prof(distance, b[2]))
    close()
    return segments, starts


#: Pixels: a point closer than this to the last one drawn adds nothing to the drawing.
_PIXEL = 0.5


def _apart(a: tuple[float, float], b: tuple[float, float]) -> bool:
    return abs(a[0] - b[0]) > _PIXEL or abs(a[1] - b[1]) > _PIXEL


def _drawn(points: list[tuple[float, float]]) -> tuple[tuple[float, float], ...]:
    """``points`` as drawn: each one at least a half pixel from the last kept, and the last."""
    kept = [points[0]]
    for point in points[1:]:
        if _apart(kept[-1], point):
            kept.append(point)
    if len(points) > 1 and kept[-1] is not points[-1]:
        kept.append(points[-1])
    return tuple(kept)


def _height(path: Toolpath) -> int:
    low, high = path.bounds()
    span_x = max(high[0] - low[0], 1e-6)
    span_y = max(high[1] - low[1], 1e-6)
    scale = min((WIDTH - 2 * MARGIN) / span_x, (XY_HEIGHT - 2 * MARGIN) / span_y)
    return int(MARGIN + 20 + span_y * scale + 60 + PROFILE_HEIGHT)


def _caption(path: Toolpath, title: str) -> str:
    minutes = path.machining_seconds / 60
    unit = path.units.length_name
    return (
        f"{title}  {path.blocks} block(s)  {len(path.moves)} moves  "
        f"est. {minutes:.1f} min  units {unit}"
    )


def render_svg(path: Toolpath, title: str = "program") -> str:
    """The toolpath as an SVG document (text)."""
    segments, starts = _layout(path)
    height = _height(path)
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{height}" '
        f'viewBox="0 0 {WIDTH} {height}" font-family="sans-serif" font-size="12">',
        f'<rect width="{WIDTH}" height="{height}" fill="white"/>',
        f'<text x="{MARGIN}" y="24" font-size="14">{escape(_caption(path, title))}</text>',
        f'<text x="{MARGIN}" y="{MARGIN + 12}">XY view</text>',
    ]
    for seg in segments:
        colour = (
            RAPID_COLOUR
            if seg.kind is MoveKind.RAPID
            else BLOCK_COLOURS[(seg.block - 1) % len(BLOCK_COLOURS)]
        )
        dash = ' stroke-dasharray="4 3"' if seg.kind is MoveKind.RAPID else ""
        for pts, cls in ((seg.points, "xy"), (seg.profile, "z")):
            coords = " ".join(f"{x:.1f},{y:.1f}" for x, y in pts)
            out.append(
                f'<polyline class="{cls} {seg.kind.value}" points="{coords}" fill="none" '
                f'stroke="{colour}" stroke-width="1"{dash}/>'
            )
    profile_top = height - PROFILE_HEIGHT
    out.append(f'<text x="{MARGIN}" y="{profile_top - 8}">Z profile (along the path)</text>')
    for block, x, y, px in starts:
        out.append(
            f'<g class="block-start" data-block="{block}"><circle cx="{x:.1f}" cy="{y:.1f}" '
            f'r="4" fill="black"/><text x="{x + 6:.1f}" y="{y - 6:.1f}">block {block}</text>'
            f'<line x1="{px:.1f}" y1="{profile_top}" x2="{px:.1f}" y2="{height - 10}" '
            f'stroke="black" stroke-dasharray="2 2"/></g>'
        )
    out.append("</svg>")
    return "\n".join(out) + "\n"


def render_png(path: Toolpath, title: str = "program") -> bytes:
    """The toolpath as a PNG image (bytes), the same drawing as :func:`render_svg`."""
    segments, starts = _layout(path)
    height = _height(path)
    image = Image.new("RGB", (WIDTH, height), "white")
    draw = ImageDraw.Draw(image)
    draw.text((MARGIN, 10), _caption(path, title), fill="black")
    draw.text((MARGIN, MARGIN), "XY view", fill="black")
    for seg in segments:
        colour = (
            RAPID_COLOUR
            if seg.kind is MoveKind.RAPID
            else BLOCK_COLOURS[(seg.block - 1) % len(BLOCK_COLOURS)]
        )
        for pts in (seg.points, seg.profile):
            if len(pts) >= 2:
                draw.line(list(pts), fill=colour, width=1)
    profile_top = height - PROFILE_HEIGHT
    draw.text((MARGIN, profile_top - 18), "Z profile (along the path)", fill="black")
    for block, x, y, px in starts:
        draw.ellipse((x - 4, y - 4, x + 4, y + 4), fill="black")
        draw.text((x + 6, y - 16), f"block {block}", fill="black")
        draw.line([(px, profile_top), (px, height - 10)], fill="black", width=1)
    buffer = io.BytesIO()
    image.save(buffer, format="PNG")
    return buffer.getvalue()
