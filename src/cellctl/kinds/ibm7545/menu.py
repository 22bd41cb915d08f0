"""The IBM 7545/7547's manual functions: the source's robot menu, then the tool-kit's extras."""

from __future__ import annotations

from typing import Any

from pydantic import field_validator

from cellctl.kinds.ibm7545.driver import Ibm7545Robot
from cellctl.kinds.ibm7545.records import PARTITIONS, ProgramFile
from cellctl.kinds.menu import (
    MachineFunction,
    NoParams,
    Params,
    Prepared,
    ProgramParams,
    Progress,
    ok,
)


def _in_range(value: int, result: str) -> int:
    """``value`` if it is a partition; else refused, naming the source's ``result``."""
    if value not in PARTITIONS:
        raise ValueError(f"partition must be 1 to 5, not {value} ({result})")
    return value


class PartitionParams(Params):
    """A partition for DOWNLOAD (the source's result 2: "partition error")."""

    partition: int

    @field_validator("partition")
    @classmethod
    def _partition(cls, value: int) -> int:
        return _in_range(value, "partition error")


class GoParams(Params):
    """A partition for GO (the source's result 2: "starting function error")."""

    partition: int

    @field_validator("partition")
    @classmethod
    def _partition(cls, value: int) -> int:
        return _in_range(value, "starting function error")


class RobotDownloadParams(PartitionParams, ProgramParams):
    pass


class InputParams(Params):
    input: int
    on: bool

    @field_validator("input")
    @classmethod
    def _input(cls, value: int) -> int:
        if not 1 <= value <= 16:
            raise ValueError(f"input must be 1 to 16, not {value}")
        return value


def _parse_records(params: Any) -> ProgramFile:
    return ProgramFile.parse(params.text, params.program)


async def _robot_init(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.return_home()
    await r.auto_mode()
    return ok("Initializing was correct", lines=["returning home", "Set on Auto mode"])


async def _robot_download(
    r: Ibm7545Robot, p: Prepared, progress: Progress | None
) -> dict[str, Any]:
    program: ProgramFile = p.parsed
    # "retry 2/3" once a transmission error made the driver send the program again.
    retry = {"text": ""}

    def report(done: int, total: int, sent: int) -> None:
        if progress is not None:
            progress(
                {
                    "records": done,
                    "records_total": total,
                    "bytes_sent": sent,
                    "retry": retry["text"],
                }
            )

    def on_retry(attempt: int, limit: int, error: Exception) -> None:
        retry["text"] = f"{attempt}/{limit}"
        report(0, len(program.records), 0)

    await r.download(p.params.partition, program, progress=report, on_retry=on_retry)
    return ok(
        "Download was correct",
        partition=p.params.partition,
        name=program.name,
        records=len(program.records),
    )


async def _robot_go(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.go(p.params.partition)
    return ok("Started Cycle", partition=p.params.partition)


async def _robot_stop(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.stop()
    return ok("Cycle stopped", lines=["Stopping Cycle"])


async def _robot_halt(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.halt()
    return ok("Halted: robot uninitialized, every partition must be downloaded again")


async def _robot_status(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    st = await r.status(waits=True)
    partitions = {str(n): prog for n, prog in st.partitions.items()}
    return ok(
        f"robot state {st.state} ({st.state_text})",
        name=r.name,
        state=st.state,
        state_text=st.state_text,
        machine_status=str(st.machine),
        status_bytes=f"{st.machine.flags:02X} {st.machine.data_error:02X}",
        partitions=partitions,
        waiting=[{"input": n, "on": v} for n, v in st.waiting],
        lines=st.lines(),
    )


async def _robot_reject(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    code, message = await r.reject_status()
    return ok(f"Reject status {code}: {message}", code=code, text=message)


async def _robot_io(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    dido = await r.io()
    inputs = [dido.input(n) for n in range(1, 17)]
    outputs = [dido.output(n) for n in range(1, 17)]
    return ok(
        "DI "
        + "".join("1" if x else "." for x in inputs)
        + "  DO "
        + "".join("1" if x else "." for x in outputs),
        name=r.name,
        inputs=inputs,
        outputs=outputs,
    )


async def _robot_io_set(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.set_input(p.params.input, p.params.on)
    word = "on" if p.params.on else "off"
    return ok(f"input {p.params.input} {word}", input=p.params.input, on=p.params.on)


async def _robot_reset(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.reset_errors()
    return ok("Errors reset")


async def _robot_home(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.return_home()
    return ok("Home", lines=["returning home"])


MENU: tuple[MachineFunction, ...] = (
    MachineFunction("robot", "init", "INITIALIZE", 1, "Return home, then auto mode.",
                    NoParams, _robot_init),
    MachineFunction("robot", "download", "DOWNLOAD", 2,
                    "Download a compiled program (.rec) into a partition.",
                    RobotDownloadParams, _robot_download, prepare=_parse_records),
    MachineFunction("robot", "go", "GO", 3, "Run the program in a partition.",
                    GoParams, _robot_go),
    MachineFunction("robot", "status", "STATUS", 4,
                    "Robot state, status bytes, partitions Full/Empty.", NoParams, _robot_status,
                    observes=True),
    MachineFunction("robot", "stop", "STOP", 5, "Stop the cycle.", NoParams, _robot_stop),
    MachineFunction("robot", "halt", "HALT", 6,
                    "Stop and treat the robot as uninitialized.", NoParams, _robot_halt),
    MachineFunction("robot", "reject", "REJECT STATUS", None,
                    "Why the controller last refused a request.", NoParams, _robot_reject),
    MachineFunction("robot", "io", "DI/DO", None, "The 16 inputs and 16 outputs.",
                    NoParams, _robot_io, observes=True),
    MachineFunction("robot", "reset", "ERROR RESET", None,
                    "Clear machine-status and reject-status errors.", NoParams, _robot_reset),
    MachineFunction("robot", "home", "RETURN HOME", None, "Return the arm home.",
                    NoParams, _robot_home),
    # Last: the keys of the functions before it stay where they were.
    MachineFunction("robot", "io_set", "IO SET", None,
                    "Drive an input of an emulator with no PLC (a real robot refuses).",
                    InputParams, _robot_io_set),
)  # fmt: skip
