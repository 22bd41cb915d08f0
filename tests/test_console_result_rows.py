"""The console's result pane shows what fits its rows: a LOG's newest lines, never its oldest
with the newest cut off (a log of long lines wrapped past the pane's seven rows)."""

from __future__ import annotations

from cellctl.ui.console.widgets import RESULT_ROWS, fit_rows


def test_lines_that_fit_are_shown_as_they_are() -> None:
    lines = ["mill2: LOG: the last 5 lines of its log", *[f"line {i}" for i in range(5)]]
    assert fit_rows(lines, 80, RESULT_ROWS) == lines


def test_a_log_that_wraps_past_the_pane_keeps_its_heading_and_newest_lines() -> None:
    heading = "mill2: LOG: the last 5 lines of its log"
    log = [f"02:5{i}:00 drip-fed O500{i}.nc, " + "x" * 110 for i in range(5)]  # 2 rows each
    shown = fit_rows([heading, *log], 118, RESULT_ROWS)
    assert shown[0] == heading
    assert shown[-2:] == log[-2:]  # the newest, whole
    assert shown[1] == "… 3 earlier lines not shown"
    rows = sum(-(-len(line) // 118) for line in shown)
    assert rows <= RESULT_ROWS


def test_one_line_longer_than_the_pane_is_left_to_the_pane() -> None:
    assert fit_rows(["x" * 2000], 80, RESULT_ROWS) == ["x" * 2000]
