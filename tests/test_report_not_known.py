"""`cellctl report shift` over a window in which no step has ended yet: a ratio with nothing
to divide by is not known (`—` in the table, null in JSON, empty in CSV), not 0 %.

The journal is a real run's (a batch on the emulated cell); the window ends half-way through
its first step, the robot's first transfer: the robot has been in a step (availability
known, performance 0: nothing finished in its time), nothing has ended (quality, OEE not
known), and the mills have not worked at all (performance not known either)."""

from __future__ import annotations

import csv
import json
from datetime import datetime
from pathlib import Path

import pytest

from cellctl.testing.rig import CellRig


def _iso(t: float) -> str:
    """``t`` as `--from` and `--to` take it (local time, to the microsecond)."""
    return datetime.fromtimestamp(t).isoformat()


@pytest.mark.virtual
async def test_the_shift_report_before_any_step_ended_says_not_known(tmp_path: Path) -> None:
    async with CellRig(tmp_path / "cell") as rig:
        rig.post("wax-robot-base", 1, "A")
        await rig.start_controller()
        await rig.wait_for(rig.all_done, "order A done", 120)
        await rig.stop_controller()
        first = rig.journal.steps()[0]
        assert first.ended is not None and first.machine == "robot", rig.describe()
        window = ["--from", _iso(first.started)]
        window += ["--to", _iso(first.started + (first.ended - first.started) / 2)]

        as_json = await rig.cli("report", "shift", "--json", *window)
        assert as_json.exit_code == 0, as_json.output
        figures = {m["machine"]: m for m in json.loads(as_json.output)["machines"]}
        assert set(figures) == {"robot", "cnc1", "cnc2"}
        for m in figures.values():
            assert m["steps_ended"] == 0, m
            assert m["quality"] is None and m["oee"] is None, m
        robot = figures["robot"]
        assert robot["production_s"] > 0 and robot["availability"] > 0, robot
        assert robot["performance"] == 0.0  # in a step, nothing finished: known, and 0
        for name in ("cnc1", "cnc2"):
            assert figures[name]["production_s"] == 0.0
            assert figures[name]["availability"] == 0.0  # known: the window went by idle
            assert figures[name]["performance"] is None  # no time in steps to divide by

        saved = tmp_path / "shift.csv"
        table = await rig.cli("report", "shift", *window, "--csv", str(saved))
        assert table.exit_code == 0, table.output
        lines = table.output.splitlines()
        (header,) = [x for x in lines if x.startswith("machine ")]

        def column(line: str, name: str) -> str:
            end = header.index(name) + len(name)  # 7 wide, right-aligned as its heading
            return line[end - 7 : end].strip()

        rows = {x.split()[0]: x for x in lines if x.split() and x.split()[0] in figures}
        assert set(rows) == set(figures), table.output
        for row in rows.values():
            assert column(row, "quality") == "—", row
            assert column(row, "OEE") == "—", row
        assert column(rows["robot"], "perf") == "0.0 %"
        assert column(rows["cnc1"], "perf") == "—"
        assert "0.0 %" not in column(rows["cnc2"], "quality")

        with saved.open(newline="") as f:
            values = {(r[1], r[2]): r[3] for r in csv.reader(f) if r[0] == "machine"}
        assert values[("cnc1", "quality")] == values[("cnc1", "oee")] == ""
        assert values[("robot", "performance")] == "0.0"
