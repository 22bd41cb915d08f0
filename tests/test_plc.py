"""The cell PLC: IO map parsing, and the driver against the emulator over Modbus/TCP on loopback."""

from __future__ import annotations

import asyncio
import gc
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from cellctl.drivers.plc import ModbusPlc
from cellctl.emulators.plc import FAULTS, PlcEmulator, PlcTiming
from cellctl.errors import (
    DeviceError,
    LinkClosed,
    LinkError,
    LinkTimeout,
    SignalTimeout,
    UsageError,
)
from cellctl.protocol.plc import (
    DEFAULT_COILS,
    DEFAULT_INPUTS,
    SIGNALS,
    PlcMap,
    canonical,
    describe,
    parse_modbus_url,
)
from cellctl.ui.cli import main

from .conftest import free_port, refusing_port

TIME_SCALE = 200.0  # conveyor 8 s -> 40 ms, door 2 s -> 10 ms
WAIT = 5.0  # generous deadline for events that do happen


# -- the IO map ---------------------------------------------------------------------------------


def full_table() -> dict[str, Any]:
    return {
        "url": "modbus://10.0.0.9",
        "unit": 3,
        "coils": {name: 100 + a for name, a in DEFAULT_COILS.items()},
        "inputs": {name: 200 + a for name, a in DEFAULT_INPUTS.items()},
    }


def test_default_map_names_every_signal_once() -> None:
    plc_map = PlcMap()
    assert set(plc_map.coils) | set(plc_map.inputs) == set(SIGNALS)
    assert len(set(plc_map.coils.values())) == len(plc_map.coils)
    assert len(set(plc_map.inputs.values())) == len(plc_map.inputs)
    assert describe("door[1]") == "door of CNC 1: 1 = open, 0 = close"
    assert PlcMap.from_toml({}) == plc_map


def test_map_from_toml_reads_addresses_url_and_unit() -> None:
    plc_map = PlcMap.from_toml(full_table())
    assert plc_map.coils["go_2"] == 100 + DEFAULT_COILS["go_2"]
    assert plc_map.inputs["estop_ok"] == 200 + DEFAULT_INPUTS["estop_ok"]
    assert plc_map.unit == 3
    assert parse_modbus_url(plc_map.url) == ("10.0.0.9", 502)
    assert plc_map.input_block == (200, len(DEFAULT_INPUTS))


def test_map_accepts_indexed_names() -> None:
    table = full_table()
    table["coils"]["clamp[1]"] = table["coils"].pop("clamp_1")
    assert PlcMap.from_toml(table).coils["clamp_1"] == 100 + DEFAULT_COILS["clamp_1"]
    assert canonical("door_open[2]") == "door_open_2"
    assert canonical("go1") == "go_1"


def test_map_optional_inputs_may_be_left_out() -> None:
    table = full_table()
    del table["inputs"]["part_present_1"]
    plc_map = PlcMap.from_toml(table)
    assert "part_present_1" not in plc_map.inputs
    with pytest.raises(UsageError, match="not wired"):
        plc_map.address("part_present_1")


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda t: t["coils"].update(conveyor_speed=20), r"coils\.conveyor_speed: unknown coil"),
        (lambda t: t["inputs"].update(door_1=40), r"inputs\.door_1: unknown input \(that is a"),
        (lambda t: t["coils"].update(go_2=100), r"coils\.go_2: address 100 is already"),
        (lambda t: t["inputs"].pop("door_closed_2"), r"inputs: missing door_closed_2"),
        (lambda t: t["coils"].pop("pallet_request"), r"coils: missing pallet_request"),
        (lambda t: t["coils"].update(go_1=-1), r"coils\.go_1: address must be 0\.\.65535"),
        (lambda t: t["coils"].update(go_1="7"), r"coils\.go_1: address must be"),
        (lambda t: t.update(url="http://plc"), r"PLC address 'http://plc'"),
        (lambda t: t.update(unit=300), r"unit: must be 0\.\.255"),
        (lambda t: t.update(timeout=0), r"timeout: must be seconds > 0"),
        (lambda t: t.update(adress="x"), r"\[plc\] adress: unknown key"),
        (lambda t: t["inputs"].update(estop_ok=5000), r"span more than 2000"),
    ],
)
def test_map_refuses_bad_tables_naming_the_key(change: Any, words: str) -> None:
    table = full_table()
    change(table)
    with pytest.raises(UsageError, match=words):
        PlcMap.from_toml(table)


# -- driver against the emulator ----------------------------------------------------------------


@pytest.fixture
async def emulator() -> AsyncIterator[PlcEmulator]:
    plc = PlcEmulator(time_scale=TIME_SCALE)
    await plc.start("modbus://127.0.0.1:0")
    yield plc
    await plc.close()


@pytest.fixture
async def plc(emulator: PlcEmulator) -> AsyncIterator[ModbusPlc]:
    # Loopback answers in milliseconds: the deadline leaves room for a loaded test box.
    driver = await ModbusPlc.connect(emulator.url, emulator.map, timeout=3.0)
    yield driver
    await driver.close()


async def test_emulator_reports_the_bound_port(emulator: PlcEmulator) -> None:
    host, port = parse_modbus_url(emulator.url)
    assert host == "127.0.0.1"
    assert port != 0


async def test_inputs_at_power_up(plc: ModbusPlc) -> None:
    inputs = await plc.read_inputs()
    assert set(inputs) == set(DEFAULT_INPUTS)
    on = {name for name, level in inputs.items() if level}
    assert on == {"outfeed_clear", "door_closed_1", "door_closed_2", "estop_ok"}
    assert await plc.read_coils() == dict.fromkeys(DEFAULT_COILS, False)


@pytest.mark.parametrize("name", list(DEFAULT_COILS))
async def test_every_coil_reaches_the_plc(emulator: PlcEmulator, plc: ModbusPlc, name: str) -> None:
    changes: list[tuple[str, bool]] = []
    emulator.hooks.coil.append(lambda n, v: changes.append((n, v)))
    await plc.write(name, True)
    assert (await plc.read_coils())[name] is True
    assert emulator.coils[name] is True
    await plc.write(f"{name[:-2]}[{name[-1]}]" if name[-1].isdigit() else name, False)
    assert await plc.read(name) is False
    assert changes == [(name, True), (name, False)]


@pytest.mark.parametrize("name", list(DEFAULT_INPUTS))
async def test_every_input_reaches_the_driver(
    emulator: PlcEmulator, plc: ModbusPlc, name: str
) -> None:
    before = (await plc.read_inputs())[name]
    emulator.set_input(name, not before)
    inputs = await plc.wait_for(name, not before, timeout=WAIT)
    assert inputs[name] is (not before)
    assert await plc.read(name) is (not before)


async def test_conveyor_delivers_on_request_and_takes_the_pallet_away(
    emulator: PlcEmulator, plc: ModbusPlc
) -> None:
    seen: list[tuple[str, bool]] = []
    emulator.hooks.input.append(lambda n, v: seen.append((n, v)))
    await plc.write("pallet_request", True)
    await plc.wait_for("pallet_present", True, timeout=WAIT)
    await plc.write("pallet_request", False)
    assert emulator.pallets_delivered == 1

    await plc.pulse("pallet_release", 0.01)
    await plc.wait_for("pallet_present", False, timeout=WAIT)
    await plc.wait_for("outfeed_clear", True, timeout=WAIT)
    assert seen == [
        ("pallet_present", True),
        ("pallet_present", False),
        ("outfeed_clear", False),
        ("outfeed_clear", True),
    ]
    assert emulator.pallets_released == 1


async def test_robot_taking_the_pallet_clears_the_pickup(
    emulator: PlcEmulator, plc: ModbusPlc
) -> None:
    await plc.pulse("pallet_request", 0.01)
    await plc.wait_for("pallet_present", True, timeout=WAIT)
    emulator.take_pallet()
    await plc.wait_for("pallet_present", False, timeout=WAIT)
    # A second request brings the next pallet.
    await plc.pulse("pallet_request", 0.01)
    await plc.wait_for("pallet_present", True, timeout=WAIT)
    assert emulator.pallets_delivered == 2


@pytest.mark.parametrize("mill", [1, 2])
async def test_vise_clamps_and_unclamps(plc: ModbusPlc, mill: int) -> None:
    await plc.write(f"clamp_{mill}", True)
    await plc.wait_for(f"clamp_closed_{mill}", True, timeout=WAIT)
    await plc.write(f"clamp_{mill}", False)
    inputs = await plc.wait_for(f"clamp_closed_{mill}", False, timeout=WAIT)
    assert inputs[f"clamp_closed_{mill}"] is False


@pytest.mark.parametrize("mill", [1, 2])
async def test_door_opens_and_closes_never_reporting_both(
    emulator: PlcEmulator, plc: ModbusPlc, mill: int
) -> None:
    both: list[bool] = []
    emulator.hooks.input.append(
        lambda n, v: both.append(
            emulator.inputs[f"door_open_{mill}"] and emulator.inputs[f"door_closed_{mill}"]
        )
    )
    await plc.write(f"door_{mill}", True)
    inputs = await plc.wait_for(f"door_open_{mill}", True, timeout=WAIT)
    assert inputs[f"door_closed_{mill}"] is False
    await plc.write(f"door_{mill}", False)
    inputs = await plc.wait_for(f"door_closed_{mill}", True, timeout=WAIT)
    assert inputs[f"door_open_{mill}"] is False
    assert both and not any(both)


@pytest.mark.parametrize("mill", [1, 2])
async def test_go_pulse_reaches_on_go(mill: int) -> None:
    got: asyncio.Queue[int] = asyncio.Queue()
    async with PlcEmulator(time_scale=TIME_SCALE, on_go=got.put_nowait) as emulator:
        await emulator.start()
        async with await ModbusPlc.connect(emulator.url, timeout=1.0) as plc:
            await plc.pulse(f"go_{mill}", 0.01)
            async with asyncio.timeout(WAIT):
                assert await got.get() == mill
            assert (await plc.read_coils())[f"go_{mill}"] is False
    assert emulator.go_count == {mill: 1, 3 - mill: 0}


# -- fault switches -----------------------------------------------------------------------------


async def test_drop_cuts_the_line_and_refuses_until_cleared(
    emulator: PlcEmulator, plc: ModbusPlc
) -> None:
    await plc.read_inputs()
    emulator.set_fault("drop")
    with pytest.raises(LinkError):
        await plc.read_inputs()
    with pytest.raises(LinkError):
        await plc.read_inputs()  # reconnecting is refused too
    emulator.clear_fault("drop")
    assert (await plc.read_inputs())["estop_ok"] is True


async def test_drop_refuses_a_new_connection(emulator: PlcEmulator) -> None:
    emulator.set_fault("drop")
    driver = await ModbusPlc.connect(emulator.url, timeout=0.5)
    with pytest.raises(LinkClosed, match="closed the connection"):
        await driver.read_inputs()
    await driver.close()


async def test_silent_gives_a_timeout_then_recovers(emulator: PlcEmulator) -> None:
    async with await ModbusPlc.connect(emulator.url, timeout=0.2) as plc:
        emulator.set_fault("silent")
        with pytest.raises(LinkTimeout, match=r"no answer to reading inputs 0\.\.10 within 0\.2 s"):
            await plc.read_inputs()
        emulator.clear_fault("silent")
        assert (await plc.read_inputs())["estop_ok"] is True


async def test_a_long_silence_then_the_plc_answers_again(emulator: PlcEmulator) -> None:
    """More unanswered requests than pymodbus tolerates on one connection (it gives up on it
    by itself after three): once the PLC answers again, so does the driver."""
    async with await ModbusPlc.connect(emulator.url, timeout=0.2) as plc:
        emulator.set_fault("silent")
        for _ in range(6):
            with pytest.raises(LinkTimeout):
                await plc.read_inputs()
        emulator.clear_fault("silent")
        # Three answers in a row, within a deadline: a driver that stayed wedged never gets
        # them. (0.2 s per request keeps the silent part short; on a loaded box an answer
        # may come later than that now and then, which starts the count again.)
        answered = 0
        async with asyncio.timeout(60):
            while answered < 3:
                try:
                    inputs = await plc.read_inputs()
                except LinkTimeout:
                    answered = 0
                    continue
                assert inputs["estop_ok"] is True
                answered += 1


async def test_stuck_door_times_out_in_words(emulator: PlcEmulator, plc: ModbusPlc) -> None:
    emulator.set_fault("stuck-door", "1")
    assert emulator.onsets.get("stuck-door") is None  # armed: nothing shows until it is told
    await plc.write("door_1", True)
    assert emulator.onsets.get("stuck-door") is not None
    with pytest.raises(SignalTimeout, match=r"^door of CNC 1 did not leave its closed position"):
        await plc.wait_for("door_closed_1", False, timeout=0.1)
    with pytest.raises(LinkTimeout, match=r"^door of CNC 1 did not open within 0\.3 s$"):
        await plc.wait_for("door_open_1", True, timeout=0.3)
    await plc.write("door_2", True)
    await plc.wait_for("door_open_2", True, timeout=WAIT)  # the other door still moves
    emulator.clear_fault("stuck-door")
    await plc.wait_for("door_open_1", True, timeout=WAIT)


async def test_stuck_door_mid_way_reports_neither_end(
    emulator: PlcEmulator, plc: ModbusPlc
) -> None:
    def stick_as_it_leaves(name: str, value: bool) -> None:
        if name == "door_closed_2" and not value:
            # Once the PLC has set it moving (its arrival timed): it stops there, however
            # late this test's next line would run on a loaded box.
            asyncio.get_running_loop().call_soon(emulator.set_fault, "stuck-door", "2")

    emulator.hooks.input.append(stick_as_it_leaves)
    await plc.write("door_2", True)
    with pytest.raises(LinkTimeout, match="door of CNC 2 did not close"):
        await plc.wait_for("door_closed_2", True, timeout=0.1)
    inputs = await plc.read_inputs()
    assert (inputs["door_open_2"], inputs["door_closed_2"]) == (False, False)


async def test_no_pallet_times_out_then_delivers_once_cleared(
    emulator: PlcEmulator, plc: ModbusPlc
) -> None:
    emulator.set_fault("no-pallet")
    assert emulator.onsets.get("no-pallet") is None
    await plc.write("pallet_request", True)
    assert emulator.onsets.get("no-pallet") is not None  # the request it ignores
    with pytest.raises(LinkTimeout, match="no pallet arrived at the conveyor pick-up within"):
        await plc.wait_for("pallet_present", True, timeout=0.3)
    emulator.clear_fault("no-pallet")
    await plc.write("pallet_request", False)
    await plc.write("pallet_request", True)
    await plc.wait_for("pallet_present", True, timeout=WAIT)


async def test_estop_drops_estop_ok_freezes_actuators_and_blocks_go(
    emulator: PlcEmulator, plc: ModbusPlc
) -> None:
    emulator.set_fault("estop")
    inputs = await plc.wait_for("estop_ok", False, timeout=WAIT)
    assert inputs["estop_ok"] is False
    await plc.pulse("go_1", 0.01)
    assert emulator.go_count[1] == 0
    await plc.write("clamp_1", True)
    with pytest.raises(LinkTimeout, match="vise of CNC 1 did not clamp"):
        await plc.wait_for("clamp_closed_1", True, timeout=0.2)
    emulator.clear_fault("estop")
    await plc.wait_for("estop_ok", True, timeout=WAIT)
    await plc.wait_for("clamp_closed_1", True, timeout=WAIT)


def test_fault_switches_are_checked() -> None:
    plc = PlcEmulator()
    assert set(FAULTS) == {"drop", "silent", "stuck-door", "no-pallet", "estop", "slow"}
    with pytest.raises(UsageError, match="unknown fault"):
        plc.set_fault("flood")
    with pytest.raises(UsageError, match="stuck-door needs a mill number 1 or 2, not '3'"):
        plc.set_fault("stuck-door", "3")
    with pytest.raises(UsageError, match=r"stuck-door needs a mill number 1 or 2: stuck-door=1$"):
        plc.set_fault("stuck-door")
    for bad in ("fast", "-5", "nan", "1e9"):
        with pytest.raises(UsageError, match="slow takes milliseconds from 0 to 60000"):
            plc.set_fault("slow", bad)
    assert "slow" not in plc.faults


async def test_slow_holds_each_answer_back_over_modbus_tcp(
    emulator: PlcEmulator, plc: ModbusPlc
) -> None:
    await plc.read_inputs()
    emulator.set_fault("slow", "300")
    started = time.monotonic()
    inputs = await plc.read_inputs()
    assert time.monotonic() - started >= 0.3  # held back: never sooner
    assert inputs == await plc.read_inputs()  # late, and the same answer
    emulator.clear_fault("slow")


# -- typed errors -------------------------------------------------------------------------------


async def test_unknown_names_refused_before_any_request(
    emulator: PlcEmulator, plc: ModbusPlc
) -> None:
    await plc.read_inputs()
    served, sent = emulator.requests_served, plc.requests
    with pytest.raises(UsageError, match="no PLC signal 'conveyor'"):
        await plc.write("conveyor", True)
    with pytest.raises(UsageError, match="pallet_present is an input"):
        await plc.write("pallet_present", True)
    with pytest.raises(UsageError, match="door_1 is a coil"):
        await plc.wait_for("door_1", True, timeout=1)
    with pytest.raises(UsageError, match="no PLC signal"):
        await plc.read("door_3")
    with pytest.raises(UsageError, match="pulse length"):
        await plc.pulse("go_1", 0)
    assert (emulator.requests_served, plc.requests) == (served, sent)


async def test_modbus_exception_is_a_device_error(emulator: PlcEmulator) -> None:
    table = full_table()
    table["coils"] = dict(DEFAULT_COILS)
    table["inputs"] = {**DEFAULT_INPUTS, "part_present_2": 300}  # beyond the PLC's inputs
    wrong = PlcMap.from_toml(table)
    async with await ModbusPlc.connect(emulator.url, wrong, timeout=1.0) as plc:
        with pytest.raises(DeviceError, match="illegal data address") as info:
            await plc.read_inputs()
        assert info.value.code == 2
        await plc.write("go_1", True)  # the coils are where the PLC has them: still fine
        assert emulator.coils["go_1"] is True


async def test_connection_refused_is_a_link_error() -> None:
    with refusing_port() as held, pytest.raises(LinkError, match="cannot reach the PLC"):
        await ModbusPlc.connect(f"modbus://127.0.0.1:{held.getsockname()[1]}", timeout=1.0)


async def test_closed_driver_says_so(plc: ModbusPlc) -> None:
    await plc.close()
    with pytest.raises(LinkClosed, match="closed"):
        await plc.read_inputs()


async def test_custom_map_serves_and_drives_the_same_signals() -> None:
    plc_map = PlcMap.from_toml(full_table())
    timing = PlcTiming(clamp_s=0.1)
    async with PlcEmulator(plc_map, time_scale=TIME_SCALE, timing=timing) as emulator:
        await emulator.start()
        async with await ModbusPlc.connect(emulator.url, plc_map, timeout=1.0) as plc:
            await plc.write("clamp_2", True)
            inputs = await plc.wait_for("clamp_closed_2", True, timeout=WAIT)
            assert inputs["estop_ok"] is True
            assert emulator.coils["clamp_2"] is True


# -- command line -------------------------------------------------------------------------------


def test_cli_emulate_plc_then_status_set_and_pulse(tmp_path: Path) -> None:
    url = f"modbus://127.0.0.1:{free_port()}"
    cellctl = [sys.executable, "-c", "from cellctl.ui.cli import main; main()"]
    proc = subprocess.Popen(
        [*cellctl, "--cell", str(tmp_path), "emulate", "plc", "--listen", url, "--time-scale", "9"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert proc.stdout is not None
        assert f"listening on {url}" in proc.stdout.readline()
        runner = CliRunner()
        base = ["--cell", str(tmp_path), "plc", "--url", url]
        done = runner.invoke(main, [*base, "set", "door[2]", "1"])
        assert done.exit_code == 0, done.output
        done = runner.invoke(main, [*base, "pulse", "go_1", "--seconds", "0.05"])
        assert done.exit_code == 0, done.output
        done = runner.invoke(main, [*base, "status"])
        assert done.exit_code == 0, done.output
        assert re.search(r"door_2 +1 +@5 +door of CNC 2: 1 = open", done.output)
        assert re.search(r"go_1 +0 ", done.output)
        refused = runner.invoke(main, [*base, "set", "pallet_present", "1"])
        assert refused.exit_code == 2
        assert "pallet_present is an input" in refused.output
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=10)
    assert "PLC emulator stopped" in out


def test_cli_reads_the_map_from_cell_toml(tmp_path: Path) -> None:
    with refusing_port() as held:
        cli_reads_the_map_from(tmp_path, held.getsockname()[1])


def cli_reads_the_map_from(tmp_path: Path, port: int) -> None:
    (tmp_path / "cell.toml").write_text(
        f'[plc]\nurl = "modbus://127.0.0.1:{port}"\ntimeout = 0.5\n'
        "coils = { pallet_request = 0, door_1 = 1 }\n"
    )
    done = CliRunner().invoke(main, ["--cell", str(tmp_path), "plc", "status"])
    assert done.exit_code == 2
    assert "coils: missing pallet_release" in done.output
    (tmp_path / "cell.toml").write_text(f'[plc]\nurl = "modbus://127.0.0.1:{port}"\n')
    done = CliRunner().invoke(main, ["--cell", str(tmp_path), "plc", "status"])
    assert done.exit_code == 3  # nothing listens there: a link error, said once
    assert f"cannot reach the PLC at modbus://127.0.0.1:{port}" in done.output


# -- what a failure leaves behind ---------------------------------------------------------------


async def test_a_timed_out_request_leaves_no_unretrieved_failure(emulator: PlcEmulator) -> None:
    """The request that timed out is ended by the driver and its outcome taken: asyncio has
    nothing to report as "Task exception was never retrieved" once it is collected."""
    loop = asyncio.get_running_loop()
    reported: list[str] = []
    previous = loop.get_exception_handler()
    loop.set_exception_handler(lambda _loop, context: reported.append(context["message"]))
    try:
        async with await ModbusPlc.connect(emulator.url, timeout=0.2) as plc:
            emulator.set_fault("silent")
            for _ in range(2):
                with pytest.raises(LinkTimeout):
                    await plc.read_inputs()
            emulator.clear_fault("silent")
            # A whole exchange on the next connection: the loop has run the old one's end.
            assert (await plc.read_inputs())["estop_ok"] is True
        gc.collect()
    finally:
        loop.set_exception_handler(previous)
    assert reported == []


async def test_a_pulse_whose_end_was_lost_still_makes_an_edge(emulator: PlcEmulator) -> None:
    """A pulse cut short by a PLC that stopped answering may leave its coil high; the next
    pulse lowers it first, so the PLC sees a rising edge again (a GO, a pallet request)."""
    async with await ModbusPlc.connect(emulator.url, timeout=0.3) as plc:
        raised = asyncio.Event()
        emulator.hooks.coil.append(lambda name, value: raised.set() if value else None)
        pulse = asyncio.ensure_future(plc.pulse("go_1", 0.5))
        async with asyncio.timeout(WAIT):
            await raised.wait()
        emulator.set_fault("silent")  # the lowering goes unanswered
        with pytest.raises(LinkTimeout):
            await pulse
        emulator.clear_fault("silent")
        assert emulator.coils["go_1"] is True and emulator.go_count[1] == 1
        await plc.pulse("go_1", 0.01)
        assert emulator.go_count[1] == 2
        assert (await plc.read_coils())["go_1"] is False
