"""What the IBM 7545 robot driver reports and keeps, apart from its line.

:class:`RobotStatus` is what ``Ibm7545Robot.status()`` returns (``lines()`` for a console),
:class:`RobotCounters` its ``counters`` (retries, transactions, records), :class:`RobotHalted`
what a watched wait raises when the arm stopped. ``_digest`` and ``_waits`` are what the driver
keeps of a downloaded program: the digest that tells it is already there, the inputs its
WAITIs wait for. All are named from :mod:`cellctl.kinds.ibm7545.driver` as well.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

from cellctl.errors import CellctlError
from cellctl.kinds.families import CycleAborted
from cellctl.kinds.ibm7545.aml import Op, decode_program
from cellctl.kinds.ibm7545.options import ROBOT_STATES
from cellctl.kinds.ibm7545.records import MachineStatus, ProgramFile


@dataclass
class RobotStatus:
    """What ``status()`` reports: host state, controller status bytes, partitions."""

    state: int
    machine: MachineStatus
    partitions: dict[int, str | None]
    waiting: list[tuple[int, bool]] = field(default_factory=list)
    """While executing: the inputs the running program's WAITIs wait for that do not have
    their value now (read from DI/DO): what it may be blocked on."""

    @property
    def state_text(self) -> str:
        """The robot state in words."""
        return ROBOT_STATES.get(self.state, f"state {self.state}")

    def lines(self) -> list[str]:
        """Human-readable lines, as the operator console shows them."""
        out = [f"robot state: {self.state} ({self.state_text})"]
        out.append(
            f"machine status: {self.machine} "
            f"(bytes {self.machine.flags:02X} {self.machine.data_error:02X})"
        )
        for p, prog in self.partitions.items():
            out.append(f"partition {p}: {'Full (' + prog + ')' if prog else 'Empty'}")
        out += self.waiting_lines()
        return out

    def waiting_lines(self) -> list[str]:
        """What an executing program may wait for, and how to go on (empty: nothing)."""
        if not self.waiting:
            return []
        inputs = ", ".join(f"input {n} {'on' if v else 'off'}" for n, v in self.waiting)
        first, value = self.waiting[0]
        return [
            f"waiting: the program's WAITI waits for {inputs} (not so now); in a cell the "
            "PLC drives them",
            f"  without one: `robot io set {first} {'on' if value else 'off'}` (an emulator), "
            "or `robot stop` ends the cycle",
        ]


@dataclass
class RobotCounters:
    """Counts a user or a benchmark may want: retries, transactions, records."""

    transactions: int = 0
    checksum_retries: int = 0
    handshake_retries: int = 0
    download_retries: int = 0
    records_downloaded: int = 0
    rejects: list[int] = field(default_factory=list)


class RobotHalted(CycleAborted):
    """The machine status says the arm stopped (servo error, power failure); ``status``."""

    def __init__(self, status: MachineStatus, detail: str) -> None:
        super().__init__(status, detail, code=status.flags)


def _digest(program: ProgramFile) -> str:
    return hashlib.sha256(program.to_text().encode("ascii")).hexdigest()[:16]


def _waits(prog: ProgramFile) -> list[tuple[int, bool]]:
    """The (input, value) pairs ``prog``'s WAITIs wait for, in program order, each once."""
    try:
        found = decode_program(prog.body)
    except CellctlError:
        return []
    out: list[tuple[int, bool]] = []
    for ins in found:
        if ins.op is not Op.WAITI:
            continue
        pair = (ins.operands[0], bool(ins.operands[1]))
        if pair not in out:
            out.append(pair)
    return out
