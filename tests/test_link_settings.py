"""Line settings a user writes (``--line``, cell.toml, dnc.toml): a baud rate no line can
have is refused in words where the settings are read (exit 2), never a traceback from the
OS call that would set it; the highest rate allowed still opens a real pty."""

from __future__ import annotations

import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cellctl.errors import UsageError
from cellctl.link import LineSettings, open_link
from cellctl.link.settings import ETHERNET_LINE, MAX_BAUDRATE

from .conftest import CELLCTL, emulator_process


@pytest.mark.parametrize("rate", ["99999999999", "3000000000", "2147483648", "1000000001"])
def test_a_baud_rate_beyond_any_line_is_refused_when_read(rate: str) -> None:
    with pytest.raises(UsageError, match=f"baud rate {rate} is beyond any serial line"):
        LineSettings.parse(f"{rate},7E2")
    with pytest.raises(UsageError, match="at most 1,000,000,000"):
        LineSettings(int(rate), 7, "E", 2)


def test_thousands_of_digits_are_refused_without_reading_them_as_a_number() -> None:
    with pytest.raises(UsageError, match=r"\(6000 digits\) is beyond any serial line"):
        LineSettings.parse("9" * 6000 + ",7E2")


def test_rates_an_emulated_cell_or_a_mem_line_uses_are_taken() -> None:
    # 4800 baud at time scale 1000, as `cellctl emulate cell` writes it in its cell.toml.
    assert LineSettings.parse("4800000,7E2").baudrate == 4_800_000
    assert LineSettings.parse("0001000000000,8N1").baudrate == MAX_BAUDRATE
    assert ETHERNET_LINE.baudrate <= MAX_BAUDRATE


@given(st.from_regex(r"\A[0-9]{1,40}[,:/ ][5-8][NEOMS](1|1\.5|2)\Z"))
def test_any_number_of_digits_gives_settings_or_a_usage_error(text: str) -> None:
    try:
        settings = LineSettings.parse(text)
    except UsageError as e:
        assert "baud rate" in str(e)
    else:
        assert 0 < settings.baudrate <= MAX_BAUDRATE


async def test_the_highest_rate_opens_a_real_pty() -> None:
    """The bound is below what pyserial hands Linux (a signed 32-bit rate)."""
    master, slave = os.openpty()
    try:
        link = await open_link(os.ttyname(slave), LineSettings(MAX_BAUDRATE, 8, "N", 1))
        await link.close()
    finally:
        os.close(master)
        os.close(slave)


@pytest.fixture
def emulator() -> Iterator[str]:
    """``cellctl emulate robot`` in its own process on a pty; yields the pty path."""
    with emulator_process("robot", "--listen", "pty", "--time-scale", "500", "--no-pacing") as url:
        yield url


def test_cli_refuses_a_huge_baud_rate_with_exit_2(emulator: str, tmp_path: Path) -> None:
    for rate in ("99999999999", "3000000000"):
        done = subprocess.run(
            [*CELLCTL, "--cell", str(tmp_path), "robot", "--link", emulator,
             "--line", f"{rate},7E2", "status"],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert done.returncode == 2, done.stderr
        assert f"baud rate {rate} is beyond any serial line" in done.stderr
        assert "Traceback" not in done.stderr
    # The robot was not disturbed: the next command with its own line works.
    done = subprocess.run(
        [*CELLCTL, "--cell", str(tmp_path), "robot", "--link", emulator, "status"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "Robot state" in done.stdout
