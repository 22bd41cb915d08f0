"""The Kerf 100's manual functions: what the console's menu, the CLI and the control API
offer for a saw (``mill.status``, ``mill.home``, ``mill.cut`` with ``machine`` a saw)."""

from __future__ import annotations

from typing import Any

from cellctl.errors import UsageError
from cellctl.kinds.menu import MachineFunction, NoParams, Prepared, ProgramParams, Progress, ok
from cellctl_saw.driver import KerfSaw
from cellctl_saw.protocol import CutList, parse_cut_list


def _parse(params: Any) -> CutList:
    found = parse_cut_list(params.text, params.program, setup=False)
    if found.problems:
        raise UsageError("; ".join(found.problems))
    return found


async def _status(saw: KerfSaw, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    found = await saw.status()
    return ok(found.shown, state=found.state, done=found.done, loaded=found.loaded)


async def _home(saw: KerfSaw, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    return ok(f"homed ({await saw.home()})")


async def _cut(saw: KerfSaw, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    cuts: CutList = p.parsed
    await saw.cut(cuts)
    return ok(f"cut {len(cuts.cuts)} pieces", cuts=len(cuts.cuts))


MENU = (
    MachineFunction(
        "mill", "status", "STATUS", 1, "State, cuts done, alarm.", NoParams, _status, observes=True
    ),
    MachineFunction("mill", "home", "HOME", 2, "Carriage to its home switch.", NoParams, _home),
    MachineFunction(
        "mill", "cut", "CUT", 3, "Cut a list of bars now.", ProgramParams, _cut, prepare=_parse
    ),
)
