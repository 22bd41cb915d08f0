"""A route's robot program for a UR, as the cell holds it: no I/O.

Two forms, by the file ``[robot_programs]`` names:

- ``NAME.script`` (URScript kept in the cell): one top-level ``def NAME(): ... end``; the
  driver sends it on the secondary interface, with one line added before its ``end`` that
  sets the end register (``write_output_integer_register(24, SEQ)``), so RTDE shows its end
  even when it is too short for a package to see it play;
- ``NAME.urp`` (a program on the robot): a one-line text file in the cell whose line is the
  program's path on the robot (``/programs/tend_cnc1.urp``; empty: ``NAME.urp``), run by
  ``load`` and ``play``.

::

    program = compile_program(text, "tend_cnc1", "robot/tend_cnc1.script")
    program.problems(ARMS["UR5e"])      # [] or "file:line:col: ..." each
    program.sendable(24, 7)             # the text that goes on the wire
"""

from __future__ import annotations

import dataclasses
import html
from dataclasses import dataclass

from cellctl.errors import UsageError
from cellctl.kinds.ur.motion import ARMS, Arm
from cellctl.kinds.ur.urscript import check, estimate, parse

#: The arm the cell's config checks a program against before it knows the robot's model:
#: the longest reach, said as such (the driver checks again against its own model before
#: sending, and `cellctl program check` against the configured one).
WIDEST = max(ARMS.values(), key=lambda arm: arm.reach)
ANY_UR = dataclasses.replace(
    WIDEST, name=f"UR of any model (the longest reach is a {WIDEST.name}'s)"
)


def entry_problems(text: str, name: str, origin: str) -> list[str]:
    """What keeps a script from being a program the driver can run: it sends the file whole
    on the secondary interface, and the robot runs one top-level ``def``."""
    statements = parse(text).statements
    form = (
        f"a UR script is one 'def {name}(): ... end' holding the program's statements "
        "(the robot runs that def when the driver sends the file)"
    )
    if not statements:
        return [f"{origin}: empty: {form}"]
    if not any(st.keyword == "def" for st in statements):
        first = statements[0]
        return [f"{origin}:{first.line}:{first.column}: not inside a 'def': {form}"]
    return []


@dataclass(frozen=True)
class UrProgram:
    """One robot program (see module docstring)."""

    name: str
    origin: str
    text: str = ""
    path: str = ""
    """The program's path on the robot (``.urp``); empty for a script."""

    @property
    def on_robot(self) -> bool:
        return bool(self.path)

    def problems(self, arm: Arm) -> list[str]:
        """What would fail on the robot (none for a ``.urp``: the robot holds it)."""
        if self.on_robot:
            return []
        return entry_problems(self.text, self.name, self.origin) + check(
            self.text, arm, self.origin
        )

    def sendable(self, end_register: int | None, seq: int) -> str:
        """The script as sent: the end register set just before its entry's ``end``."""
        if end_register is None:
            return self.text if self.text.endswith("\n") else self.text + "\n"
        program = parse(self.text)
        entry = program.entry
        lines = self.text.splitlines()
        if entry is None:
            body = "\n".join("  " + line for line in lines)
            return (
                f"def {self.name}():\n{body}\n"
                f"  write_output_integer_register({end_register}, {seq})\nend\n"
            )
        end_line = _end_of(lines, entry.line)
        indent = " " * (entry.column + 1)
        lines.insert(end_line - 1, f"{indent}write_output_integer_register({end_register}, {seq})")
        return "\n".join(lines) + "\n"


def _end_of(lines: list[str], start: int) -> int:
    """The 1-based line of the ``end`` closing the block opened on line ``start``."""
    depth = 0
    for number in range(start, len(lines) + 1):
        body = lines[number - 1].split("#", 1)[0].strip()
        if body.startswith(("def ", "while ", "if ", "thread ")):
            depth += 1
        elif body == "end":
            depth -= 1
            if depth == 0:
                return number
    raise UsageError(f"line {start}: its block has no 'end'")


def compile_program(source: str, name: str, origin: str, arm: Arm | None = None) -> UrProgram:
    """The cell's program ``name`` from its file's text; UsageError listing its problems on
    ``arm`` (None: any UR's, the robot's model not known yet)."""
    if origin.endswith(".urp"):
        path = next(
            (ln.strip() for ln in source.splitlines() if ln.strip() and not ln.startswith("#")),
            f"{name}.urp",
        )
        if not path.endswith(".urp") or any(c in path for c in "\n\r"):
            raise UsageError(f"{origin}: names {path!r}, not a .urp program on the robot")
        return UrProgram(name, origin, path=path)
    program = UrProgram(name, origin, text=source)
    problems = program.problems(arm or ANY_UR)
    if problems:
        raise UsageError("; ".join(problems))
    return program


def preview_svg(text: str, name: str, arm: Arm) -> tuple[str, int]:
    """The tool's path seen from above (x, y), with the arm's reach, as SVG; and how many
    moves it makes."""
    _, moves = estimate(parse(text), arm)
    points = [arm.position(moves[0].start)] if moves else []
    points += [arm.position(m.end) for m in moves]
    size, scale = 400, 400 / (2.2 * arm.reach)

    def xy(p: tuple[float, float, float]) -> str:
        return f"{size / 2 + p[0] * scale:.1f},{size / 2 - p[1] * scale:.1f}"

    path = " ".join(xy(p) for p in points)
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {size} {size}" '
        f'width="{size}" height="{size}">',
        f"<title>{html.escape(name)}: {len(moves)} moves, {arm.name} seen from above</title>",
        f'<circle cx="{size / 2}" cy="{size / 2}" r="{arm.reach * scale:.1f}" fill="none" '
        'stroke="#999" stroke-dasharray="4 4"/>',
        f'<circle cx="{size / 2}" cy="{size / 2}" r="4" fill="#333"/>',
    ]
    if points:
        parts.append(f'<polyline points="{path}" fill="none" stroke="#06c" stroke-width="2"/>')
        for p in points:
            parts.append(f'<circle cx="{xy(p).split(",")[0]}" cy="{xy(p).split(",")[1]}" '
                         'r="3" fill="#06c"/>')  # fmt: skip
    parts.append("</svg>")
    return "\n".join(parts), len(moves)
