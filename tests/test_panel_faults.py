"""`cellctl emulate cell --panel`: an instructor switches faults on and off while the cell
runs (`fault MACHINE:NAME[=ARG]`, `fault off MACHINE:NAME`, `faults`), refused as `--fault`
refuses them, in the same words; and a switch that takes a default says the value it took,
at start as on the panel.

The real command in its own process; its machines are reached as the controller reaches
them: a mill's readiness on the CTS line of its RFC 2217 link, the PLC through its driver."""

from __future__ import annotations

import asyncio
import re
import signal
import subprocess
import tomllib
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from cellctl.drivers.plc import ModbusPlc
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.emulators.plc import FAULTS as PLC_FAULTS
from cellctl.emulators.switches import default_of, takes_argument
from cellctl.errors import LinkError, UsageError
from cellctl.kinds import registry
from cellctl.link import LineSettings, open_link
from cellctl.plan.faults import check_switch as switched_on_fresh
from cellctl.protocol.plc import PlcMap
from tests.conftest import CELLCTL, until
from tests.test_fault_switches import every_switch

#: The shipped cell whose cnc2 is an ISO control (its switches take defaults in ms).
MODERN_CELL = EXAMPLE_CELL.parent / "cell-modern"


@dataclass
class Panel:
    """A running `emulate cell --panel`: what it said, and a line to type hand commands on."""

    proc: asyncio.subprocess.Process
    cell: Path
    said: list[str] = field(default_factory=list)

    async def line(self) -> str:
        assert self.proc.stdout is not None
        async with asyncio.timeout(30):
            text = (await self.proc.stdout.readline()).decode()
        self.said.append(text)
        assert text, "the emulated cell ended: " + "".join(self.said)
        return text.strip()

    async def hand(self, command: str) -> str:
        """Type ``command`` and read its one-line answer."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(command.encode() + b"\n")
        await self.proc.stdin.drain()
        return await self.line()

    def url(self, machine: str) -> str:
        found = re.search(rf"^\s*{machine}\s+(\S+)", "".join(self.said), re.M)
        assert found, "".join(self.said)
        return found.group(1)

    def toml(self) -> dict[str, object]:
        return tomllib.loads((self.cell / "cell.toml").read_text())


@asynccontextmanager
async def emulated_cell(tmp_path: Path, *args: str) -> AsyncIterator[Panel]:
    """`cellctl emulate cell --panel ARGS` until its hand commands are offered; stopped
    with Ctrl-C after."""
    cell = tmp_path / "cell"
    proc = await asyncio.create_subprocess_exec(
        *CELLCTL, "--cell", str(cell), "emulate", "cell", "--time-scale", "1000", "--panel",
        *args,
        stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.STDOUT,
    )  # fmt: skip
    panel = Panel(proc, cell)
    try:
        while not (await panel.line()).startswith("hand commands"):
            pass
        yield panel
    finally:
        if proc.returncode is None:
            proc.send_signal(signal.SIGINT)
        async with asyncio.timeout(30):
            await proc.wait()


@pytest.mark.timeout(180)
async def test_an_instructor_pulls_a_cable_mid_run_and_puts_it_back(tmp_path: Path) -> None:
    async with emulated_cell(tmp_path) as panel:
        assert "fault MACHINE:NAME[=ARG]" in panel.said[-1], panel.said[-1]
        machines = panel.toml()["machines"]
        assert isinstance(machines, dict)
        link = await open_link(panel.url("cnc2"), LineSettings.parse(machines["cnc2"]["line"]))
        plc_table = panel.toml()["plc"]
        assert isinstance(plc_table, dict)
        plc = await ModbusPlc.connect(plc_table["url"], PlcMap.from_toml(plc_table), timeout=5)
        try:
            await link.wait_cts(True, timeout=30)  # READY: its automatic operator readied it
            assert "cnc2: nothing on" in await panel.hand("faults")

            # cnc2's READY line is cut: the mill is not ready to a host any more.
            assert await panel.hand("fault cnc2:never-ready") == "cnc2: never-ready on"
            await link.wait_cts(False, timeout=10)
            listed = await panel.hand("faults")
            assert "cnc2: never-ready on (its switches: never-ready, no-next, drop" in listed
            assert "cnc1: nothing on" in listed and "robot: nothing on" in listed, listed

            # Back in: the switch off, and its operator selects the link mode again (READY).
            assert await panel.hand("fault off cnc2:never-ready") == (
                "cnc2: never-ready off; it shows READY"
            )
            await link.wait_cts(True, timeout=10)
            assert await panel.hand("fault off cnc2:never-ready") == (
                "cnc2: never-ready is not on (nothing switched off)"
            )

            # The PLC's network cut: its driver's reads fail, and answer again once it is back.
            assert (await plc.read_inputs())["estop_ok"] is True
            assert await panel.hand("fault plc:drop") == "plc: drop on"
            with pytest.raises(LinkError):
                await plc.read_inputs()
            assert "plc: drop on" in await panel.hand("faults")
            assert await panel.hand("fault off plc:drop") == "plc: drop off"
            answered: dict[str, bool] = {}

            async def answers() -> bool:
                try:
                    answered.update(await plc.read_inputs())
                except LinkError:
                    return False
                return True

            await until(answers, "the PLC answering again", timeout=30)
            assert answered["estop_ok"] is True
            assert "plc: nothing on" in await panel.hand("faults")
        finally:
            await plc.close()
            await link.close()


#: Bad fault commands, refused by the panel in `--fault`'s own words.
REFUSED = {
    "cnc9:drop": "fault 'cnc9:drop': no machine 'cnc9' (robot, cnc1, cnc2, plc)",
    "cnc1:stal": "fault 'cnc1:stal': unknown fault 'stal' for cnc1; known: never-ready, ",
    "cnc1:stall=3": "fault 'cnc1:stall=3': stall takes no argument, not '3'",
}


async def _refused_at_start(tmp_path: Path, text: str) -> str:
    """What `emulate cell --fault TEXT` says as it refuses to start (exit 2)."""
    proc = await asyncio.create_subprocess_exec(
        *CELLCTL, "--cell", str(tmp_path / text.replace(":", "_")), "emulate", "cell",
        "--fault", text,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    async with asyncio.timeout(60):
        _, err = await proc.communicate()
    assert proc.returncode == 2, err
    return " ".join(err.decode().split())


@pytest.mark.timeout(180)
async def test_bad_fault_commands_are_refused_in_the_words_of_fault(tmp_path: Path) -> None:
    at_start = await asyncio.gather(*(_refused_at_start(tmp_path, text) for text in REFUSED))
    async with emulated_cell(tmp_path) as panel:
        for (text, words), started in zip(REFUSED.items(), at_start, strict=True):
            refused = await panel.hand(f"fault {text}")
            assert refused.startswith(f"panel: {words}"), refused
            assert refused.removeprefix("panel: ") in started, (refused, started)
        # The machine's emulator refuses a value in its own words, as it does at start.
        assert await panel.hand("fault cnc1:drop=soon") == (
            "panel: drop takes a line count, not 'soon'"
        )
        refused = await panel.hand("fault off cnc1:stal")
        assert refused.startswith("panel: " + REFUSED["cnc1:stal"]), refused
        assert (await panel.hand("fault off cnc1:drop=3")).startswith(
            "panel: fault off cnc1:drop=3: write fault off MACHINE:NAME, without =ARG"
        )
        refused = await panel.hand("fault")  # not a command the panel knows
        assert refused.startswith("panel: unknown hand command 'fault': "), refused
        assert "fault off MACHINE:NAME" in refused and "faults (" in refused
        # Nothing refused was switched on.
        assert "cnc1: nothing on" in await panel.hand("faults")


@pytest.mark.timeout(180)
async def test_a_default_taken_is_said_at_start_and_on_the_panel(tmp_path: Path) -> None:
    async with emulated_cell(
        tmp_path, "--template", str(MODERN_CELL), "--fault", "cnc2:adapter-latency",
        "--fault", "plc:slow", "--fault", "cnc1:drop=3",
    ) as panel:  # fmt: skip
        started = [line.strip() for line in panel.said]
        assert "fault cnc2: adapter-latency on (16 ms, its default)" in started, started
        assert "fault plc: slow on (400 ms, its default)" in started, started
        assert "fault cnc1: drop=3 on" in started, started

        assert await panel.hand("fault cnc2:line-lag") == "cnc2: line-lag on (16 ms, its default)"
        assert await panel.hand("fault cnc2:line-lag=5") == "cnc2: line-lag=5 on"
        listed = await panel.hand("faults")
        # A table of arguments shows them (the PLC's, the mill's); a control that keeps its
        # switches' names only shows those.
        assert "plc: slow (400 ms, its default) on" in listed, listed
        assert "cnc1: drop=3 on" in listed, listed
        assert re.search(r"cnc2: (adapter-latency, line-lag|line-lag, adapter-latency) on", listed)
        off = await panel.hand("fault off cnc1:drop")  # then what its display shows
        assert off.startswith("cnc1: drop off"), off
        assert await panel.hand("fault cnc1:drop") == "cnc1: drop on (5 lines, its default)"
        off = await panel.hand("fault off cnc2:adapter-latency")
        assert off.startswith("cnc2: adapter-latency off"), off


@pytest.mark.parametrize(("kind", "name"), every_switch())
def test_no_switch_takes_a_default_its_table_does_not_name(kind: str | None, name: str) -> None:
    """Each switch that takes an argument is either refused without it, or its description
    names the value it takes then: what help, refusals and the panel show is that table."""
    table = registry.kind(kind).faults if kind else PLC_FAULTS
    if not takes_argument(table, name):
        assert default_of(table, name) is None
        return
    try:
        switched_on_fresh(kind or "plc", kind, name, None)
    except UsageError:
        assert default_of(table, name) is None, f"{name}: refused without its argument"
    else:
        assert default_of(table, name), f"{name}: a default its description does not name"


def test_emulate_cell_help_names_the_fault_hand_commands() -> None:
    done = subprocess.run(
        [*CELLCTL, "emulate", "cell", "--help"], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    text = " ".join(done.stdout.split())
    for command in ("fault MACHINE:NAME[=ARG]", "fault off MACHINE:NAME", "faults ("):
        assert command in text, (command, text)


@pytest.mark.timeout(180)
async def test_a_cobots_switches_on_are_listed(tmp_path: Path) -> None:
    """The UR emulator keeps its switches behind its controller: `faults` reads them there
    (it answered "what is on cannot be read")."""
    tending = EXAMPLE_CELL.parent / "cell-tending"
    async with emulated_cell(tmp_path, "--template", str(tending)) as panel:
        assert await panel.hand("fault robot:local_mode") == "robot: local_mode on"
        listed = await panel.hand("faults")
        assert "robot: local_mode on" in listed and "cannot be read" not in listed, listed
        assert (await panel.hand("fault off robot:local_mode")).startswith("robot: local_mode off")
        listed = await panel.hand("faults")
        assert "robot: nothing on" in listed, listed
