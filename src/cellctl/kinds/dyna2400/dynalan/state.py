"""The DYNALAN machine model's data: the fault it raises, the moves and steps a run yields, the
modal state and the per-machine configuration.

:mod:`cellctl.kinds.dyna2400.dynalan.machine` executes statements over these (and re-exports
them, so either path imports them)::

    state = MachineState.initial(Units.INS)   # power-up state, at the reference zero
    state.set_units(Units.MM)                 # START MM: converts what the state holds

No I/O and no clock here, as in the rest of the package.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field, replace

from cellctl.errors import CellctlError
from cellctl.kinds.dyna2400.dynalan.model import Statement
from cellctl.kinds.dyna2400.dynalan.table import (
    AXES,
    CLEARANCE_Z,
    FEED_DEFAULT,
    RAPID_RATE,
    STEP_OVER,
    TOOL_DIAMETER_DEFAULT,
    Kind,
    Travel,
    Units,
    scale,
)

Vec = tuple[float, float, float]


class ProgramFault(CellctlError):
    """A statement cannot be executed: what the controller would stop on.

    ``code`` is a short name (``travel``, ``arc``, ``malformed`` ...), ``number`` the line.
    """

    def __init__(self, code: str, message: str, number: int | None = None) -> None:
        self.code = code
        self.message = message
        self.number = number
        where = f"line {number:03d}: " if number is not None else ""
        super().__init__(f"{where}{message}")


class MoveKind(enum.Enum):
    FEED = "feed"
    RAPID = "rapid"
    DWELL = "dwell"


@dataclass(frozen=True, slots=True)
class Move:
    """One motion: its path (polyline, reference coordinates, program units) and its time."""

    kind: MoveKind
    path: tuple[Vec, ...]
    rate: float  # units/min; 0 for a dwell
    seconds: float
    number: int  # the line it came from

    @property
    def start(self) -> Vec:
        return self.path[0]

    @property
    def end(self) -> Vec:
        return self.path[-1]

    @property
    def length(self) -> float:
        return sum(math.dist(a, b) for a, b in zip(self.path, self.path[1:], strict=False))


@dataclass(frozen=True)
class MachineConfig:
    """Per-machine facts the program does not say: travel, rapid rate, clearance (inches)."""

    travel: Travel = field(default_factory=Travel)
    rapid_rate: float = RAPID_RATE
    clearance_z: float = CLEARANCE_Z
    step_over: float = STEP_OVER


@dataclass
class MachineState:
    """The controller's modal state. ``position`` is in reference coordinates."""

    units: Units = Units.INS
    position: Vec = (0.0, 0.0, 0.0)
    local_zero: Vec = (0.0, 0.0, 0.0)
    local: bool = False
    feed: dict[str, float] = field(default_factory=dict)
    tool: int = 0
    tool_diameter: float = TOOL_DIAMETER_DEFAULT
    spindle_rpm: int = 0
    spindle_on: bool = False
    coolant_on: bool = False
    axis_context: Kind | None = None  # what an axis-only line means now
    drill_peck: float | None = None
    drill_top: float | None = None
    drill_bottom: float | None = None

    @classmethod
    def initial(cls, units: Units = Units.INS) -> MachineState:
        """Power-up state: default feed rates, the default tool, at the reference zero."""
        feed = scale(FEED_DEFAULT, units)
        return cls(
            units=units,
            feed=dict.fromkeys(AXES, feed),
            tool_diameter=scale(TOOL_DIAMETER_DEFAULT, units),
        )

    def copy(self) -> MachineState:
        return replace(self, feed=dict(self.feed))

    def frame(self) -> Vec:
        """Origin of the coordinates that GO and cycles use (local zero or reference zero)."""
        return self.local_zero if self.local else (0.0, 0.0, 0.0)

    def set_units(self, units: Units) -> None:
        """START INS/MM: switch units, converting what the state holds."""
        if units is self.units:
            return
        k = units.per_inch / self.units.per_inch
        self.position = _mul(self.position, k)
        self.local_zero = _mul(self.local_zero, k)
        self.feed = {a: v * k for a, v in self.feed.items()}
        self.tool_diameter *= k
        self.units = units


def _mul(v: Vec, k: float) -> Vec:
    return (v[0] * k, v[1] * k, v[2] * k)


class Outcome(enum.Enum):
    BLOCK_END = "block end"  # reached the 900 line (or ran past the last line)
    HALT = "HALT"
    END = "END"


@dataclass(frozen=True, slots=True)
class Step:
    """One executed statement: its moves, whether it waits for the operator, how it ended."""

    number: int
    statement: Statement
    moves: tuple[Move, ...] = ()
    operator: bool = False
    outcome: Outcome | None = None


#: A memory entry: a statement, or the reason its text is not one (fails when executed).
Entry = Statement | str
