"""The plan's chart shades each fault window: a machine's on its row, the PLC's (an
emergency stop, a dropped or silent PLC: it stops the whole cell, and has no row) across
every row, in the same style, labelled as the PLC's."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.ui.cli import main


def chart(tmp_path: Path, *faults: str) -> str:
    """The Gantt chart (SVG) of a 30-minute plan of one robot base from 06:00 with ``faults``
    (``--fault`` each)."""
    cell = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, cell)
    out = tmp_path / "out"
    windows = [arg for text in faults for arg in ("--fault", text)]
    result = CliRunner().invoke(
        main,
        ["plan", "--dir", str(cell), "--add", "wax-robot-base:1", "--start", "2026-11-25T06:00",
         "--shift", "30m", *windows, "--out", str(out)],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    return (out / "plan.svg").read_text()


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
def test_a_plc_window_is_shaded_across_every_row(tmp_path: Path) -> None:
    svg = chart(tmp_path, "plc:estop@06:05-06:10", "cnc2:down@06:20-06:25")
    windows = re.findall(
        r'<rect x="([\d.]+)" y="([\d.]+)" width="([\d.]+)"[^>]*class="window">'
        r"<title>([^<]*)</title>",
        svg,
    )
    plc = [w for w in windows if w[3].startswith("plc estop (the whole cell)")]
    down = [w for w in windows if w[3].startswith("down")]
    # One on each row: the robot's, cnc1's and cnc2's; all over the same span.
    assert len(plc) == 3 and len({y for _, y, _, _ in plc}) == 3, windows
    assert len({(x, w) for x, _, w, _ in plc}) == 1
    assert len(down) == 1 and down[0][1] in {y for _, y, _, _ in plc}
    # The same style as a machine's window.
    styles = set(
        re.findall(r'fill="[^"]+" fill-opacity="[^"]+" stroke="[^"]+"[^>]*class="window"', svg)
    )
    assert len(styles) == 1, styles


@pytest.mark.timeout(300)  # plays on a busy box: CPU, not waiting
def test_a_window_past_the_plan_ends_at_the_axis_end(tmp_path: Path) -> None:
    """A fault window that closes after the plan's end is shaded up to the axis' end (the
    plan's end), as the steps are: not past it, off the chart."""
    svg = chart(tmp_path, "cnc2:down@06:20-07:00")
    axis_end = max(
        float(x) for x in re.findall(r'<line x1="[\d.]+" y1="[\d.]+" x2="([\d.]+)"', svg)
    )
    [(x, width)] = re.findall(
        r'<rect x="([\d.]+)" y="[\d.]+" width="([\d.]+)"[^>]*class="window">', svg
    )
    # 06:20 to the plan's end at 06:30: the last third of the axis, ending where it ends.
    assert float(x) + float(width) == pytest.approx(axis_end, abs=0.2), (x, width, axis_end)
