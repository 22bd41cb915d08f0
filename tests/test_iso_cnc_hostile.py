"""Hostile G-code: the check, the time estimate and the preview answer in a subprocess limited
in memory and CPU time (``tests.conftest.run_limited``), with a typed problem (or a drawing);
the emulated control stops on garbage with an alarm instead of crashing."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import pytest

from cellctl.emulators.serve import serve
from cellctl.kinds.iso_cnc.emulator import Activity, EmulatorOptions, IsoCncEmulator, Mode
from cellctl.kinds.iso_cnc.tape import DC1
from cellctl.link import LineSettings, open_link

from .conftest import run_limited, until

_CHECK = textwrap.dedent(
    """
    import json, sys
    from pathlib import Path
    from cellctl.errors import UsageError
    from cellctl.kinds import registry
    from cellctl.kinds.kind import ProgramRole
    kind = registry.kind("iso-cnc")
    options = kind.checked_options({})
    path = Path(sys.argv[1])
    checked = kind.language.check(path, ProgramRole.MILLING, options)
    text = path.read_bytes().decode("latin-1")
    try:
        drawn = len(kind.language.preview(text, "hostile", options).svg)
    except UsageError as e:
        drawn = str(e)
    print(json.dumps({"problems": list(checked.problems[:5]), "count": len(checked.problems),
                      "seconds": checked.machining_s, "drawn": drawn}))
    """
)


def check_in_subprocess(tmp_path: Path, data: bytes) -> dict[str, object]:
    path = tmp_path / "hostile.nc"
    path.write_bytes(data)
    result: dict[str, object] = json.loads(run_limited(_CHECK, str(path)))
    return result


def tiny_arcs(n: int) -> bytes:
    rows = ["O1", "G21 G90 G17 G0 X0 Y0", "G1 F1000"]
    rows += [f"G{2 + i % 2}X{(i + 1) * 0.002:.3f}Y0R.001" for i in range(n)]
    return ("\n".join([*rows, "M30"]) + "\n").encode()


def test_a_million_tiny_arcs_are_refused_at_once(tmp_path: Path) -> None:
    found = check_in_subprocess(tmp_path, tiny_arcs(1_000_000))
    problems = found["problems"]
    assert isinstance(problems, list) and found["count"] == 1
    assert problems[0].startswith(f"{tmp_path / 'hostile.nc'}:1: ")
    # too many characters or blocks for a read-in: cellctl's cap, said as such
    assert "the most cellctl checks for a read-in" in problems[0]
    assert problems[0].endswith("drip-feed it (`cellctl dnc drip`, up to 1 GiB)")
    assert found["drawn"] == "cannot trace hostile: no moves"


def test_twenty_thousand_tiny_arcs_are_timed_and_drawn_in_bounded_memory(tmp_path: Path) -> None:
    found = check_in_subprocess(tmp_path, tiny_arcs(20_000))
    assert found["count"] == 0
    assert isinstance(found["seconds"], float) and found["seconds"] > 0
    assert isinstance(found["drawn"], int) and found["drawn"] < 2_000_000


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        (b"O1\n" + b"(" * 200_000 + b"\nM30\n", ":2: block of 200000 characters (at most 256)"),
        (b"O1\n" + b"G1 X1 (a (b (c (d\n" * 20_000 + b"M30\n", ":2:10: ( inside a comment"),
        (b"O1\n" + b"G1 X1 (never closed\n" * 20_000 + b"M30\n", "comment not closed"),
        (bytes(range(256)) * 4000, "not ISO code"),
        (b"O1\nG1 X1 F100\n" * 9_000_000, "more than 16777216, the most cellctl checks"),
    ],
)
def test_hostile_programs_get_a_typed_problem(tmp_path: Path, data: bytes, expected: str) -> None:
    found = check_in_subprocess(tmp_path, data)
    problems = found["problems"]
    assert isinstance(problems, list) and problems and expected in problems[0]
    assert isinstance(found["count"], int) and found["count"] <= 101


async def test_the_control_stops_on_garbage_with_an_alarm() -> None:
    """A host that pours binary at a drip-feed: alarm 085 (not 7-bit ISO) or 087 (it did not
    stop at DC3), never a crash; RESET clears it."""
    control = IsoCncEmulator(EmulatorOptions(), time_scale=10)
    control.mode = Mode.RMT
    line = LineSettings(96000, 7, "E", 2)
    server = await serve(control, "pty", line)
    link = await open_link(server.url, line)
    try:
        control.cycle_start()
        assert await link.read_exactly(1, timeout=10) == DC1
        await link.write(b"(" * 2000)
        await until(lambda: control.activity == Activity.ALARM, "the alarm", timeout=30)
        assert control.alarms[-1].code == 87
        await link.write(bytes([0xFF]) * 10)
        control.reset()
        control.cycle_start()
        await link.write(bytes([0xFF]))
        await until(lambda: control.alarms[-1].code == 85, "alarm 085", timeout=30)
    finally:
        await link.close()
        await server.close()
