"""Plans: the real cell controller played forward on virtual time (:mod:`.engine`).

The engine loads when one of its names is first asked for: ``cellctl.plan.when`` (what a
planner types, the plan's poll period) stays light for the command line's options.
"""

from __future__ import annotations

from typing import Any

__all__ = ["FaultWindow", "HeldPart", "PlanInputs", "PlanOrder", "PlanRun", "simulate"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from cellctl.plan import engine

        return getattr(engine, name)
    raise AttributeError(f"module 'cellctl.plan' has no attribute {name!r}")
