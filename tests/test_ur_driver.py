"""The UR driver against the UR emulator through real TCP sockets, and ur-rtde's
RTDEReceiveInterface (an independent client, in its own process) reading the emulator."""

from __future__ import annotations

import asyncio
import json
import random
import re
import sys
from collections.abc import AsyncIterator

import pytest

from cellctl.errors import LinkError, SignalTimeout, UsageError
from cellctl.kinds import registry
from cellctl.kinds.condition import Condition
from cellctl.kinds.families import Robot
from cellctl.kinds.ur.dashboard import RobotMode, RuntimeState, SafetyStatus
from cellctl.kinds.ur.driver import FIELDS, LocalMode, UrOptions, UrRefused, UrRobot, UrStopped
from cellctl.kinds.ur.emulator import UrEmulator
from cellctl.kinds.ur.program import compile_program
from tests.conftest import until

SCALE = 20.0
TEND = """\
def tend_cnc1():
  movej([0.5, -1.2, 1.0, -1.4, -1.57, 0], a=1.4, v=1.05)
  set_standard_digital_out(1, True)
  sleep(0.5)
  movej([0, -1.57, 0, -1.57, 0, 0])
end
"""
LONG = """\
def long_move():
  movej([2.5, -1.57, 0, -1.57, 0, 0], a=0.5, v=0.2)
  set_standard_digital_out(2, True)
end
"""


@pytest.fixture
async def emulator() -> AsyncIterator[UrEmulator]:
    emu = UrEmulator(time_scale=SCALE, programs={"/programs/tend.urp": TEND})
    await emu.start("127.0.0.1")
    yield emu
    await emu.close()


def options(emu: UrEmulator, **extra: object) -> UrOptions:
    return UrOptions(
        secondary_port=emu.ports["secondary"],
        rtde_port=emu.ports["rtde"],
        power_on_timeout=10,
        brake_release_timeout=10,
        **extra,  # type: ignore[arg-type]
    )


@pytest.fixture
async def robot(emulator: UrEmulator) -> AsyncIterator[UrRobot]:
    r = await UrRobot.connect(emulator.dashboard_url, name="ur1", options=options(emulator))
    yield r
    await r.close()


async def test_initialize_runs_a_script_and_a_urp(emulator: UrEmulator, robot: UrRobot) -> None:
    assert isinstance(robot, Robot)
    assert robot.cold and robot.host_status().condition is Condition.NOT_READY
    await robot.initialize()  # power on, brake release, RUNNING
    status = await robot.status()
    assert (status.mode, status.safety, status.runtime) == (
        RobotMode.RUNNING,
        SafetyStatus.NORMAL,
        RuntimeState.STOPPED,
    )
    assert status.remote is True and robot.ready
    # A script kept in the cell: sent on the secondary interface, its end seen through RTDE.
    script = compile_program(TEND, "tend_cnc1", "robot/tend_cnc1.script")
    slot = await robot.ensure_program("tend_cnc1", script)
    await robot.start(slot)
    await robot.wait_end(0, timeout=30)
    assert emulator.controller.runs == ["tend_cnc1"]
    assert (await robot.machine_status()).output(1)
    assert emulator.controller.out_registers[24] >= 1  # the end register the driver added
    # A program on the robot: load and play.
    urp = compile_program("/programs/tend.urp\n", "tend", "robot/tend.urp")
    slot = await robot.ensure_program("tend", urp)
    await robot.start(slot)
    await robot.wait_end(0, timeout=30)
    assert emulator.controller.runs == ["tend_cnc1", "/programs/tend.urp"]
    assert (await robot.status()).loaded == "/programs/tend.urp"


async def test_refusals_in_urs_words(emulator: UrEmulator, robot: UrRobot) -> None:
    with pytest.raises(UrRefused, match=re.escape("File not found: /programs/none.urp")):
        await robot.command("load", "/programs/none.urp")
    with pytest.raises(UrRefused, match="Failed to execute: play") as refused:
        await robot.command("play")
    # No result code of UR's own: its answer and the command, never a "(code 0)".
    assert str(refused.value).endswith("(the robot answered 'Failed to execute: play' to 'play')")
    emulator.set_fault("local_mode")
    with pytest.raises(LocalMode, match="local mode") as local:
        await robot.initialize()
    assert "switch it to remote control" in str(local.value) and "code 0" not in str(local.value)
    assert emulator.controller.mode == RobotMode.POWER_OFF  # nothing acted
    emulator.clear_fault("local_mode")
    await robot.initialize()
    # A pose beyond a UR5e's reach: refused before a byte goes out.
    far = compile_program(
        "def far():\n  movel(p[1.1, 0, 0.2, 0, 0, 0])\nend\n", "far", "far.script"
    )
    with pytest.raises(UsageError, match="out of reach for a UR5e"):
        await robot.ensure_program("far", far)


async def test_protective_stop_stops_the_program_until_the_operator_unlocks(
    emulator: UrEmulator, robot: UrRobot
) -> None:
    await robot.initialize()
    slot = await robot.ensure_program("long", compile_program(LONG, "long_move", "long.script"))
    await robot.start(slot)
    await until(lambda: emulator.controller.runtime == RuntimeState.PLAYING, "the program plays")
    emulator.set_fault("protective_stop")
    with pytest.raises(UrStopped, match="Safetystatus: PROTECTIVE_STOP") as stopped:
        await robot.wait_end(0, timeout=30)
    assert not stopped.value.status.ok
    assert robot.host_status().condition is Condition.ALARM
    # The cell never unlocks by itself: reset_errors closes a popup only.
    await robot.reset_errors()
    assert emulator.controller.safety == SafetyStatus.PROTECTIVE_STOP
    with pytest.raises(UrRefused, match="Cannot unlock protective stop until 5s after occurrence"):
        await robot.unlock_protective_stop()
    await asyncio.sleep(5.0 / SCALE)  # UR's own rule: 5 s (machine time) after the stop
    await robot.unlock_protective_stop()
    await until(lambda: robot._latest_ok(), "RTDE shows the stop unlocked", timeout=10)
    await robot.resume()  # play: the paused program goes on
    robot._current, robot._running = robot._programs[slot], True
    await robot.wait_end(0, timeout=60)
    assert emulator.controller.digital_out(2)


@pytest.mark.parametrize(
    ("fault", "words"),
    [("power_off", "Robotmode: POWER_OFF"), ("estop", "Safetystatus: ROBOT_EMERGENCY_STOP")],
)
async def test_power_off_and_emergency_stop(
    emulator: UrEmulator, robot: UrRobot, fault: str, words: str
) -> None:
    await robot.initialize()
    slot = await robot.ensure_program("long", compile_program(LONG, "long_move", "long.script"))
    await robot.start(slot)
    await until(lambda: emulator.controller.runtime == RuntimeState.PLAYING, "the program plays")
    emulator.set_fault(fault)
    with pytest.raises(UrStopped, match=words):
        await robot.wait_end(0, timeout=30)
    assert str(await robot.machine_status()) == words
    assert robot.cold and robot.needs_initialize(UrRefused("play", words, "x"))


async def test_a_wait_cut_short_and_asked_again_sees_the_end(emulator: UrEmulator) -> None:
    """The cell waits for a cycle in slices while its doors open: a wait that ran out while
    the program played, asked again after the program ended, sees the end by the runtime
    state (no end register here): it knows the program played, and does not take it for a
    program that never started."""
    robot = await UrRobot.connect(
        emulator.dashboard_url, name="ur1", options=options(emulator, end_register=None)
    )
    try:
        await robot.initialize()
        slot = await robot.ensure_program("tend", compile_program(TEND, "tend_cnc1", "t.script"))
        await robot.start(slot)
        await until(lambda: emulator.controller.runtime == RuntimeState.PLAYING, "it plays")
        with pytest.raises(SignalTimeout, match=re.escape("did not end within 0.01 s")):
            await robot.wait_end(0, timeout=0.01)
        await until(lambda: emulator.controller.runtime == RuntimeState.STOPPED, "it ends")
        await robot.wait_end(0, timeout=10 * robot.options.start_timeout)
        assert emulator.controller.digital_out(1) and not robot.running
    finally:
        await robot.close()


async def test_a_program_that_never_ends_and_a_dropped_connection(
    emulator: UrEmulator, robot: UrRobot
) -> None:
    await robot.initialize()
    emulator.set_fault("never_ends")
    slot = await robot.ensure_program("tend", compile_program(TEND, "tend_cnc1", "t.script"))
    await robot.start(slot)
    with pytest.raises(
        SignalTimeout, match=re.escape("did not end within 1 s (programState PLAYING)")
    ):
        await robot.wait_end(0, timeout=1)
    await robot.stop()
    emulator.set_fault("drop")
    await until(lambda: robot.link.closed and robot.rtde_error is not None, "the drop is seen")
    with pytest.raises(LinkError):
        await robot.machine_status()


async def test_rtde_refuses_unknown_fields_and_too_high_a_frequency(emulator: UrEmulator) -> None:
    from cellctl.kinds.ur import rtde

    reader, writer = await asyncio.open_connection("127.0.0.1", emulator.ports["rtde"])

    async def ask(packet_type: int, payload: bytes) -> tuple[int, bytes]:
        writer.write(rtde.encode(packet_type, payload))
        async with asyncio.timeout(5):
            header = await reader.readexactly(3)
        async with asyncio.timeout(5):
            body = await reader.readexactly(rtde.HEADER.unpack(header)[0] - 3)
        return rtde.decode(header + body)[:2]

    t = rtde.PacketType
    assert await ask(t.REQUEST_PROTOCOL_VERSION, rtde.request_protocol_version(3)) == (
        t.REQUEST_PROTOCOL_VERSION,
        b"\x00",
    )
    assert await ask(t.REQUEST_PROTOCOL_VERSION, rtde.request_protocol_version(2)) == (
        t.REQUEST_PROTOCOL_VERSION,
        b"\x01",
    )
    names = ["actual_q", "no_such_field"]
    got, reply = await ask(t.SETUP_OUTPUTS, rtde.setup_outputs_payload(125.0, names))
    assert rtde.parse_setup_reply(reply, names).refused() == ["no_such_field (NOT_FOUND)"]
    got, _ = await ask(t.SETUP_OUTPUTS, rtde.setup_outputs_payload(1000.0, ["actual_q"]))
    assert got == t.TEXT_MESSAGE
    writer.close()


async def test_rtde_packages_late_are_sent_not_skipped(emulator: UrEmulator) -> None:
    """The stream keeps its schedule (package k due at start + k/frequency): after the loop
    stalls, the packages it was late for all come, each stamped with its own cycle."""
    import itertools
    import time

    from cellctl.kinds.ur import rtde

    reader, writer = await asyncio.open_connection("127.0.0.1", emulator.ports["rtde"])

    async def packet() -> tuple[int, bytes]:
        async with asyncio.timeout(5):
            header = await reader.readexactly(3)
        async with asyncio.timeout(5):
            body = await reader.readexactly(rtde.HEADER.unpack(header)[0] - 3)
        return rtde.decode(header + body)[:2]

    t = rtde.PacketType
    names = ["timestamp", "robot_mode"]
    writer.write(rtde.encode(t.REQUEST_PROTOCOL_VERSION, rtde.request_protocol_version(2)))
    assert await packet() == (t.REQUEST_PROTOCOL_VERSION, b"\x01")
    writer.write(rtde.encode(t.SETUP_OUTPUTS, rtde.setup_outputs_payload(125.0, names)))
    got, reply = await packet()
    recipe = rtde.parse_setup_reply(reply, names)
    writer.write(rtde.encode(t.START, b""))
    assert (await packet())[0] == t.START
    stamps: list[float] = []
    while len(stamps) < 40:
        got, body = await packet()
        assert got == t.DATA_PACKAGE
        stamps.append(rtde.unpack_data(recipe, body)["timestamp"])
        if len(stamps) == 5:
            # The whole event loop stalls, as on a loaded box: 25 cycles late at once.
            time.sleep(0.2)  # noqa: ASYNC251
    writer.close()
    steps = [b - a for a, b in itertools.pairwise(stamps)]
    assert steps == [pytest.approx(1 / 125.0)] * len(steps), steps


# -- an independent client: ur-rtde's RTDEReceiveInterface ----------------------------------------

CLIENT = """
import json, sys, time
import rtde_receive
fields = sys.argv[2].split(",")
r = rtde_receive.RTDEReceiveInterface(sys.argv[1], 125.0, fields)
deadline = time.monotonic() + 10
while r.getTimestamp() <= 0 and time.monotonic() < deadline:
    time.sleep(0.01)
print(json.dumps({
    "q": r.getActualQ(),
    "robot_mode": r.getRobotMode(),
    "safety_mode": r.getSafetyMode(),
    "safety_bits": r.getSafetyStatusBits(),
    "protective_stopped": r.isProtectiveStopped(),
    "runtime_state": r.getRuntimeState(),
    "inputs": r.getActualDigitalInputBits(),
    "outputs": r.getActualDigitalOutputBits(),
    "timestamp": r.getTimestamp(),
}))
r.disconnect()
"""


async def test_ur_rtde_reads_the_fields_the_driver_relies_on() -> None:
    pytest.importorskip("rtde_receive", reason="ur-rtde is in the dev extra (Python < 3.13)")
    # ur-rtde's receive interface connects to port 30004 only: a loopback address of its own
    # (127.x.y.z all reach this machine) keeps parallel tests apart.
    host = f"127.{random.randrange(1, 250)}.{random.randrange(1, 250)}.{random.randrange(2, 250)}"
    emu = UrEmulator(time_scale=SCALE)
    await emu.start(host, rtde_port=30004)
    try:
        c = emu.controller
        c.mode = RobotMode.RUNNING
        c.set_input(3, True)
        c.set_digital_out(5, True)
        c.set_fault("protective_stop")
        c.runtime = RuntimeState.PAUSED
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-c", CLIENT, host, ",".join(FIELDS),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        async with asyncio.timeout(30):
            out, err = await proc.communicate()
        assert proc.returncode == 0, err.decode()
        seen = json.loads(out.decode().strip().splitlines()[-1])
    finally:
        await emu.close()
    assert seen["q"] == pytest.approx(list(c.q))
    assert seen["robot_mode"] == RobotMode.RUNNING
    assert seen["safety_mode"] == SafetyStatus.PROTECTIVE_STOP
    assert seen["protective_stopped"] is True
    assert seen["runtime_state"] == RuntimeState.PAUSED
    assert seen["inputs"] == 1 << 3 and seen["outputs"] == 1 << 5
    assert seen["timestamp"] > 0


def test_registered_through_the_registry() -> None:
    kind = registry.kind("ur")
    assert kind.family == "robot" and kind.origin is not None
    assert kind.states.words(7) == "RUNNING"
    assert "protective_stop" in kind.faults
    assert [f.name for f in kind.menu()] == [  # type: ignore[misc]
        "status", "init", "unlock", "close_safety_popup", "play", "pause", "stop", "power_off",
    ]  # fmt: skip
