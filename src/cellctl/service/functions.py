"""Every manual function of a machine, once: the source's robot and CNC menus plus the
tool-kit's extras. The CLI, the control API and the console all run them from this table::

    fn = function("robot", "download")
    params = fn.check({"partition": 3, "program": "load1.rec", "text": text})  # no byte yet
    result = await fn.run(robot, params, progress)     # {"message": "Download was correct", ...}

Parameters are checked (and programs parsed and validated) by ``check`` before a driver is
touched, so bad input is refused before a byte goes out. Results are JSON-ready dicts with a
``message`` in the source's words.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from cellctl.drivers.mill import MILL_STATES, Dyna2400Mill
from cellctl.drivers.mill import Progress as MillProgress
from cellctl.drivers.robot import ROBOT_STATES, Ibm7545Robot
from cellctl.errors import UsageError
from cellctl.protocol.dynalan import parse_program
from cellctl.protocol.robot import PARTITIONS, ProgramFile

Progress = Callable[[dict[str, Any]], None]
"""Called with a JSON-ready dict as a download goes on."""

#: The largest program text a caller may send (a DYNALAN program of ~100,000 lines).
MAX_PROGRAM_CHARS = 4_000_000


class InvalidParams(UsageError):
    """Parameters that do not fit their schema (a JSON-RPC -32602): the message names the
    field and says why."""


#: How many of a validation's problems a message lists.
SHOWN_PROBLEMS = 5
#: How much of a field's name a message shows (a peer picks the names).
SHOWN_NAME = 60


class Params(BaseModel):
    """Base of the functions' parameters: unknown keys are refused."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class NoParams(Params):
    pass


class PartitionParams(Params):
    partition: int

    @field_validator("partition")
    @classmethod
    def _partition(cls, value: int) -> int:
        if value not in PARTITIONS:
            raise ValueError(f"partition must be 1 to 5, not {value} (partition error)")
        return value


class ProgramParams(Params):
    program: str = Field(min_length=1, max_length=255, description="The file's name.")
    text: str = Field(max_length=MAX_PROGRAM_CHARS, description="The file's contents.")


class RobotDownloadParams(PartitionParams, ProgramParams):
    pass


class MillInitParams(ProgramParams):
    force: bool = False


class MillDownloadParams(ProgramParams):
    wait: bool = True


class UploadParams(Params):
    timeout: float = Field(default=120.0, gt=0, le=3600)


Runner = Callable[[Any, Any, Progress | None], Awaitable[dict[str, Any]]]


@dataclass(frozen=True)
class MachineFunction:
    """One function of a machine family: its menu key, its parameters, how it runs."""

    family: str  # "robot" or "mill"
    name: str
    label: str  # as the source's menu shows it
    menu: int | None  # the source's menu number; None for the tool-kit's extras
    doc: str
    params: type[Params]
    runner: Runner
    observes: bool = False
    """Only reads the machine: allowed while it is in automatic service."""

    def check(self, raw: dict[str, Any] | None) -> Any:
        """Validated parameters (programs parsed): UsageError, with the reason, otherwise."""
        try:
            params = self.params.model_validate(raw or {})
        except ValidationError as e:
            raise InvalidParams(f"{self.family} {self.name}: {describe(e)}") from None
        return _prepare(self, params)

    async def run(self, driver: Any, params: Any, progress: Progress | None = None) -> Any:
        """Run on ``driver`` with parameters from :meth:`check`."""
        return await self.runner(driver, params, progress)


def describe(error: ValidationError) -> str:
    """A pydantic error in one line: ``partition: partition must be 1 to 5 ...``."""
    parts = []
    problems = error.errors(include_url=False, include_input=False)
    for item in problems[:SHOWN_PROBLEMS]:
        where = ".".join(str(x) for x in item["loc"]) or "parameters"
        if len(where) > SHOWN_NAME:
            where = where[:SHOWN_NAME] + "…"
        message = str(item["msg"]).removeprefix("Value error, ")
        parts.append(f"{where}: {message}")
    if len(problems) > SHOWN_PROBLEMS:
        parts.append(f"and {len(problems) - SHOWN_PROBLEMS} more")
    return "; ".join(parts)


@dataclass(frozen=True)
class Prepared:
    """Checked parameters plus what was parsed from them."""

    params: Any
    parsed: Any = None


def _prepare(fn: MachineFunction, params: Params) -> Prepared:
    if fn.family == "robot" and isinstance(params, RobotDownloadParams):
        program = ProgramFile.parse(params.text, params.program)
        return Prepared(params, program)
    if fn.family == "mill" and isinstance(params, ProgramParams):
        return Prepared(params, parse_program(params.text, name=params.program))
    return Prepared(params)


# -- robot ----------------------------------------------------------------------------------------


def _ok(message: str, **data: Any) -> dict[str, Any]:
    return {"message": message, **data}


async def _robot_init(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.return_home()
    await r.auto_mode()
    return _ok("Initializing was correct", lines=["returning home", "Set on Auto mode"])


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
    return _ok(
        "Download was correct",
        partition=p.params.partition,
        name=program.name,
        records=len(program.records),
    )


async def _robot_go(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.go(p.params.partition)
    return _ok("Started Cycle", partition=p.params.partition)


async def _robot_stop(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.stop()
    return _ok("Cycle stopped", lines=["Stopping Cycle"])


async def _robot_halt(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.halt()
    return _ok("Halted: robot uninitialized, every partition must be downloaded again")


async def _robot_status(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    st = await r.status()
    partitions = {str(n): prog for n, prog in st.partitions.items()}
    return _ok(
        f"robot state {st.state} ({st.state_text})",
        name=r.name,
        state=st.state,
        state_text=st.state_text,
        machine_status=str(st.machine),
        status_bytes=f"{st.machine.flags:02X} {st.machine.data_error:02X}",
        partitions=partitions,
        lines=st.lines(),
    )


async def _robot_reject(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    code, message = await r.reject_status()
    return _ok(f"Reject status {code}: {message}", code=code, text=message)


async def _robot_io(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    dido = await r.io()
    inputs = [dido.input(n) for n in range(1, 17)]
    outputs = [dido.output(n) for n in range(1, 17)]
    return _ok(
        "DI "
        + "".join("1" if x else "." for x in inputs)
        + "  DO "
        + "".join("1" if x else "." for x in outputs),
        name=r.name,
        inputs=inputs,
        outputs=outputs,
    )


async def _robot_reset(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.reset_errors()
    return _ok("Errors reset")


async def _robot_home(r: Ibm7545Robot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.return_home()
    return _ok("Home", lines=["returning home"])


# -- mill -----------------------------------------------------------------------------------------


async def _mill_init(m: Dyna2400Mill, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    result = await m.initialize(p.parsed, force=p.params.force)
    return _ok(
        result.message,
        code=result.code,
        lines=[],
        after=["operator: jog the axes to the reference zero, then press NEXT"],
    )


async def _mill_download(m: Dyna2400Mill, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    def report(d: MillProgress) -> None:
        if progress is not None:
            progress(
                {
                    "block": d.block,
                    "blocks": d.blocks,
                    "lines": d.lines_sent,
                    "lines_total": d.lines_total,
                    "bytes_sent": d.bytes_sent,
                    "bytes_total": d.bytes_total,
                    "phase": d.phase,
                }
            )

    result = await m.download(p.parsed, wait=p.params.wait, progress=report)
    return _ok(result.message, code=result.code)


async def _mill_load(m: Dyna2400Mill, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    result = await m.load(p.parsed)
    return _ok(result.message, code=result.code)


async def _mill_go(m: Dyna2400Mill, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    if m.start_output is None:
        raise UsageError(
            f"{m.name}: no start signal: set options.start_signal (a PLC coil) in cell.toml"
        )
    result = await m.go()
    return _ok(result.message, code=result.code)


async def _mill_end(m: Dyna2400Mill, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    result = await m.end()
    return _ok(result.message, code=result.code)


async def _mill_status(m: Dyna2400Mill, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    st = await m.status()
    lines = [f"{m.name}: state {st.state} ({st.state_text})"]
    if st.condition:
        lines.append(f"  {st.condition}")
    lines.append(f"  CTS {'high (ready)' if st.ready else 'low'}")
    return _ok(
        f"state {st.state} ({st.state_text})",
        name=m.name,
        state=st.state,
        state_text=st.state_text,
        condition=st.condition,
        ready=st.ready,
        initialized=m.initialized,
        lines=lines,
    )


async def _mill_upload(m: Dyna2400Mill, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    text = await m.upload(timeout=p.params.timeout)
    return _ok(f"{len(text.splitlines())} lines received", text=text)


FUNCTIONS: tuple[MachineFunction, ...] = (
    MachineFunction("robot", "init", "INITIALIZE", 1, "Return home, then auto mode.",
                    NoParams, _robot_init),
    MachineFunction("robot", "download", "DOWNLOAD", 2,
                    "Download a compiled program (.rec) into a partition.",
                    RobotDownloadParams, _robot_download),
    MachineFunction("robot", "go", "GO", 3, "Run the program in a partition.",
                    PartitionParams, _robot_go),
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
    MachineFunction("mill", "init", "INITIALIZE", 1,
                    "Send the setup program; the operator sets the reference zero.",
                    MillInitParams, _mill_init),
    MachineFunction("mill", "download", "DOWNLOAD", 2,
                    "Validate, split into blocks, stream them as the mill asks.",
                    MillDownloadParams, _mill_download),
    MachineFunction("mill", "go", "GO", 3, "Start the loaded program (PLC start signal).",
                    NoParams, _mill_go),
    MachineFunction("mill", "status", "STATUS", 4, "State 0-4, its condition, CTS.",
                    NoParams, _mill_status, observes=True),
    MachineFunction("mill", "end", "HALT", 5,
                    "ENDLOAD: the end program; the mill returns to manual.", NoParams, _mill_end),
    MachineFunction("mill", "load", "PROGRAM LOAD", None,
                    "Load a program (at most 900 lines) to start with GO.",
                    ProgramParams, _mill_load),
    MachineFunction("mill", "upload", "UPLOAD", None,
                    "Receive the mill's program (start UPLOAD on its panel).",
                    UploadParams, _mill_upload),
)  # fmt: skip

FAMILIES = ("robot", "mill")
#: Machine kinds of each family (as in cell.toml).
FAMILY_OF_KIND = {"ibm7545": "robot", "ibm7547": "robot", "dyna2400": "mill"}


def function(family: str, name: str) -> MachineFunction:
    """The function ``name`` of ``family``; UsageError naming the known ones otherwise."""
    for fn in FUNCTIONS:
        if fn.family == family and fn.name == name:
            return fn
    known = ", ".join(f.name for f in FUNCTIONS if f.family == family)
    raise UsageError(f"no {family} function {name!r} (known: {known})")


def menu(family: str) -> list[MachineFunction]:
    """The family's functions, the source's menu first (by number), then the extras."""
    mine = [f for f in FUNCTIONS if f.family == family]
    return sorted(mine, key=lambda f: (f.menu is None, f.menu or 0))


def state_text(family: str, state: int) -> str:
    """A machine state in words."""
    if family == "mill":
        return MILL_STATES.get(state, f"state {state}")
    return ROBOT_STATES.get(state, f"state {state}")
