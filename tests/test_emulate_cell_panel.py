"""`cellctl emulate cell --panel`: the machines' operators by hand, on stdin. A Dyna 2400 mill
in ERROR (a malformed block, as a host that does not validate sends it) stays there until its
operator resets it at the machine: `clear cnc1` does, and the mill is READY (CTS high) again.

The real command in its own process; the mill is driven with raw bytes over its RFC 2217
link, as the controller's driver would reach it."""

from __future__ import annotations

import asyncio
import re
import signal
import subprocess
import tomllib
from pathlib import Path

import pytest

from cellctl.link import LineSettings, open_link
from tests.conftest import CELLCTL


def lines(*rows: str) -> bytes:
    return b"".join(row.encode() + b"\r\n" for row in rows)


@pytest.mark.timeout(120)
async def test_clear_resets_a_dyna_mill_in_error_at_its_panel(tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    proc = await asyncio.create_subprocess_exec(
        *CELLCTL, "--cell", str(cell), "emulate", "cell", "--time-scale", "1000", "--panel",
        stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.STDOUT,
    )  # fmt: skip
    assert proc.stdin is not None and proc.stdout is not None
    stdin, stdout = proc.stdin, proc.stdout
    said: list[str] = []

    async def line() -> str:
        async with asyncio.timeout(30):
            text = (await stdout.readline()).decode()
        said.append(text)
        assert text, "the emulated cell ended: " + "".join(said)
        return text.strip()

    async def hand(command: str) -> str:
        stdin.write(command.encode() + b"\n")
        await stdin.drain()
        return await line()

    try:
        while not (await line()).startswith("hand commands"):
            pass
        assert "clear MACHINE" in said[-1], said[-1]
        found = re.search(r"^\s*cnc1\s+(\S+)", "".join(said), re.M)
        assert found, "".join(said)
        setting = tomllib.loads((cell / "cell.toml").read_text())["machines"]["cnc1"]["line"]
        link = await open_link(found.group(1), LineSettings.parse(setting))
        try:
            await link.wait_cts(True, timeout=10)  # READY: its automatic operator readied it
            await link.write(lines("000 GO X 1.000", "001 GO X 1.2.3", "002 SKIP TO 900", "900"))
            await link.wait_cts(False, timeout=10)
            for _ in range(100):
                shown = await hand("show")
                if "cnc1: ERROR" in shown:
                    break
                await asyncio.sleep(0.05)
            assert "cnc1: ERROR" in shown, shown
            assert not await link.cts()  # in ERROR it stays not ready: nobody else clears it

            cleared = await hand("clear cnc1")
            assert re.fullmatch(r"cnc1: ERROR .*line 001.* cleared: READY", cleared), cleared
            await link.wait_cts(True, timeout=10)
            assert await hand("clear cnc1") == "cnc1: nothing to clear (READY)"
            assert "cnc1: READY" in await hand("show")
            refused = await hand("clear cnc9")
            assert refused.startswith("panel: clear cnc9: no machine 'cnc9'"), refused
            assert "cnc1" in refused and "robot" in refused
        finally:
            await link.close()
    finally:
        if proc.returncode is None:
            proc.send_signal(signal.SIGINT)
        async with asyncio.timeout(30):
            await proc.wait()


def test_emulate_cell_help_names_the_hand_commands() -> None:
    done = subprocess.run(
        [*CELLCTL, "emulate", "cell", "--help"], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    text = " ".join(done.stdout.split())
    assert "--panel" in text and "clear MACHINE" in text, text
