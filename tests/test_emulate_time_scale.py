"""`--time-scale` out of range is refused by the option, naming it and its range, before the
command prints or writes anything (it was refused by the cell file the demo had written, with
that file's lines); the range is the cell file's own ``[cell] time_scale``."""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Annotated

import click
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydantic import TypeAdapter, ValidationError

from cellctl.cell.configschema import CellTable
from cellctl.ui.emulate_cli import TIME_SCALE

from .conftest import CELLCTL


@pytest.mark.parametrize("scale", ["1e9", "0", "-1", "nan", "inf", "100000.5"])
def test_demo_refuses_a_time_scale_out_of_range_before_its_banner(
    tmp_path: Path, scale: str
) -> None:
    out = tmp_path / "out"
    done = subprocess.run(
        [*CELLCTL, "demo", "--time-scale", scale, "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert done.stdout == ""  # no banner
    assert "Invalid value for '--time-scale'" in done.stderr
    assert "is not in the range 0<x<=100000." in done.stderr
    assert "cell.toml" not in done.stderr
    assert not out.exists()


def test_demo_help_gives_the_range() -> None:
    done = subprocess.run(
        [*CELLCTL, "demo", "--help"], capture_output=True, text=True, timeout=60, check=True
    )
    assert "0<x<=100000]" in done.stdout


#: What the cell file accepts for [cell] time_scale (the one table of the range).
CELL_FILE_SCALE: TypeAdapter[float] = TypeAdapter(
    Annotated[float, *CellTable.model_fields["time_scale"].metadata]  # type: ignore[misc]
)


@given(st.one_of(st.floats(), st.text(max_size=12), st.sampled_from(["1e5", "100000", "5e-324"])))
def test_the_option_takes_what_the_cell_file_takes(value: float | str) -> None:
    text = str(value)
    try:
        scale = TIME_SCALE.convert(text, None, None)
    except click.BadParameter:
        accepted = True
        try:
            CELL_FILE_SCALE.validate_python(text, strict=False)
        except ValidationError:
            accepted = False
        assert not accepted, text
        return
    assert CELL_FILE_SCALE.validate_python(scale) == scale


@pytest.mark.parametrize("command", [["emulate", "cell"], ["emulate", "factory", "plant"]])
def test_the_emulated_cells_refuse_it_as_the_demo_does(tmp_path: Path, command: list[str]) -> None:
    # They wrote a cell.toml the controller would then refuse (or a line faster than any).
    done = subprocess.run(
        [*CELLCTL, "--cell", str(tmp_path / "c"), *command, "--time-scale", "2e5"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert done.returncode == 2, done.stdout + done.stderr
    assert "is not in the range 0<x<=100000." in done.stderr
    assert list(tmp_path.iterdir()) == []
