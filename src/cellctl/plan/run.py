"""Play a plan (one policy or several, compared) and write what it says::

    result = play(inputs, ("default", "one-at-a-time"), workdir)
    print("\\n".join(result.lines()))
    write_plan(result, Path("plan-out"))   # plan.json, plan.svg, inputs.json, cell/

Each policy is played by the engine (:func:`cellctl.plan.engine.simulate`) on its own copy
of the cell, from the same inputs and seed; the reports come from the journals it wrote.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cellctl.cell.config import load_cell
from cellctl.cell.journal import Journal
from cellctl.cell.journalrecords import Step
from cellctl.errors import UsageError
from cellctl.files import write_output
from cellctl.plan import engine
from cellctl.plan.engine import PlanInputs
from cellctl.plan.inputs import (
    CELL_COPY,
    INPUTS_FILE,
    check_copy_target,
    copy_config,
    inputs_dict,
    save_inputs,
)
from cellctl.plan.report import PlanReport, machines_of, plan_report, plan_svg, policy_name
from cellctl.plan.spec import check_inputs
from cellctl.plan.when import span_text, when_text
from cellctl.tasks import report_progress, spawned_pool

PLAN_JSON = "plan.json"
PLAN_SVG = "plan.svg"


@dataclass
class PlanResult:
    """The plans of one set of inputs, one per policy, and their chart."""

    inputs: PlanInputs
    policies: tuple[str, ...]
    reports: list[PlanReport]
    svg: str

    def as_dict(self) -> dict[str, Any]:
        """``plan.json``: the inputs (as ``inputs.json`` holds them) and each policy's plan."""
        return {
            "inputs": inputs_dict(self.inputs, self.policies),
            "plans": [r.as_dict() for r in self.reports],
        }

    def lines(self) -> list[str]:
        """Each plan's report; with several policies, a comparison last."""
        out: list[str] = []
        for report in self.reports:
            if out:
                out.append("")
            out += report.lines()
        if len(self.reports) > 1:
            out += ["", "policies compared:"]
            out.append(f"  {'policy':<16} {'on time':>7} {'late':>5} {'made':>6}  last order done")
            for r in self.reports:
                done = r.last_finished
                last = when_text(done) if done is not None else "not all in plan"
                made = sum(r.parts_made.values())
                name = policy_name(r.policy)
                out.append(f"  {name:<16} {r.on_time:>7} {r.late:>5} {made:>6}  {last}")
        return out


#: How far the plays have gone: told a policy and the machine seconds it has played.
Progress = Callable[[str, float], None]


def play(
    inputs: PlanInputs,
    policies: tuple[str, ...],
    workdir: Path,
    *,
    workers: int = 1,
    progress: Progress | None = None,
) -> PlanResult:
    """Play ``inputs`` under each policy in ``workdir/<policy>/``; refused before anything
    runs for an order, fault or policy the cell cannot take. ``workers`` > 1: the policies
    side by side in that many spawned processes (a plan is CPU-bound; the command line
    passes its cores, a running cell's service plays one plan on one core). ``progress``:
    told now and then how far each policy's play has gone (:func:`engine.simulate`; from a
    thread of this process when the policies play in processes of their own)."""
    config = load_cell(inputs.cell_dir)
    check_inputs(config, inputs.orders, inputs.faults, policies)
    for name in inputs.out_of_service:
        if name not in machines_of(config):
            raise UsageError(f"out of service: the cell has no machine {name!r}")
    if not inputs.start < inputs.until:
        raise UsageError("a plan's end must be after its start")
    # The engine plays the real cell's configuration (an emulated cell's scaled back).
    real = copy_config(inputs.cell_dir, workdir / "config")
    jobs = [(inputs, policy, real, workdir / policy) for policy in policies]
    if workers > 1 and len(jobs) > 1:
        told = None if progress is None else _from_pool(progress)
        with spawned_pool(min(workers, len(jobs)), progress=told) as pool:
            tell = [progress is not None] * len(jobs)
            played = list(pool.map(_play_policy, *zip(*jobs, strict=True), tell))
    else:
        played = [_play_policy(*job, progress) for job in jobs]
    reports = [report for report, _, _ in played]
    steps = [s for _, s, _ in played]
    types = [t for _, _, t in played]
    svg = plan_svg(reports, steps, types, machines_of(config))
    return PlanResult(inputs, policies, reports, svg)


def _from_pool(progress: Progress) -> Callable[[Any], None]:
    """``progress`` told what a pool's worker reports (``(policy, played_s)``)."""

    def told(item: Any) -> None:
        policy, played = item
        progress(policy, played)

    return told


def _play_policy(
    inputs: PlanInputs,
    policy: str,
    real: Path,
    workdir: Path,
    progress: Progress | bool | None = None,
) -> tuple[PlanReport, list[Step], dict[str, str]]:
    """One policy of :func:`play` (the cell's configuration copied at ``real``): its report,
    its steps and its parts' types. ``progress``: told how far it has gone; True in a
    pool's worker: reported to the pool's parent (:func:`cellctl.tasks.report_progress`)."""
    config = load_cell(inputs.cell_dir)
    tell: engine.PlayProgress | None = None
    if progress is True:

        def tell(played: float) -> None:
            report_progress((policy, played))

    elif callable(progress):
        tell = functools.partial(progress, policy)
    run = engine.simulate(
        dataclasses.replace(inputs, policy=policy, cell_dir=real), workdir, progress=tell
    )
    with Journal(run.journal_path) as journal:
        report = plan_report(
            journal,
            config,
            inputs.orders,
            start=inputs.start,
            until=inputs.until,
            ended=run.ended,
            wall_s=run.wall_s,
            policy=policy,
            seed=inputs.seed,
            faults=inputs.faults,
            held_at_start=len(inputs.held),
            poll_period=run.poll_period,
            under_way_at_start=sum(len(o.under_way) for o in inputs.orders),
        )
        return report, journal.steps(), {p.id: p.part_type for p in journal.parts()}


def play_in_temp(
    inputs: PlanInputs,
    policies: tuple[str, ...],
    *,
    workers: int = 1,
    progress: Progress | None = None,
) -> PlanResult:
    """:func:`play` in a temporary directory, removed after."""
    with tempfile.TemporaryDirectory(prefix="cellctl-plan-") as tmp:
        return play(inputs, policies, Path(tmp), workers=workers, progress=progress)


def check_out(out: Path) -> None:
    """Refuse (UsageError) an ``--out`` directory the plan could not be written to, before
    anything is played: not a directory, not writable, a directory or a link where one of
    its files goes, or a ``cell/`` that is not a plan's own copy (a link, a real cell: see
    :func:`~cellctl.plan.inputs.check_copy_target`). Made if missing."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"{out}: cannot write the plan there: {e.strerror or e}") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise UsageError(f"{out}: cannot write the plan there: not writable")
    for name in (INPUTS_FILE, PLAN_JSON, PLAN_SVG):
        if (out / name).is_dir() or (out / name).is_symlink():
            raise UsageError(f"{out / name}: in the way of the plan's file (remove it)")
    check_copy_target(out / CELL_COPY)


def write_plan(result: PlanResult, out: Path) -> list[Path]:
    """Write ``out/plan.json``, ``out/plan.svg``, ``out/inputs.json`` and ``out/cell/``
    (:func:`check_out` says beforehand whether it can)."""
    check_out(out)
    path = out
    try:
        written = [save_inputs(result.inputs, result.policies, out)]
        path = out / PLAN_JSON
        write_output(path, json.dumps(result.as_dict(), indent=1) + "\n")
        path = out / PLAN_SVG
        write_output(path, result.svg)
    except OSError as e:
        raise UsageError(f"{e.filename or path}: cannot write the plan: {e.strerror}") from None
    return [*written, out / PLAN_JSON, out / PLAN_SVG]


def summary_line(result: PlanResult) -> str:
    """One line per result for a log: the first policy's verdicts and its span."""
    r = result.reports[0]
    return (
        f"plan ({policy_name(r.policy)}): on time {r.on_time}, late {r.late}, "
        f"{span_text(r.ended - r.start)} played in {r.wall_s:.1f} s"
    )


def report_from_dict(data: dict[str, Any]) -> PlanReport:
    """A :class:`PlanReport` again from its :meth:`PlanReport.as_dict` (an API's answer)."""
    from cellctl.plan.engine import FaultWindow
    from cellctl.plan.report import OrderOutcome

    fields = {f.name for f in dataclasses.fields(PlanReport)}
    found = {k: v for k, v in data.items() if k in fields}
    found["orders"] = [OrderOutcome(**o) for o in data.get("orders", [])]
    found["faults"] = [FaultWindow(**f) for f in data.get("faults", [])]
    return PlanReport(**found)


def result_from_dict(data: dict[str, Any], svg: str, base: Path) -> PlanResult:
    """A :class:`PlanResult` again from :meth:`PlanResult.as_dict` and its chart (the
    inputs' cell directory relative to ``base``)."""
    from cellctl.plan.inputs import parse_inputs

    inputs, policies = parse_inputs(data["inputs"], base)
    reports = [report_from_dict(r) for r in data["plans"]]
    return PlanResult(inputs, policies, reports, svg)
