"""Plans: the real cell controller played forward on virtual time (:mod:`.engine`)."""

from __future__ import annotations

from cellctl.plan.engine import (
    FaultWindow,
    HeldPart,
    PlanInputs,
    PlanOrder,
    PlanRun,
    simulate,
)

__all__ = ["FaultWindow", "HeldPart", "PlanInputs", "PlanOrder", "PlanRun", "simulate"]
