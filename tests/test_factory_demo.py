"""``cellctl demo --factory N`` as a user runs it: a private Mosquitto, emulated cells, each
cell's ``cellctl run`` and the factory, all started and stopped by the one command."""

from __future__ import annotations

import re
import signal
import subprocess
import time
from pathlib import Path

from cellctl.cell.config import load_cell
from cellctl.emulators.cell import EXAMPLE_CELL
from tests.conftest import CELLCTL

TENDING = Path(__file__).resolve().parent.parent / "examples" / "cell-tending"
DEMO = [*CELLCTL, "demo", "--factory", "2", "--parts", "4", "--time-scale", "1000"]


def left_behind(marker: Path) -> list[str]:
    """Command lines of running processes that name ``marker`` (the demo's directory)."""
    found = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            words = cmdline.read_bytes().split(b"\0")
        except OSError:
            continue  # it ended meanwhile
        text = " ".join(w.decode(errors="replace") for w in words)
        if str(marker) in text:
            found.append(text)
    return found


def test_the_factory_demo_makes_every_part_once_and_leaves_nothing_running(
    tmp_path: Path,
) -> None:
    """Two kinds of cell: cell1 the cobot-tending cell (--template), cell2 the example cell;
    each makes its own part types, the batch mixes them all."""
    out = tmp_path / "demo-out"
    result = subprocess.run(
        [*DEMO, "--template", str(TENDING), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    text = result.stdout
    cells = re.findall(
        r"^(cell\d): (\d+) orders?, parts made (\d+) \((.*)\);.*parts cut twice (\d+)$",
        text,
        re.M,
    )
    assert [c[0] for c in cells] == ["cell1", "cell2"], text
    assert all(twice == "0" for *_, twice in cells), text
    assert sum(int(made) for _, _, made, _, _ in cells) == 4, text
    made = {name: set(re.findall(r"\d+ x ([^,\s]+)", what)) for name, _, _, what, _ in cells}
    assert made["cell1"] == set(load_cell(TENDING).parts), text
    assert made["cell2"] <= set(load_cell(EXAMPLE_CELL).parts) and made["cell2"], text
    total = re.search(
        r"^total: 4 orders \(4 done\), parts made 4 of 4; makespan ([0-9.]+) s", text, re.M
    )
    assert total is not None, text
    assert "bound of the best split" in text and text.rstrip().count("parts cut twice 0") == 3
    assert "order F1 sent to cell" in text and "order F4 done at cell" in text
    for cell in ("cell1", "cell2"):
        log = (out / "factory" / cell / "run.log").read_text()
        assert "mailbox: mqtt://127.0.0.1:" in log  # the cell took its orders from the broker
        assert (out / "factory" / cell / "gantt.svg").exists()
    assert left_behind(tmp_path) == []


def test_ctrl_c_stops_the_cells_and_the_broker(tmp_path: Path) -> None:
    out = tmp_path / "demo-out"
    proc = subprocess.Popen(
        [*DEMO, "--parts", "8", "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert proc.stdout is not None
        seen = []
        for line in proc.stdout:
            seen.append(line)
            if "orders submitted" in line:
                break
        assert any("orders submitted" in s for s in seen), "".join(seen)
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, "".join(seen) + rest
    assert "interrupted" in rest
    deadline = time.monotonic() + 5  # a process that has exited may linger a moment in /proc
    while left_behind(tmp_path) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert left_behind(tmp_path) == []
