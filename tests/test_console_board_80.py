"""At 80x24 the console's board keeps a machine's progress figures on their line (the words
shorten, never the figures: block n of m and the time left), and each traffic row stays one
row of the pane, cut to its width."""

from __future__ import annotations

import time
from typing import Any

import pytest

from cellctl.service.status import CellStatus
from cellctl.ui.console.widgets import board_text, progress_text, traffic_text

#: The board's columns at 80x24: the screen less the menu (36), its border and padding.
BOARD_80 = 41
#: The traffic pane's columns at 80x24 (less its padding).
TRAFFIC_80 = 78


def status_with(progress: dict[str, Any]) -> dict[str, Any]:
    now = time.time()
    machine = {
        "name": "cnc2",
        "kind": "dyna2400",
        "family": "mill",
        "condition": "out-of-service",
        "state": "Executing",
        "step": {"what": "manual", "program": "toy_mill_table_finish_cnc2.dyn", "started": now},
        "progress": {"unit": "bytes", "fraction": 0.3, "since": now, **progress},
        "failures": 0,
        "busy_s": 0.0,
        "utilization": 0.0,
        "in_service": False,
        "out_reason": "taken out by the operator",
        "manual": True,
    }
    cell = {
        "name": "lab",
        "directory": "/tmp/lab",
        "access": "attached",
        "mode": "running",
        "paused": False,
        "started_at": now,
        "pid": 1,
        "time": now,
    }
    return CellStatus.model_validate(
        {
            "cell": cell,
            "machines": {"cnc2": machine},
            "orders": [],
            "parts": [],
            "alarms": [],
            "events": [],
        }
    ).model_dump(mode="json")


def counted(raw: dict[str, Any]) -> str:
    """Where a progress counted in its unit ends on its line: the bar, then the count."""
    return f"       ██░░░░░░  30% {raw['done']}/{raw['total']} bytes"


@pytest.mark.parametrize(
    ("phase", "block", "blocks", "left"),
    [
        ("sending", 1, 1, 12.0),
        ("machining", 2, 3, 345.0),
        ("machining", 12, 15, 4321.0),
        ("downloading", None, None, 9.0),
    ],
)
def test_the_boards_progress_line_keeps_its_figures_at_80_columns(
    phase: str, block: int | None, blocks: int | None, left: float
) -> None:
    raw = {"phase": phase, "done": 300, "total": 1000, "block": block, "blocks": blocks}
    raw["time_left_s"] = left
    board = board_text(status_with(raw), BOARD_80).plain.splitlines()
    at = next(i for i, x in enumerate(board) if "░" in x or "█" in x)
    # A progress counted in its unit has its figures on the line below the bar.
    lines = board[at : at + (1 if blocks else 2)]
    assert all(len(x) <= BOARD_80 for x in lines), lines
    shown = " ".join(lines)
    figures = (f"{block}/{blocks} " if blocks else "") + f"{left:.0f}"
    assert figures in shown and "left" in shown, lines
    # Whole before anything is cut (the step's name after them may be).
    assert "…" not in lines[0][: lines[0].find("left") if blocks else len(counted(raw))], lines


def test_the_progress_words_shorten_not_the_figures() -> None:
    raw = status_with(
        {"phase": "machining", "done": 1, "total": 2, "block": 2, "blocks": 3, "time_left_s": 12}
    )
    p = CellStatus.model_validate(raw).machines["cnc2"].progress
    assert p is not None
    assert progress_text(p) == "machining block 2/3 12 s left"
    assert progress_text(p, 40) == "machining block 2/3 12 s left"
    assert progress_text(p, 20) == "mach b2/3 12s left"
    assert progress_text(p, 13) == "b2/3 12s left"


@pytest.mark.parametrize("width", [TRAFFIC_80, 60, 40])
def test_each_traffic_row_is_cut_to_the_panes_width(width: int) -> None:
    sent = bytes(range(48, 48 + 40)) * 3
    row = {
        "time": time.time(),
        "dir": ">>",
        "hex": sent.hex(" ").upper(),
        "text": sent.decode("ascii"),
    }
    shown = traffic_text("cnc2", [row, {**row, "dir": "<<"}], width, command=row).plain
    rows = shown.splitlines()
    assert len(rows) == 3
    assert all(len(r) <= width for r in rows), rows
    assert rows[0].split()[1] == ">>*" and "|" in rows[0]
