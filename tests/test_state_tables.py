"""The host's state guards every function: every function in every host state, on both
machines. A refusal is the source's result, with no byte on the line; an allowed function
goes to the machine (its bytes, byte-exact for the robot)."""

from __future__ import annotations

import subprocess
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest

from cellctl.drivers.state import StateStore
from cellctl.errors import CellctlError, DeviceError
from cellctl.kinds.dyna2400.driver import CallbackOutput, Dyna2400Mill, MillConfig
from cellctl.kinds.dyna2400.dynalan import parse_program
from cellctl.kinds.dyna2400.states import MILL_HOST_STATES, MillFunction
from cellctl.kinds.ibm7545.aml import compile_source
from cellctl.kinds.ibm7545.driver import Ibm7545Robot, RobotConfig
from cellctl.kinds.ibm7545.records import ProgramFile, Record
from cellctl.kinds.ibm7545.states import RobotFunction
from cellctl.link import MILL_LINE
from cellctl.testing import ScriptedLink, expected_exchange

from .conftest import CELLCTL, emulator_process

XOFF, XON, ACK = b"\x13", b"\x11", b"\x06"
READY = XOFF + XON
PROGRAMS = Path(__file__).resolve().parent.parent / "examples" / "programs"


def execute(operand: bytes, done: bytes = ACK) -> list[tuple[bytes, bytes]]:
    return [(b"X", READY), (operand + b"\r\n", done)]


def read(operand: bytes, record: bytes) -> list[tuple[bytes, bytes]]:
    return [(b"R", READY), (operand + b"\r\n", record), (ACK, b"EG\r\n"), (ACK, b"")]


PROGRAM = ProgramFile.build("DEMO", 1, [Record("D", b"\x01\x02")])
DOWNLOAD_3 = [
    (b"N", ACK),
    (b"090344454D4F20202020A8\r\n", ACK),
    (b"D02010203\r\n", ACK),
    (b"E0000\r\n", ACK),
]

RobotCall = Callable[[Ibm7545Robot], Awaitable[object]]

#: function -> (the call, the bytes of the spec when it goes out)
ROBOT_CALLS: dict[RobotFunction, tuple[RobotCall, list[tuple[bytes, bytes]]]] = {
    RobotFunction.INITIALIZE: (
        lambda r: r.initialize(),
        execute(b"11", XOFF + XON) + execute(b"20"),
    ),
    RobotFunction.RETURN_HOME: (lambda r: r.return_home(), execute(b"11", XOFF + XON)),
    RobotFunction.AUTOSTART: (lambda r: r.auto_mode(), execute(b"20")),
    RobotFunction.DOWNLOAD: (lambda r: r.download(3, PROGRAM), DOWNLOAD_3),
    RobotFunction.GO: (lambda r: r.go(3), execute(b"33") + execute(b"22")),
    RobotFunction.APPLICATION: (lambda r: r.select_application(3), execute(b"33")),
    RobotFunction.START_CYCLE: (lambda r: r.start_cycle(), execute(b"22")),
    RobotFunction.STOP_CYCLE: (lambda r: r.stop(), execute(b"23", XOFF + XON)),
    RobotFunction.HALT_CYCLE: (lambda r: r.halt(), execute(b"23")),
    RobotFunction.MC_STATUS: (lambda r: r.status(), read(b"01", b"D02000000\r\n")),
    RobotFunction.REJECT_STATUS: (lambda r: r.reject_status(), read(b"02", b"D010000\r\n")),
    RobotFunction.DIDO_STATUS: (lambda r: r.io(), read(b"10", b"D040000000000\r\n")),
    RobotFunction.ERRESET: (lambda r: r.reset_errors(), execute(b"24")),
}

#: (function, robot state, partition 3 full) -> the source's result code when refused.
ROBOT_REFUSED = {
    (RobotFunction.GO, 0, False): 3,  # after HALT: "partition empty", as the source
    (RobotFunction.GO, 0, True): 2,  # a stale saved view: still "starting function error"
    **{(RobotFunction.START_CYCLE, 0, full): 2 for full in (False, True)},
    **{(RobotFunction.DOWNLOAD, 0, full): 48 for full in (False, True)},
    # A cycle runs: downloads are for state 1 ("initialized, ready for downloads").
    **{(RobotFunction.DOWNLOAD, 2, full): 48 for full in (False, True)},
    (RobotFunction.GO, 1, False): 3,
    (RobotFunction.GO, 2, False): 3,
    **{(RobotFunction.APPLICATION, state, False): 1 for state in (0, 1, 2)},
}

ROBOT_CASES = [
    (function, state, full)
    for function in RobotFunction
    for state in (0, 1, 2)
    for full in (False, True)
]


@pytest.mark.parametrize(
    ("function", "state", "full"),
    ROBOT_CASES,
    ids=[f"{f.value}-state{s}-{'full' if p else 'empty'}" for f, s, p in ROBOT_CASES],
)
async def test_robot_function_in_host_state(
    tmp_path: Path, function: RobotFunction, state: int, full: bool
) -> None:
    store = StateStore(tmp_path)
    store.save("r1", {"state": state, "partitions": {"3": "DEMO"} if full else {}})
    call, script = ROBOT_CALLS[function]
    refused = ROBOT_REFUSED.get((function, state, full))
    async with expected_exchange([] if refused is not None else script) as link:
        robot = Ibm7545Robot(link, name="r1", store=store, config=RobotConfig(reply_timeout=0.2))
        if refused is None:
            await call(robot)
            return
        with pytest.raises(DeviceError) as err:
            await call(robot)
    assert err.value.code == refused
    assert "host's state" in str(err.value)
    assert link.bytes_sent == 0


async def test_a_refused_download_leaves_its_partition_empty(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    store.save("r1", {"state": 0, "partitions": {"3": "OLD"}})  # a stale view
    async with expected_exchange([]) as link:
        robot = Ibm7545Robot(link, name="r1", store=store)
        with pytest.raises(DeviceError, match="improper startup sequence"):
            await robot.download(3, PROGRAM)
    assert robot.partitions[3] is None
    assert StateStore(tmp_path).load("r1").get("partitions", {}) == {}


def test_go_after_halt_is_partition_empty_at_the_command_line(tmp_path: Path) -> None:
    """The defect: after init, download 3, go 3, stop, halt, `go 3` said "Started Cycle"."""

    def robot(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [*CELLCTL, "--cell", str(tmp_path), "robot", "--link", url, *args],
            capture_output=True,
            text=True,
            timeout=60,
        )

    rec = tmp_path / "p.rec"
    rec.write_text(compile_source("DELAY(0)\nEND", "P", 3).to_text())
    args = ("robot", "--listen", "pty", "--time-scale", "500", "--no-pacing")
    with emulator_process(*args) as url:
        for step in (["init"], ["download", "3", str(rec)], ["go", "3"], ["stop"], ["halt"]):
            done = robot(*step)
            assert done.returncode == 0, (step, done.stdout, done.stderr)
        again = robot("go", "3")
        assert again.returncode == 5, again.stdout
        assert "partition empty (code 3)" in again.stderr
        status = robot("status")
    assert "Partition 3" in status.stdout and "Full" not in status.stdout


# -- the mill ------------------------------------------------------------------------------------


class ModemLink(ScriptedLink):
    """A scripted link (nothing may be sent) with a CTS line the test sets."""

    has_modem_lines = True

    def __init__(self, cts: bool) -> None:
        super().__init__([], MILL_LINE)
        self.level = cts

    async def cts(self) -> bool:
        return self.level


SETUP = PROGRAMS / "cnc1_setup.dyn"
ROUGH = PROGRAMS / "robot_base_rough_cnc1.dyn"
MillCall = Callable[[Dyna2400Mill], Awaitable[object]]
MILL_CALLS: dict[MillFunction, MillCall] = {
    MillFunction.INITIALIZE: lambda m: m.initialize(SETUP),
    MillFunction.INITIALIZE_FORCE: lambda m: m.initialize(SETUP, force=True),
    MillFunction.DOWNLOAD: lambda m: m.download(ROUGH),
    MillFunction.ENDLOAD: lambda m: m.end(),
    MillFunction.STATUS: lambda m: m.status(),
    MillFunction.GO: lambda m: m.go(),
    MillFunction.LOAD: lambda m: m.load(ROUGH),
    MillFunction.LINE_EXECUTE: lambda m: m.line_execute(parse_program("000 GO X 1.000\n")),
    MillFunction.UPLOAD: lambda m: m.upload(timeout=0.01),
}
#: (function, host state) -> the source's result code when refused.
MILL_REFUSED = {
    **{(MillFunction.INITIALIZE, s): 1 for s in ("1 setup", "2", "3", "4")},
    (MillFunction.DOWNLOAD, "0"): 1,
    (MillFunction.DOWNLOAD, "1"): 1,
    **{(MillFunction.DOWNLOAD, s): 2 for s in ("1 setup", "3", "4")},
    **{(f, s): 2 for f in (MillFunction.ENDLOAD, MillFunction.GO) for s in ("3", "4")},
    **{(f, s): 2 for f in (MillFunction.LOAD, MillFunction.LINE_EXECUTE) for s in ("3", "4")},
}
#: CTS as the controller drives it in each state (low: not ready, waiting for NEXT, busy).
MILL_CTS = {"0": False, "1": True, "1 setup": False, "2": True, "3": False, "4": False}
MILL_CASES = [(f, s) for f in MillFunction for s in MILL_HOST_STATES]


@pytest.mark.parametrize(
    ("function", "state"), MILL_CASES, ids=[f"{f.value}-state{s}" for f, s in MILL_CASES]
)
async def test_mill_function_in_host_state(
    tmp_path: Path, function: MillFunction, state: str
) -> None:
    store = StateStore(tmp_path)
    number = int(state[0])
    initialized = state == "1 setup" or number >= 2
    store.save("cnc1", {"state": number, "initialized": initialized, "loaded": "ROUGH"})
    link = ModemLink(MILL_CTS[state])
    config = MillConfig(ready_wait=0.01, accept_timeout=0.01, pace_writes=False)
    mill = Dyna2400Mill(
        link, name="cnc1", store=store, config=config, start_output=CallbackOutput(lambda: None)
    )
    refused = MILL_REFUSED.get((function, state))
    try:
        await MILL_CALLS[function](mill)
    except DeviceError as e:
        if refused is None:
            assert "host's state" not in str(e), e  # the machine's own answer (CTS), not ours
        else:
            assert e.code == refused and "host's state" in str(e), e
            assert link.bytes_sent == 0
            return
    except (CellctlError, AssertionError):
        # Allowed: it went on to the line (the scripted link takes no byte) or timed out.
        assert refused is None, f"{function} in state {state} should be refused"
        return
    assert refused is None, f"{function} in state {state} should be refused"
