"""Read-only views of the cell for drawing it: its layout from cell.toml, the journal's steps
(for a Gantt chart) and the toolpath of a program a route names.

::

    layout = cell_layout(access)         # machines with kinds, part types with their routes
    steps = journal_steps(access, since=time.time() - 3600)
    svg = program_preview(access, "cnc1", "robot_base_rough_cnc1")
    figures = shift_figures(access, since=None, until=None)   # the last shift's OEE

A preview is drawn only for a DYNALAN program that one of the mill's route steps names in
cell.toml (by its name or its path as written there): no other file is ever read.
"""

from __future__ import annotations

import dataclasses
from collections import OrderedDict
from typing import Any

from cellctl.cell.config import CONVEYOR, CellConfig, load_cell
from cellctl.cell.controller import OUT
from cellctl.clock import current_clock
from cellctl.errors import UsageError
from cellctl.kinds import registry
from cellctl.service.access import CellAccess
from cellctl.service.functions import family_of_kind

#: Steps a ``steps.list`` answer carries at most (the newest).
MAX_STEPS = 5000
#: Toolpath drawings kept (program file, its modification time) -> SVG.
_PREVIEWS: OrderedDict[tuple[str, str, int], tuple[str, int]] = OrderedDict()
_PREVIEWS_KEPT = 16
#: The ideal step times of the last cell a shift report was asked of.
_IDEAL: dict[tuple[str, float, int], dict[str, float]] = {}


def cell_config(access: CellAccess) -> CellConfig:
    """The running controller's checked cell.toml, else the one in the cell directory."""
    try:
        return access.controller().config
    except UsageError:
        return load_cell(access.directory)


def cell_layout(access: CellAccess) -> dict[str, Any]:
    """What the cell is made of: machines (name, kind, family, role), the places a part can be,
    and each part type's route (mill, program name, program path as in cell.toml); or what
    the access says of its own (:meth:`~cellctl.service.access.CellAccess.layout`)."""
    own = access.layout()
    if own is not None:
        return own
    config = cell_config(access)
    machines = [
        {
            "name": m.name,
            "kind": m.kind,
            "family": family_of_kind(m.kind) or m.kind,
            "role": "robot" if m is config.robot else "mill",
        }
        for m in [config.robot, *config.mills]
    ]
    parts = {
        name: {
            "route": [
                {
                    "mill": step.mill,
                    "program": step.name,
                    "path": _relative(config, step.program),
                    "lines": step.lines,
                    "machining_s": step.machining_s,
                }
                for step in part.route
            ],
            "transfers": part.transfers(),
        }
        for name, part in config.parts.items()
    }
    return {
        "name": config.name,
        "robot": config.robot.name,
        "mills": [m.name for m in config.mills],
        "places": [CONVEYOR, config.robot.name, *(m.name for m in config.mills), OUT],
        "machines": machines,
        "part_types": parts,
    }


def journal_steps(access: CellAccess, since: float | None) -> list[dict[str, Any]]:
    """The journal's steps that started at or after ``since`` (every one if None), oldest
    first, with each part's type; at most :data:`MAX_STEPS` (the newest)."""
    journal = access.journal()
    if journal is None:
        return []
    types = {p.id: p.part_type for p in journal.parts()}
    steps = [s for s in journal.steps() if since is None or s.started >= since]
    return [
        {**dataclasses.asdict(s), "part_type": types.get(s.part_id, "")} for s in steps[-MAX_STEPS:]
    ]


def shift_figures(access: CellAccess, since: float | None, until: float | None) -> dict[str, Any]:
    """The shift report (:mod:`cellctl.cell.shift`) of ``[since, until]`` (default: the
    8 h before ``until``, not before the journal's first step; ``until`` now)."""
    from cellctl.cell.shift import MAX_WINDOW, SHIFT, cell_time_scale, ideal_times, shift_report

    end = current_clock().now() if until is None else until
    journal = access.journal()
    first = min((s.started for s in journal.steps()), default=end) if journal else end
    start = max(end - SHIFT, min(first, end - 1.0)) if since is None else since
    if end <= start:
        raise UsageError("the report's window ends before it starts: give --from before --to")
    if end - start > MAX_WINDOW:
        raise UsageError(f"the report's window is at most {MAX_WINDOW / 86400:g} days")
    config = cell_config(access)
    machines = [config.robot.name, *(m.name for m in config.mills)]
    scale = cell_time_scale(config)
    if journal is None:
        from cellctl.cell.shift import ShiftReport

        return ShiftReport(start, end, scale, [], 0, 0, 0).as_dict()
    toml = config.directory / "cell.toml"
    key = (str(config.directory), scale, toml.stat().st_mtime_ns if toml.exists() else 0)
    if key not in _IDEAL:  # the machines' models run every program: once per cell.toml
        _IDEAL.clear()
        _IDEAL[key] = ideal_times(config, scale)
    # Attached: this process runs the controller (else a last run not stopped ended unheard).
    running = access.mode == "attached"
    return shift_report(
        journal, machines, _IDEAL[key], start, end, time_scale=scale, running_now=running
    ).as_dict()


def program_preview(access: CellAccess, machine: str, program: str) -> dict[str, Any]:
    """The toolpath drawing (SVG text) of ``program``, a route step of mill ``machine``
    named by its name or its path as cell.toml writes it; anything else is refused."""
    config = cell_config(access)
    mill = next((m for m in config.mills if m.name == machine), None)
    if mill is None:
        known = ", ".join(m.name for m in config.mills)
        raise UsageError(f"unknown mill {machine!r} (known: {known})")
    steps = [s for p in config.parts.values() for s in p.route if s.mill == machine]
    step = next(
        (s for s in steps if program in (s.name, _relative(config, s.program))),
        None,
    )
    if step is None:
        named = ", ".join(sorted({s.name for s in steps})) or "none"
        raise UsageError(
            f"{program!r} is not a program of {machine}'s routes in cell.toml (they are: {named})"
        )
    try:
        mtime = step.program.stat().st_mtime_ns
        key = (machine, str(step.program), mtime)
        cached = _PREVIEWS.get(key)
        if cached is None:
            kind = registry.kind(mill.kind)
            language = kind.language
            if language is None or language.preview is None:
                raise UsageError(f"{machine}: a {kind.title} has no toolpath preview")
            text = step.program.read_text(encoding="latin-1")
            drawn = language.preview(text, step.program.name, kind.checked_options(mill.options))
            cached = (drawn.svg, drawn.blocks)
            _PREVIEWS[key] = cached
            while len(_PREVIEWS) > _PREVIEWS_KEPT:
                _PREVIEWS.popitem(last=False)
    except OSError as e:
        raise UsageError(f"{step.name}: cannot read {step.program.name}: {e.strerror}") from None
    svg, blocks = cached
    return {"machine": machine, "program": step.name, "blocks": blocks, "svg": svg}


def _relative(config: CellConfig, path: Any) -> str:
    try:
        return str(path.relative_to(config.directory))
    except ValueError:
        return str(path)
