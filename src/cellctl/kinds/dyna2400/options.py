"""What the Dyna 2400's declaration needs without its driver: its options (``cell.toml``)
and its states (the registry reads these at start; the driver is imported when a mill is
opened)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from cellctl.errors import UsageError
from cellctl.kinds.dyna2400.dynalan import MachineConfig, Travel
from cellctl.kinds.kind import MachineState as KindState


class MillState(KindState):
    """Machine states, as the source's STATUS() prints them."""

    NOT_READY = 0, "Uninitialized, not ready"
    READY = 1, "Uninitialized, Ready"
    INITIALIZED = 2, "Initialized"
    DOWNLOADED = 3, "Downloaded, active"
    GO = 4, "Go, active"


class MillConfig(BaseModel):
    """Deadlines and per-machine facts; every one can be set per mill (``cell.toml`` options)."""

    model_config = ConfigDict(frozen=True, extra="forbid", defer_build=True)

    readiness: Literal["modem", "inband"] = "modem"
    """``modem``: CTS from the line (serial, RFC 2217). ``inband``: DC1/DC3 (project's own)."""
    ready_wait: float = 2.0
    """Seconds the controller may take to show READY before "Machine not ready"."""
    accept_timeout: float = 5.0
    """Seconds after a block's last byte for the controller to take it (CTS low)."""
    block_margin: float = 2.0
    """A block may run this many times its estimated machining time ..."""
    block_extra: float = 60.0
    """... plus this many seconds, before the driver gives up on it."""
    setup_timeout: float = 1800.0
    """Seconds the operator may take to jog to the reference zero and press NEXT."""
    upload_timeout: float = 120.0
    """Seconds to wait for an upload to start and end (the operator starts it)."""
    pace_writes: bool = True
    """Write no faster than the line carries (honest progress, bounded buffers)."""
    go_pulse: float = 0.5
    """Seconds the start output stays on for GO."""
    travel: Travel = Field(default_factory=Travel)
    """The axes' travel limits, mm: a table of x_min ... z_max."""
    rapid_rate: float = 50.0
    """Rapid traverse rate, mm/s (for the machining estimate)."""
    time_scale: float = Field(default=1.0, gt=0, le=100_000)
    """The machine's time runs this many times faster than a real one's (an emulated cell
    writes it): the toolpath's cut estimate, in the real machine's time, is divided by it
    for the progress and the time left."""
    end_program: str | None = None
    """Path of the END program; the built-in ``000 END`` if None."""

    @classmethod
    def from_options(cls, options: dict[str, Any]) -> MillConfig:
        """From ``cell.toml`` options; ``travel`` is a table of x_min ... z_max."""
        try:
            return cls.model_validate(options)
        except ValidationError as e:
            unknown = [str(i["loc"][0]) for i in e.errors() if i["type"] == "extra_forbidden"]
            if unknown:
                raise UsageError(f"unknown mill option(s): {', '.join(sorted(unknown))}") from None
            raise UsageError(f"mill options: {e.errors()[0]['msg']}") from None

    def machine(self) -> MachineConfig:
        return MachineConfig(travel=self.travel, rapid_rate=self.rapid_rate)
