"""``cellctl demo`` as a user runs it (finding 12): headings that read as words, Gantt charts
with a legend, from the batch's start, both runs on one time axis, and ``--dashboard`` with
one controller (the API and the machines connected once)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import threading
import time
import urllib.request
from pathlib import Path
from queue import Empty, Queue

from cellctl.cell.journal import open_journal
from cellctl.cell.report import gantt_svg
from cellctl.clock import RealClock
from cellctl.mailbox.base import Order
from tests.conftest import CELLCTL

DEMO = [*CELLCTL, "demo", "--parts", "2", "--time-scale", "1000"]
TICKS = re.compile(r'text-anchor="middle">([\d.]+) s</text>')


def test_the_demo_names_its_runs_and_charts_both_on_one_axis(tmp_path: Path) -> None:
    out = tmp_path / "demo-out"
    result = subprocess.run([*DEMO, "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    text = result.stdout
    # A heading is words, not something that looks like a command to type.
    assert "cellctl schedule" not in text
    assert "batch: 1 wax-robot-base + 1 wax-toy-mill-table" in text, text
    assert "parts in parallel (cellctl's scheduler)" in text
    assert "one part at a time (the source's way)" in text
    charts = {name: (out / name / "gantt.svg").read_text() for name in ("cell", "one-at-a-time")}
    both = (out / "gantt.svg").read_text()
    for svg in (*charts.values(), both):
        legend = svg.split('<g class="legend">', 1)[1]
        for entry in ("wax-robot-base", "wax-toy-mill-table", "failed or interrupted", "start-up"):
            assert entry in legend, entry
    # One time axis: the same ticks on each run's chart and on the chart of both.
    ticks = [TICKS.findall(svg) for svg in (*charts.values(), both)]
    assert ticks[0] == ticks[1] == ticks[2] and len(ticks[0]) == 11, ticks
    assert "parts in parallel" in both and "one part at a time" in both
    # The axis holds the longer run whole (its start-up and makespan).
    makespans = [float(m) for m in re.findall(r"^makespan: ([\d.]+) s$", text, re.M)]
    assert len(makespans) == 2 and float(ticks[0][-1]) >= max(makespans), (makespans, ticks)
    assert both.count('class="step transfer"') == 2 * charts["cell"].count('class="step transfer"')


class _ListClock(RealClock):
    """Wall time from ``now[0]``, which the test sets."""

    def __init__(self, now: list[float]) -> None:
        super().__init__()
        self._at = now

    def now(self) -> float:
        return self._at[0]


def test_a_chart_starts_at_the_batch_not_at_its_first_step(tmp_path: Path) -> None:
    """The time between the batch's start and the first step (the controller connecting:
    the robot initialized, the mills' setups sent) is on the chart, drawn and in the legend;
    a step of a few hundredths of a second is still a visible bar."""
    now = [1000.0]
    with open_journal(tmp_path, clock=_ListClock(now)) as journal:
        order = Order("O1", "wax-robot-base", 1, 0, "accepted", now[0], now[0])
        [part] = journal.create_parts(order)
        now[0] = 1012.0  # the robot's first step, 12 s after the batch started
        step = journal.begin_step(part.id, "transfer", "robot", "conveyor_to_cnc1")
        now[0] = 1012.05
        journal.end_step(step.id, "finished")
        now[0] = 1013.0
        cut = journal.begin_step(part.id, "machine", "cnc1", "robot_base_rough_cnc1")
        now[0] = 1100.0
        journal.end_step(cut.id, "finished")
        steps = journal.steps()
    svg = gantt_svg(steps, ["robot", "cnc1"], part_types={part.id: "wax-robot-base"}, since=1000.0)
    start_up = re.search(r'<rect x="90" y="[\d.]+" width="([\d.]+)"[^>]*class="start-up"', svg)
    assert start_up is not None, svg
    assert abs(float(start_up.group(1)) - 12 / 100 * 900) < 1  # 12 of the 100 s, at 900 px
    transfer = re.search(
        r'<rect x="([\d.]+)" y="[\d.]+" width="([\d.]+)"[^>]*class="step transfer"', svg
    )
    assert transfer is not None, svg
    assert abs(float(transfer.group(1)) - (90 + 12 / 100 * 900)) < 1
    assert float(transfer.group(2)) >= 2.0


def _lines(stream: object, into: Queue[str]) -> None:
    for line in iter(stream.readline, ""):  # type: ignore[attr-defined]
        into.put(line)


def _until(lines: Queue[str], seen: list[str], pattern: str, deadline: float) -> str:
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise AssertionError(f"no line with {pattern!r} in time:\n{''.join(seen)}")
        try:
            line = lines.get(timeout=left)
        except Empty:
            continue
        seen.append(line)
        if re.search(pattern, line):
            return line


def test_the_dashboard_demo_keeps_one_controller_after_the_batch(tmp_path: Path) -> None:
    out = tmp_path / "demo-out"
    demo = subprocess.Popen(
        [*DEMO, "--no-compare", "--dashboard", "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "COLUMNS": "200"},
    )
    lines: Queue[str] = Queue()
    threading.Thread(target=_lines, args=(demo.stdout, lines), daemon=True).start()
    seen: list[str] = []
    try:
        url = _until(lines, seen, r"^dashboard: http", time.monotonic() + 60).split()[-1]
        _until(lines, seen, r"the batch is done", time.monotonic() + 60)
        _until(lines, seen, r"Ctrl-C stops", time.monotonic() + 10)
        # The dashboard still answers after the batch, on the same address.
        base, token = url.split("/#token=")
        request = urllib.request.Request(
            f"{base}/server/info", headers={"Authorization": f"Bearer {token}"}
        )
        with urllib.request.urlopen(request, timeout=5) as answer:
            assert answer.status == 200
    finally:
        demo.send_signal(signal.SIGINT)
        try:
            demo.wait(timeout=30)
        except subprocess.TimeoutExpired:
            demo.kill()
            demo.wait(timeout=10)
    while True:
        try:
            seen.append(lines.get(timeout=2))
        except Empty:
            break
    text = "".join(seen)
    assert "parts in parallel (cellctl's scheduler)" in text
    # One controller: the API started and the machines connected once, not again after it.
    assert text.count("control API on") == 1, text
    assert text.count("connected to robot") == 1, text
    assert (out / "cell" / "gantt.svg").is_file()


def test_a_demo_interrupted_says_so_and_exits_130(tmp_path: Path) -> None:
    """Ctrl-C before the batch is done: "interrupted", exit 130, and no figures of a batch
    that was not run (they read as a finished batch with nothing made)."""
    demo = subprocess.Popen(
        [*CELLCTL, "demo", "--parts", "2", "--time-scale", "50", "--out", str(tmp_path / "o")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert demo.stdout is not None
        seen = ""
        while "connected to robot" not in seen:
            line = demo.stdout.readline()
            assert line, seen + demo.communicate(timeout=30)[1]
            seen += line
        demo.send_signal(signal.SIGINT)
        out, err = demo.communicate(timeout=60)
    finally:
        demo.kill()
        demo.wait()
    assert demo.returncode == 130, seen + out + err
    assert "interrupted" in out + err
    assert "parts made" not in seen + out and "makespan" not in seen + out
