"""The emulated ISO-code control's panel and records, apart from what it does on its line
(:mod:`cellctl.kinds.iso_cnc.emulator`): its parameters and fault switches, its mode switch
and activity, and what it records of its runs (blocks, machine time, stalls) and alarms.
No I/O: the kind's table, the CLI and a test's setup read these without an event loop::

    options = EmulatorOptions(buffer_size=256, tolerance=10, cs_flow=True)
    FAULTS["line-lag"]                     # "=MS: each piece of the host's data is held ..."
    Mode.RMT                               # CYCLE START runs the tape as it comes
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

from pydantic import BaseModel, ConfigDict, Field

from cellctl.kinds.iso_cnc.motion import MotionModel

#: Fault switches: name -> what it does (``--fault NAME[=ARG]`` on the command line).
FAULTS = {
    "adapter-latency": "=MS: its DC3/DC1 reach the host MS milliseconds late (a USB adapter) "
    "(default 16 ms)",
    "line-lag": "=MS: each piece of the host's data is held 0 to MS milliseconds before it "
    "crosses (a device server's packet timer), in order (default 16 ms)",
    "parity-noise": "=RATE: each received character has a parity error with probability RATE "
    "(alarm 085) (default 0.01)",
    "dr-off": "DR (DSR) off: a transfer raises alarm 086",
    "never-dc1": "it never sends DC1 (the host waits for ever)",
    "tolerance-2": "it tolerates 2 characters after DC3 (a CS-only control)",
    "noise": "=RATE[,SEED]: every byte, each way, flipped in one bit or dropped with "
    "probability RATE",
}


class Mode(enum.StrEnum):
    EDIT = "EDIT"
    """READ puts the tape into memory."""
    MEM = "MEM"
    """CYCLE START runs the selected program from memory."""
    RMT = "RMT"
    """CYCLE START runs the tape as it comes (drip-feed)."""


class Activity(enum.StrEnum):
    IDLE = "idle"
    READING = "reading"
    RUNNING = "running"
    PUNCHING = "punching"
    ALARM = "alarm"


class EmulatorOptions(BaseModel):
    """The emulated control's parameters and fault switches."""

    model_config = ConfigDict(frozen=True, extra="forbid", defer_build=True)

    buffer_size: int = Field(default=256, ge=16, le=1 << 20)
    """Characters its reader buffer holds."""
    high_water: int | None = Field(default=None, ge=1)
    """DC3 when the buffer holds this many (default: buffer_size - tolerance)."""
    low_water: int | None = Field(default=None, ge=0)
    """DC1 again when it has drained to this many (default: buffer_size // 2)."""
    tolerance: int = Field(default=10, ge=0, le=1000)
    """Characters accepted after its DC3; one more is alarm 087."""
    cs_flow: bool = False
    """It also drops RTS (the host's CTS) at the high-water mark."""
    adapter_latency_ms: float = Field(default=0.0, ge=0, le=10000)
    """Its DC3/DC1 reach the host this late (machine ms: divided by the time scale)."""
    line_lag_ms: float = Field(default=0.0, ge=0, le=10000)
    """Each piece of the host's data is held a random 0 to this many machine ms before it
    crosses its line, in order (a device server's packet timer): blocks start later than a
    host that counts them through at the line rate expects, by a varying amount."""
    parity_noise: float = Field(default=0.0, ge=0, le=1)
    """Probability of a parity error on each character received (alarm 085)."""
    dr_off: bool = False
    """DR (DSR) is off: a transfer raises alarm 086."""
    never_dc1: bool = False
    """It never sends DC1."""
    auto_operator: bool = False
    """READ (EDIT) or CYCLE START (RMT) is pressed again whenever the control is idle."""
    rapid_mm_min: float = Field(default=10000.0, gt=0)
    """Rapid traverse, mm/min (its motion model)."""
    accel_mm_s2: float | None = Field(default=None, gt=0)
    """Acceleration, mm/s² (None: moves run at their rate from end to end)."""
    punch_leader: int = Field(default=20, ge=0, le=1000)
    """NUL characters it punches before and after the programs."""
    seed: int | None = None
    """Seed for the parity noise (None: random)."""

    def motion(self) -> MotionModel:
        return MotionModel(rapid_mm_min=self.rapid_mm_min, accel_mm_s2=self.accel_mm_s2)


@dataclass(frozen=True)
class Stall:
    """The axes stopped waiting for data: from ``start_s`` (machine s since the run began)."""

    start_s: float
    seconds: float


@dataclass(frozen=True)
class Alarm:
    code: int
    text: str
    detail: str = ""


@dataclass
class DripRun:
    """One drip-feed or memory run: blocks executed, machine seconds, its stalls."""

    number: int = 0
    blocks: int = 0
    machine_s: float = 0.0
    stalls: list[Stall] = field(default_factory=list)
    done: bool = False

    @property
    def stall_s(self) -> float:
        return sum(s.seconds for s in self.stalls)
