"""``cellctl factory plan``: ``cellctl plan`` over every cell of a factory whose directory is
on this host (``FACTORY_DIR/CELL``, as ``cellctl emulate factory`` writes them, or
``--cell-dir CELL=DIR``)::

    cellctl factory --dir plant plan --shift 8h
    cellctl factory --dir plant plan --fault cell2/cnc2:down@10:00-11:00 --out plan-out

Each cell is asked through its own control API (``plan.run``: its open orders, held parts
and machines out of service now), the running cells side by side, each playing in its own
controller's process; the cells no controller runs are played from their files side by side
too, in worker processes (one a core). The factory's orders not yet given to a cell are not
in any cell's plan.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import click

from cellctl.errors import EXIT_CODES, CellctlError, UsageError, exit_code
from cellctl.ui.common import console, fail, print_json, print_line
from cellctl.ui.plan_cli import poll_option


async def _ask(directory: Path, params: dict[str, Any], span_s: float) -> Any:
    """Cell ``directory``'s ``plan.run`` answer (waited for as ``cellctl plan`` waits: while
    its play goes on), or its refusal (kept: the other cells go on)."""
    from cellctl.service.client import open_cell, plan_call

    try:
        async with await open_cell(directory, {}) as cell:
            return await plan_call(cell, params, span_s)
    except CellctlError as e:
        return e


def _plan_here(directory: str, params: dict[str, Any], span_s: float) -> tuple[str, Any]:
    """A worker process's plan of the cell no controller runs at ``directory``: ("plan",
    answer) or ("refused", why) (an error's words cross the process boundary, not its
    object)."""
    import asyncio

    answer = asyncio.run(_ask(Path(directory), params, span_s))
    if isinstance(answer, CellctlError):
        return "refused", (exit_code(answer), str(answer))
    return "plan", answer


def _refusal(code: int, words: str) -> CellctlError:
    """A worker process's refusal as an error of its kind again (by its exit code, the one
    table of them: :data:`cellctl.errors.EXIT_CODES`)."""
    return _of_kind(next((k for k, c in EXIT_CODES.items() if c == code), CellctlError), words)


def _of_kind(kind: type[CellctlError], words: str) -> CellctlError:
    try:
        return kind(words)
    except TypeError:  # a kind made of more than words (a device's code): said as is
        return CellctlError(words)


def _no_plan(refused: dict[str, CellctlError | str]) -> CellctlError:
    """No cell planned: every cell's refusal in one line, of the kind of the first that is
    not the caller's input (a refused token, a link down), else a usage error: its exit
    code is the one a single cell's `cellctl plan` would give."""
    errors = [e for e in refused.values() if isinstance(e, CellctlError)]
    first = next((e for e in errors if not isinstance(e, UsageError)), None)
    words = "; ".join(f"{name}: {why}" for name, why in refused.items())
    return _of_kind(type(first), words) if first is not None else UsageError(words)


def _cell_dirs(
    factory_dir: Path, cells: list[str], given: tuple[str, ...]
) -> tuple[dict[str, Path], dict[str, str]]:
    """The cells' directories on this host, and why each other cell is not planned (its
    directory is elsewhere: on the host that runs it). A ``--cell-dir`` with no cell is
    refused: it was said to be there."""
    mapping: dict[str, Path] = {}
    for text in given:
        name, sep, where = text.partition("=")
        if not sep or name not in cells:
            raise UsageError(f"--cell-dir {text!r}: write CELL=DIR, CELL one of {', '.join(cells)}")
        if not (Path(where) / "cell.toml").is_file():
            raise UsageError(f"--cell-dir {text!r}: no cell there (no {where}/cell.toml)")
        mapping[name] = Path(where)
    found, away = {}, {}
    for name in cells:
        directory = mapping.get(name, factory_dir / name)
        if (directory / "cell.toml").is_file():
            found[name] = directory
        else:
            away[name] = f"not on this host (no {directory}/cell.toml; --cell-dir {name}=DIR)"
    if not found:
        raise UsageError(
            f"no cell directory of {', '.join(cells)} on this host (looked in {factory_dir}/"
            "CELL; say where with --cell-dir CELL=DIR)"
        )
    return found, away


def _faults_by_cell(faults: tuple[str, ...], cells: dict[str, Path]) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {name: [] for name in cells}
    for text in faults:
        name, sep, rest = text.partition("/")
        if not sep or name not in cells:
            raise UsageError(
                f"--fault {text!r}: write CELL/MACHINE:FAULT@HH:MM-HH:MM, CELL one of "
                f"{', '.join(cells)}"
            )
        out[name].append(rest)
    return out


def _check(
    cells: dict[str, Path],
    windows: dict[str, list[str]],
    shift: str | None,
    until: str | None,
    policy: str,
) -> float:
    """The options against each cell's own machines and faults, before any cell is asked
    (each cell checks them again at its own time); the plan's span, s."""
    from cellctl.cell.config import load_cell
    from cellctl.clock import current_clock
    from cellctl.plan.spec import check_inputs, parse_fault, plan_window, policies_of

    now = current_clock().now()
    end = plan_window(now, shift, until)
    policies = policies_of(policy)
    for name, texts in windows.items():
        found = [parse_fault(text, now) for text in texts]
        try:
            check_inputs(load_cell(cells[name]), [], found, policies, end)
        except UsageError as e:
            raise UsageError(f"{name}: {e}") from None
    return end - now


@click.command("plan")
@click.option("--shift", metavar="SPAN", help="How far ahead: 8h, 90m, 2d ...  [default: 8h]")
@click.option("--until", metavar="TIME", help="Or up to: 'FRI 18:00', 18:00, 2026-11-27T18:00.")
@click.option(
    "--fault",
    "faults",
    multiple=True,
    metavar="CELL/MACHINE:FAULT@HH:MM-HH:MM",
    help="A fault window in one cell (repeatable): cell2/cnc2:down@10:00-11:00.",
)
@click.option(
    "--policy",
    default="default",
    show_default=True,
    metavar="NAME",
    help="The scheduler's policy in every cell: default, one-at-a-time, ... or all.",
)
@click.option(
    "--seed",
    type=click.IntRange(0, 2**63 - 1),
    default=0,
    show_default=True,
    metavar="N",
    help="Seed of anything random in the emulated machines.",
)
@poll_option
@click.option(
    "--cell-dir",
    "cell_dirs",
    multiple=True,
    metavar="CELL=DIR",
    help="Where a cell's directory is (default FACTORY_DIR/CELL).",
)
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    help="Write each cell's plan (plan.json, plan.svg, inputs.json) in OUT/CELL.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the plans as JSON.")
@click.pass_context
def factory_plan(
    ctx: click.Context,
    shift: str | None,
    until: str | None,
    faults: tuple[str, ...],
    policy: str,
    seed: int,
    poll: float | None,
    cell_dirs: tuple[str, ...],
    out: Path | None,
    as_json: bool,
) -> None:
    """What every cell of the factory finishes, and when: `cellctl plan` for each."""
    import asyncio
    import contextlib

    from cellctl.cell.owner import controller_holder
    from cellctl.factory.config import load_factory
    from cellctl.plan.run import check_out, result_from_dict, write_plan
    from cellctl.tasks import spawned_pool

    factory_dir = Path(ctx.obj["factory_dir"])
    try:
        config = load_factory(factory_dir)
        cells, away = _cell_dirs(factory_dir, list(config.cells), cell_dirs)
        windows = _faults_by_cell(faults, cells)
        span_s = _check(cells, windows, shift, until, policy)
        if out is not None:  # before any cell's plan is played
            for name in cells:
                check_out(out / name)
    except CellctlError as e:
        fail(e)
    params: dict[str, Any] = {k: v for k, v in (("shift", shift), ("until", until)) if v}
    params.update(policy=policy, seed=seed)
    if poll is not None:
        params["poll"] = poll

    asked = {name: {**params, "fault": windows[name]} for name in cells}
    # A cell with a controller plays its plan in that controller's process; the others in
    # worker processes here. All side by side: a factory's cells are planned in the time of
    # its longest, given the cores.
    running = {name: d for name, d in cells.items() if controller_holder(d)}

    async def ask_running() -> dict[str, Any]:
        answers = await asyncio.gather(
            *(_ask(d, asked[name], span_s) for name, d in running.items())
        )
        return dict(zip(running, answers, strict=True))

    others = {name: d for name, d in cells.items() if name not in running}
    # A plan is CPU-bound: the cells take the time of the longest, given the cores.
    with spawned_pool(len(others)) if others else contextlib.nullcontext() as pool:
        planned = (
            {}
            if pool is None
            else {
                name: pool.submit(_plan_here, str(d), asked[name], span_s)
                for name, d in others.items()
            }
        )
        answers = asyncio.run(ask_running())
        for name, future in planned.items():
            what, answer = future.result()
            answers[name] = _refusal(*answer) if what == "refused" else answer
    plans: dict[str, Any] = {}
    refused: dict[str, CellctlError | str] = dict(away)
    for name, directory in cells.items():
        try:
            answer = answers[name]
            if isinstance(answer, CellctlError):
                raise answer
            result = result_from_dict(answer["plan"], answer["svg"], directory)
        except CellctlError as e:  # one cell's refusal (no open orders ...): the others go on
            refused[name] = e
            continue
        result.inputs = dataclasses.replace(result.inputs, cell_dir=directory)
        plans[name] = result
        if out is not None:
            try:
                write_plan(result, out / name)
            except CellctlError as e:
                fail(e)
    if not plans:
        fail(_no_plan(refused))
    if as_json:
        print_json(
            {name: r.as_dict() for name, r in plans.items()}
            | {name: {"refused": str(why)} for name, why in refused.items()}
        )
        return
    for name, result in plans.items():
        print_line(f"== {name} ({cells[name]})")
        for line in result.lines():
            print_line(line)
        print_line("")
    # "factory plant", but "factory" (the default name) or "north factory" as it is
    named = config.name if "factory" in config.name.lower() else f"factory {config.name}"
    count = len(plans)
    print_line(f"{named}: {count} cell{'' if count == 1 else 's'} planned")
    for name, result in plans.items():
        r = result.reports[0]
        made = sum(r.parts_made.values())
        # Orders the plan does not finish within its span are said, not left to be inferred.
        open_ones = sum(o.finished is None for o in r.orders)
        print_line(
            f"  {name:<10} on time {r.on_time}, late {r.late}, not finished {open_ones}, "
            f"parts made {made}"
        )
    for name, why in refused.items():
        print_line(f"  {name:<10} not planned: {why}")
    for name in plans if out is not None else ():
        console.print(f"saved {out}/{name}/plan.json, plan.svg, inputs.json", markup=False)
