"""Help says what a user otherwise finds out the hard way (issue 19, finding 13): each
command's default time scale and why they differ, that an emulated mill's operator presses
NEXT by itself, and README's line rate is the mill's default line."""

from __future__ import annotations

from pathlib import Path

import click
from click.testing import CliRunner

from cellctl.emulators.serve import CELL_TIME_SCALE, DEMO_TIME_SCALE, MACHINE_TIME_SCALE
from cellctl.kinds.dyna2400.emulator import OperatorDelays
from cellctl.link.settings import MILL_LINE
from cellctl.ui.cli import main
from cellctl.ui.common import subcommands

ROOT = Path(__file__).resolve().parent.parent


def _walk(
    command: click.Command, path: tuple[str, ...] = ()
) -> list[tuple[tuple[str, ...], click.Command]]:
    """Every command under ``command`` (imported as a user's `--help` would reach it)."""
    found = [(path, command)]
    if isinstance(command, click.Group):
        for name, sub in subcommands(command).items():
            found += _walk(sub, (*path, name))
    return found


def test_every_time_scale_option_says_its_default_and_the_others() -> None:
    defaults = {}
    for path, command in _walk(main):
        for param in command.params:
            if isinstance(param, click.Option) and "--time-scale" in param.opts:
                help_text = param.help or ""
                if not param.show_default:  # a driver's option: no scale of its own
                    continue
                defaults[" ".join(path)] = param.default
                for scale in (MACHINE_TIME_SCALE, CELL_TIME_SCALE, DEMO_TIME_SCALE):
                    assert f"{scale:g} for" in help_text, (path, help_text)
    assert defaults["emulate mill"] == defaults["emulate robot"] == MACHINE_TIME_SCALE
    assert defaults["emulate cell"] == defaults["emulate factory"] == CELL_TIME_SCALE
    assert defaults["demo"] == DEMO_TIME_SCALE


def test_mill_init_says_an_emulator_presses_next_by_itself() -> None:
    shown = " ".join(CliRunner().invoke(main, ["mill", "init", "--help"]).output.split())
    assert "press NEXT" in shown
    assert f"by itself {OperatorDelays().setup:g} s" in shown


def test_readme_gives_the_mills_default_line() -> None:
    readme = (ROOT / "README.md").read_text()
    assert "2400 baud" not in readme
    line = (
        f"{MILL_LINE.baudrate} baud, {MILL_LINE.bytesize}{MILL_LINE.parity}{MILL_LINE.stopbits:g}"
    )
    assert line in readme
