"""What the cell's machines physically have to do, timed by the machines' own models.

::

    phys = physical_durations(load_cell("cell"), time_scale=100.0)
    phys.transfers["conveyor_to_cnc1"].seconds     # the arm's motion, doors and vises
    phys.machining[("cnc1", "robot_base_rough_cnc1")].parts   # door, download, cut
    phys.bound(["wax-robot-base"] * 10, config.parts)         # s: no schedule finishes sooner

Nothing here was measured: every figure comes from the programs and the models the emulators
run on, at the given time scale (machine times divided by it; the line's characters at the
baud rate the cell's configuration names, which an emulated cell has already multiplied).

- **A transfer** (robot program ``A_to_B``) runs on the robot kind's motion model (its
  :class:`~cellctl.kinds.families.RobotModel`) from the best of its possible starting
  points (home, or where any transfer ends). Its WAITIs take what the PLC's machinery
  takes (:class:`~cellctl.protocol.plc.PlcTiming`, through the cell's wiring
  :data:`~cellctl.protocol.plc.EXAMPLE_WIRING`): a door of A or B, commanded as the transfer
  starts, is open ``door_s`` later; a vise the program itself commanded reaches its position
  ``clamp_s`` after the WRITEO; every other input (a pallet, the outfeed) counts as there
  already. The transfer ends when the program raises its "cycle done" output.
- **A machining step** is the door closing behind the robot (``door_s``: it starts closing when
  the load ends, and the mill may not cut before it is shut), then for each block its
  characters at the line rate (``bits per char / baud``; the driver's block plus its Ctrl-Z) and
  its cut time from the machine model the mill kind's emulator executes (its
  :class:`~cellctl.kinds.families.MillModel`), from the best of the states the mill can
  be in (after its setup, or after any of its programs).
- **A robot program's download** (its characters both ways, from the robot kind's model, at
  the robot's line rate) happens once per program the batch uses: the robot's term of the bound
  counts it once, the mills' terms do not.

Left out, so the bound stays below any real run: the conveyor (a pallet counts as waiting),
the start-up of each step (robot select and start, the mill's readiness), the mill's least
busy time per block and every reply time. The combinatorics are the scheduler's
(:func:`cellctl.cell.scheduler.resource_bounds`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from cellctl.cell.config import CONVEYOR, CellConfig, PartType
from cellctl.cell.model import DEFAULT_DONE_OUTPUT
from cellctl.cell.scheduler import resource_bounds
from cellctl.kinds import registry
from cellctl.kinds.families import MillModel, ProgramRun, RobotModel
from cellctl.protocol.plc import EXAMPLE_WIRING, PlcTiming, RobotWiring


@dataclass(frozen=True)
class StepTime:
    """One step's physical seconds and what they are made of (``parts`` sum to ``seconds``)."""

    seconds: float
    parts: dict[str, float] = field(default_factory=dict)


@dataclass
class Physics:
    """Physical seconds of every transfer, machining step and robot download of a cell."""

    transfers: dict[str, StepTime]
    machining: dict[tuple[str, str], StepTime]
    robot_downloads: dict[str, float]
    time_scale: float = 1.0

    @property
    def transfer_s(self) -> dict[str, float]:
        return {k: v.seconds for k, v in self.transfers.items()}

    @property
    def machining_s(self) -> dict[tuple[str, str], float]:
        return {k: v.seconds for k, v in self.machining.items()}

    def terms(self, parts: Sequence[str], types: Mapping[str, PartType]) -> dict[str, float]:
        """Each resource's least busy time for ``parts``: the robot's with its downloads."""
        if not parts:
            return {}
        terms = resource_bounds(parts, types, self.transfer_s, self.machining_s)
        used = {t for name in set(parts) for t in types[name].transfers()}
        terms["robot"] += sum(self.robot_downloads.get(t, 0.0) for t in used)
        return terms

    def bound(self, parts: Sequence[str], types: Mapping[str, PartType]) -> float:
        """The least makespan of ``parts`` (part type names) on this cell, in seconds."""
        return max(self.terms(parts, types).values(), default=0.0)


def physical_durations(
    config: CellConfig,
    *,
    time_scale: float = 1.0,
    done_output: int | None = None,
    timing: PlcTiming | None = None,
    wiring: RobotWiring = EXAMPLE_WIRING,
) -> Physics:
    """The physical durations of ``config``'s steps at ``time_scale`` (see module docstring).

    ``done_output`` is the transfer programs' "cycle done" output (``[cell] done_output``);
    ``timing`` defaults to the PLC emulator's, the robot's and mills' models to their kinds'.
    """
    timing = timing or PlcTiming()
    transfers = transfer_durations(
        config, time_scale=time_scale, done_output=done_output, timing=timing, wiring=wiring
    )
    robot: RobotModel = _model(config.robot.kind)
    programs = config.robot_programs
    line = config.robot.line
    downloads = {name: line.wire_time(robot.download_chars(p)) for name, p in programs.items()}
    machining: dict[tuple[str, str], StepTime] = {}
    for m in config.mills:
        route = [s for t in config.parts.values() for s in t.route]
        steps = {s.name: s.program for s in route if s.mill == m.name}
        mill: MillModel = _model(m.kind)
        times = mill.cut_times(m.setup, list(steps.values()))
        for name, (cut_s, wire_chars) in zip(steps, times, strict=True):
            door = timing.door_s / time_scale
            wire = m.line.wire_time(wire_chars)
            cut = cut_s / time_scale
            machining[(m.name, name)] = StepTime(
                door + wire + cut, {"door": door, "download": wire, "cut": cut}
            )
    return Physics(transfers, machining, downloads, time_scale)


def transfer_durations(
    config: CellConfig,
    *,
    time_scale: float = 1.0,
    done_output: int | None = None,
    timing: PlcTiming | None = None,
    wiring: RobotWiring = EXAMPLE_WIRING,
) -> dict[str, StepTime]:
    """The transfers of :func:`physical_durations` alone (the robot's model only)."""
    timing = timing or PlcTiming()
    if done_output is None:
        done_output = int(config.raw.get("cell", {}).get("done_output", DEFAULT_DONE_OUTPUT))
    mills = [m.name for m in config.mills]
    robot: RobotModel = _model(config.robot.kind)
    programs = config.robot_programs
    starts = robot.starts(programs.values())
    return {
        name: _transfer_time(
            name, robot, program, starts, mills, done_output, timing, wiring, time_scale
        )
        for name, program in programs.items()
    }


def _model(kind: str) -> Any:
    """A kind's timing model; a kind without one cannot be bounded from physics."""
    declared = registry.kind(kind)
    if declared.timing is None:
        raise ValueError(f"kind {kind!r} declares no timing model: no bound from physics")
    return declared.timing()


def _transfer_time(
    name: str,
    robot: RobotModel,
    program: Any,
    starts: list[Any],
    mills: list[str],
    done_output: int,
    timing: PlcTiming,
    wiring: RobotWiring,
    time_scale: float,
) -> StepTime:
    source, _, target = name.partition("_to_")
    doors = {mills.index(p) + 1 for p in (source, target) if p != CONVEYOR and p in mills}
    vises = dict(wiring.vise_outputs)
    waits = {"door": 0.0, "clamp": 0.0}

    def ready(port: int, value: bool, now: float, run: ProgramRun) -> float:
        signal = wiring.input_of(port)
        if signal is None:
            return now
        plc_input, inverted = signal
        level = value != inverted
        kind, _, mill_text = plc_input.rpartition("_")
        mill = int(mill_text) if mill_text.isdigit() else 0
        at = now
        if kind == "door_open" and level and mill in doors:
            at = max(now, timing.door_s)  # commanded open as the transfer starts
        elif kind == "clamp_closed":
            writes = [(t, v) for t, p, v in run.writes if vises.get(p) == mill]
            if writes and writes[-1][1] == level:
                at = max(now, writes[-1][0] + timing.clamp_s)
        label = "door" if kind == "door_open" else "clamp"
        waits[label] = waits.get(label, 0.0) + (at - now)
        return at

    best: StepTime | None = None
    for start in starts:
        waits.update(door=0.0, clamp=0.0)
        run = robot.run(program, input_ready=ready, start=start)
        end = run.first_write(done_output, True)
        total = run.end_s if end is None else end
        # What the arm did up to the cycle-done output: its motion is the rest.
        motion = total - waits["door"] - waits["clamp"]
        step = StepTime(
            total / time_scale,
            {
                "motion": motion / time_scale,
                "door": waits["door"] / time_scale,
                "clamp": waits["clamp"] / time_scale,
            },
        )
        if best is None or step.seconds < best.seconds:
            best = step
    assert best is not None
    return best


__all__ = ["Physics", "StepTime", "physical_durations", "transfer_durations"]
