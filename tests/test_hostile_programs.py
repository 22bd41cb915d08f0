"""Hostile DYNALAN programs: validation and preview answer within bounded CPU time and memory,
with a typed problem at the right line; the mill emulator stops on them instead of crashing.

Each program is checked in a subprocess whose address space and CPU time are limited
(``tests.conftest.run_limited``), so a program that would make the checker grow or run
without bound fails its test instead of the machine.
The inputs that found bugs are kept here as plain tests.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import re
import textwrap
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from cellctl.emulators.serve import Server, serve
from cellctl.kinds.dyna2400 import dynalan
from cellctl.kinds.dyna2400.emulator import Dyna2400Emulator, OperatorDelays
from cellctl.kinds.dyna2400.preview import render_png, render_svg
from cellctl.link import LineSettings, Link, open_link
from tests.conftest import LIMITED_WALL_S, run_limited

_CHECK = textwrap.dedent(
    """
    import json, sys
    from cellctl.kinds.dyna2400 import dynalan
    from cellctl.kinds.dyna2400.preview import render_png, render_svg
    text = open(sys.argv[1], "rb").read().decode("ascii", "replace")
    result = dynalan.validate(dynalan.parse_program(text, name="hostile"))
    drawn = 0
    if result.toolpath is not None:
        drawn = len(render_svg(result.toolpath)) + len(render_png(result.toolpath))
    errors = [(p.row, p.column, p.code, p.message) for p in result.errors]
    print(json.dumps({"errors": errors[:20], "count": len(errors), "drawn": drawn}))
    """
)


def check_in_subprocess(tmp_path: Path, data: bytes | str) -> dict[str, object]:
    """Validate and preview ``data`` in a memory-limited subprocess; its summary."""
    path = tmp_path / "hostile.dyn"
    if isinstance(data, str):
        data = data.encode("ascii")
    path.write_bytes(data)
    summary: dict[str, object] = json.loads(run_limited(_CHECK, str(path)))
    return summary


def program(*rows: str) -> str:
    return "\n".join(rows) + "\n"


def first_error(summary: dict[str, object]) -> tuple[int, int, str, str]:
    errors = summary["errors"]
    assert isinstance(errors, list) and errors, summary
    row, column, code, message = errors[0]
    return row, column, code, message


def errors_of(text: str) -> list[dynalan.Problem]:
    return dynalan.validate(dynalan.parse_program(text)).errors


# -- the defects of the issue, each a plain test -------------------------------------------------


def test_pass_depth_of_1e7_is_refused_with_the_pass_count(tmp_path: Path) -> None:
    # Grew past 7 GB in a minute before passes were counted.
    text = program(
        "000 START INS 01",
        "001 GO Z -.100",
        "002 CPOCKET R= .750 ZD= -.800 DP= 0.0000001",
        "003 SKIP TO 900",
        "900",
    )
    row, column, code, message = first_error(check_in_subprocess(tmp_path, text))
    assert (row, column, code) == (3, 5, "cycle")
    assert message == "pass depth 1e-07 gives 7,000,000 passes; at most 100,000"


def test_zero_feed_is_an_error_not_a_division_by_zero() -> None:
    # FR XYZ = 0 then a GR move ended in ZeroDivisionError.
    text = program("000 START INS 01", "001 FR XYZ = 0", "002 GR X 1.0", "003 SKIP TO 900", "900")
    errors = errors_of(text)
    assert [(p.row, p.column, p.code) for p in errors] == [(2, 14, "feed-range")]


def test_zero_feed_from_the_machine_state_is_a_fault_at_the_move() -> None:
    state = dynalan.MachineState.initial(dynalan.Units.INS)
    state.feed["X"] = 0.0
    result = dynalan.validate(
        dynalan.parse_program(program("000 GR X 1.0", "001 SKIP TO 900", "900")),
        dynalan.ValidationContext(initial=state),
    )
    assert [(p.row, p.code) for p in result.errors] == [(1, "feed")]
    assert "feed rate 0 for X" in result.errors[0].message


@pytest.mark.parametrize(
    ("row", "code", "fragment"),
    [
        ("002 CPOCKET R= .750 ZD= -.800 DP= 0", "cycle", "DP= (depth a pass) must be above 0"),
        ("002 CPOCKET R= .750 ZD= -.800 DP= -.1", "cycle", "DP= (depth a pass) must be above 0"),
        ("002 TD = 0", "range", "tool diameter must be above 0"),
        ("002 DWELL -1", "range", "DWELL takes a time of 0 seconds or more"),
        ("002 DRIL PECK= -.1", "range", "PECK= takes 0"),
        ("002 GO X " + "9" * 400, "bad-number", "is too large: at most 1,000,000"),
        ("002 REPEAT " + "9" * 5000, "bad-number", "whole number 9999"),
    ],
)
def test_degenerate_values_are_errors_with_line_and_column(
    row: str, code: str, fragment: str
) -> None:
    text = program("000 START INS 01", "001 GO Z -.100", row, "003 SKIP TO 900", "900")
    errors = errors_of(text)
    assert errors, text
    assert errors[0].row == 3 and errors[0].column > 4
    assert errors[0].code == code and fragment in errors[0].message


def test_tiny_tool_is_refused_by_the_points_it_would_make() -> None:
    text = program(
        "000 START INS 01",
        "001 GO Z -.100",
        "002 TD = .0001",
        "003 CPOCKET R= .750 ZD= -.800 DP= 0.01",
        "004 SKIP TO 900",
        "900",
    )
    (error,) = errors_of(text)
    assert (error.row, error.code) == (4, "cycle")
    assert "points of motion; at most 200,000" in error.message


def test_tiny_peck_is_refused_by_the_pecks_it_would_make() -> None:
    text = program(
        "000 START INS 01",
        "001 DRIL PECK= .0000001",
        "002 ZH= 0",
        "003 ZD= -3.9",
        "004   X 1 Y 1",
        "005 SKIP TO 900",
        "900",
    )
    (error,) = errors_of(text)
    assert (error.row, error.code) == (5, "cycle")
    assert error.message == "peck 1e-07 gives 39,000,000 pecks; at most 100,000"


# -- hostile programs under the memory limit -----------------------------------------------------


def _nested_repeats(depth: int, body: list[str]) -> str:
    rows = ["000 START INS 01", "001 GO Z -.100"]
    rows += ["REPEAT 99"] * depth + body + ["REPEAT END"] * depth + ["SKIP TO 900"]
    numbered = rows[:2] + [f"{i:03d} {r}" for i, r in enumerate(rows[2:], start=2)]
    return program(*numbered, "900")


HOSTILE = {
    "repeat-6-deep": (_nested_repeats(6, ["GR X .001", "GR X -.001"]), "size"),
    "repeat-around-a-pocket": (
        _nested_repeats(2, ["CPOCKET R= .750 ZD= -.800 DP= 0.01"]),
        "size",
    ),
    "repeat-450-deep": (_nested_repeats(440, ["SPINDLE ON"]), "size"),
    "skip-to-itself": (program("000 SKIP TO 000", "001 SKIP TO 900", "900"), "skip"),
    "long-line-of-digits": ("000 GO X " + "1" * 1_000_000 + "\n", "bad-number"),
    "long-line-of-words": ("000 GO " + "X 1 " * 100_000 + "\n", "axis-words"),
    "long-cycle": ("000 CPOCKET " + "R= 1 " * 100_000 + "\n", "syntax"),
    "long-comment": ("000 ;" + "A" * 1_000_000 + "a\n", "comment"),
    "100k-moves": (
        program(*(f"{i % 1000:03d} GR X {'.001' if i % 2 else '-.001'}" for i in range(100_000))),
        "travel",
    ),
    "150k-repeats-nested": (
        program(
            *(f"{i % 1000:03d} REPEAT 99" for i in range(75_000)),
            *(f"{i % 1000:03d} REPEAT END" for i in range(75_000)),
        ),
        "split",
    ),
    "200k-skips": (program(*(f"{i % 1000:03d} SKIP TO 999" for i in range(200_000))), "skip"),
    "not-ascii": (bytes(range(256)) * 400, "character"),
    "tiny-and-huge": (
        program(
            "000 START MM 01",
            "001 TD = .0000000000000000000000000000001",
            "002 GO X 999999.9999",
            "003 FR XYZ = .0000000000000000000000000000000000000000001",
            "004 GR Y -999999",
            "005 SKIP TO 900",
            "900",
        ),
        None,
    ),
}


@pytest.mark.parametrize("name", list(HOSTILE))
@pytest.mark.timeout(LIMITED_WALL_S + 20)
def test_hostile_program_gets_an_answer(tmp_path: Path, name: str) -> None:
    data, code = HOSTILE[name]
    summary = check_in_subprocess(tmp_path, data)
    count = summary["count"]
    assert isinstance(count, int) and count > 0
    if code is not None:
        codes = {error[2] for error in summary["errors"]}  # type: ignore[attr-defined]
        assert code in codes, summary


def test_a_long_run_of_short_moves_is_drawn_as_a_few_lines() -> None:
    # 3,000 feed moves of a thousandth of an inch in a row, 0.3 px each on the drawing: one
    # polyline per view of what a person can see, its ends where the moves' ends are.
    moves = [f"{(i + 2) % 1000:03d} GR X .001" for i in range(3000)]
    text = program("000 START INS 01", "001 GO X 1 Y 1 Z 0", *moves, "999 END")
    result = dynalan.validate(dynalan.parse_program(text, name="long"))
    assert result.toolpath is not None
    svg = render_svg(result.toolpath)
    feeds = re.findall(r'<polyline class="xy feed" points="([^"]*)"', svg)
    assert feeds, svg[:2000]
    lines = [[float(p.split(",")[0]) for p in line.split()] for line in feeds]
    assert len(feeds) <= result.toolpath.blocks  # one a block at most
    assert sum(map(len, lines)) < 2000  # about 860 px of line: no point within 0.5 px
    xs = [x for line in lines for x in line]
    assert min(xs) == pytest.approx(50.0) and max(xs) == pytest.approx(910.0)  # end to end
    for line in lines:  # each point a half pixel on from the last, but the line's end
        assert all(b - a > 0.5 for a, b in itertools.pairwise(line[:-1]))
    assert len(render_png(result.toolpath)) > 0


# -- the emulator stops on what it cannot run ----------------------------------------------------

FAST_LINE = LineSettings(115200, 8, "N", 1)


@pytest.fixture
async def mill() -> AsyncIterator[tuple[Dyna2400Emulator, Server, Link]]:
    emulator = Dyna2400Emulator(
        time_scale=1000.0, delays=OperatorDelays(1.0, 1.0, 10.0), min_busy_s=0.05
    )
    server = await serve(emulator, "rfc2217://127.0.0.1:0", FAST_LINE, pacing=False)
    emulator.start()
    link = await open_link(server.url, FAST_LINE)
    await link.wait_cts(True, timeout=5)
    yield emulator, server, link
    await link.close()
    await server.close()


@pytest.mark.parametrize(
    ("rows", "fragment"),
    [
        (("000 FR XYZ = 0", "001 GR X 1.0"), "feed rate 0"),
        (("000 GO Z -.100", "001 CPOCKET R= .750 ZD= -.800 DP= 0.0000001"), "7,000,000 passes"),
    ],
)
async def test_emulator_enters_its_error_condition(
    mill: tuple[Dyna2400Emulator, Server, Link], rows: tuple[str, ...], fragment: str
) -> None:
    emulator, _, link = mill
    number = len(rows)
    block = [*rows, f"{number:03d} SKIP TO 900", "900"]
    await link.write(b"".join(r.encode() + b"\r\n" for r in block))
    async with asyncio.timeout(30):
        await emulator.failed.wait()
    assert emulator.error is not None and fragment in emulator.error
