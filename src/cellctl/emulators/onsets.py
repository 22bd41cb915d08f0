"""When each fault switched on first acted: the moment a host could first notice it.

Every emulator keeps one (``emulator.onsets``). A fault switched on is *armed* until it
changes what the machine does -- the line drops, a request goes unanswered, a block ends
without readiness, a coil is ignored -- and that moment is its onset (wall time, the running
loop's clock's ``now()``)::

    mill.set_fault("stall")           # armed: nothing shows until the running block ends
    ...
    mill.onsets.get("stall")          # None, or when the block ended without readiness

Benches measure a controller's reaction from it (``bench/fault_reaction.py``).
"""

from __future__ import annotations

from cellctl.clock import current_clock


class FaultOnsets:
    """Onset times of the faults switched on (see module docstring)."""

    def __init__(self) -> None:
        self._at: dict[str, float] = {}

    def arm(self, name: str) -> None:
        """Fault ``name`` was switched on: its onset is still to come."""
        self._at.pop(name, None)

    def act(self, name: str) -> None:
        """Fault ``name`` acts now (only its first act since it was armed counts)."""
        self._at.setdefault(name, current_clock().now())

    def get(self, name: str) -> float | None:
        """When fault ``name`` first acted since it was switched on, or None."""
        return self._at.get(name)
