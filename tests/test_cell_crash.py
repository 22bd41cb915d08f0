"""kill -9 of ``cellctl run`` at random points of a run, then a restart, until it settles.

The emulated cell runs in this process; the controller is a real ``python -m cellctl run``
subprocess, killed with SIGKILL at seeded random points (during a transfer, during machining,
between steps). Afterwards every order is done or has its unfinished parts held for
inspection, and no mill cut any physical part twice: that is checked from the mills' own
execution logs (``EmulatedCell.runs_per_part``), not from the controller's journal.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import random
import signal
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from cellctl.cell.journal import INTERRUPTED_TRANSFER
from cellctl.testing.rig import MILL_INDEX, CellRig, where_transferred


async def spawn_controller(directory: Path, log: Path) -> asyncio.subprocess.Process:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    out = log.open("ab")
    try:
        return await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "cellctl",
            "--cell",
            str(directory),
            "run",
            "--no-live",
            stdout=out,
            stderr=out,
            env=env,
        )
    finally:
        out.close()


def kill_points(rig: CellRig, rng: random.Random) -> list[tuple[str, Callable[[], bool]]]:
    """Three or four conditions to kill at, in run order, chosen by ``rng``."""
    points: list[tuple[str, Callable[[], bool]]] = []
    done = 0
    # The first kill always lands in a cut (long enough not to be missed); then any.
    kinds = ["machine"] + [rng.choice(["transfer", "machine", "between"]) for _ in range(3)]
    for kind in kinds[: rng.choice([3, 4])]:
        done += rng.randint(0, 2)
        floor = done

        def open_step(kind: str = kind, floor: int = floor) -> bool:
            return rig.finished_steps() >= floor and bool(rig.open_steps(kind))

        def between(floor: int = floor) -> bool:
            return rig.finished_steps() >= floor and not rig.journal.open_steps()

        if kind == "between":
            points.append((f"between steps after {floor} finished", between))
        else:
            points.append((f"during a {kind} step after {floor} finished", open_step))
    return points


async def operator_inspects(rig: CellRig) -> None:
    """Clear the alarms; find each held part in the cell and release it where it is.

    After a kill the machines finished what they were doing: a transfer's part is where
    the arm left it, a cut ran to its end; a transfer the running controller stopped
    mid-way left its part in the gripper, which goes back by hand. The operator looks (the
    emulators' physical state) and says so: a part in a vise whose mill's log shows its cut
    counts as cut.
    """
    await rig.clear_alarms()
    for part in rig.held_parts():
        step = rig.journal.steps(part.id)[-1]
        if step.kind == "transfer":
            where = await where_transferred(rig.cell, rig.journal, step)
            result = await rig.cli("part", "release", part.id, "--at", where)
        else:
            blank = rig.cell.vise[MILL_INDEX[step.machine]]
            assert blank is not None, rig.describe()
            cut = rig.cell.runs_per_part().get(blank, {}).get(step.machine, 0)
            args = ["part", "release", part.id] + ([] if cut else ["--redo"])
            result = await rig.cli(*args)
        assert result.exit_code == 0, result.output


@pytest.mark.parametrize("seed", [7, 2024])
@pytest.mark.timeout(240)
async def test_kill_9_and_restart_never_cuts_a_part_twice(tmp_path: Path, seed: int) -> None:
    rng = random.Random(seed)
    directory = tmp_path / "cell"
    log = tmp_path / "controller.log"
    async with CellRig(directory, time_scale=300.0) as rig:
        rig.post("wax-robot-base", 2, "A")
        rig.post("wax-toy-mill-table", 1, "B")
        kills = []
        for what, condition in kill_points(rig, rng):
            if rig.held_parts():
                await operator_inspects(rig)
            proc = await spawn_controller(directory, log)
            try:
                await rig.wait_for(
                    lambda c=condition, p=proc: c() or p.returncode is not None or rig.all_done(),  # type: ignore[misc]
                    what,
                    timeout=60,
                )
            finally:
                assert proc.returncode is None, log.read_text(errors="replace")
                proc.send_signal(signal.SIGKILL)
                await proc.wait()
            if rig.all_done():
                break  # the run got there first: no more points to kill at
            kills.append(what)
            in_flight = {s.part_id: s for s in rig.journal.open_steps()}
            # The restart holds every part whose step was in flight: nothing is restarted.
            proc = await spawn_controller(directory, log)
            try:
                await rig.wait_for(
                    lambda f=in_flight: not (set(f) - {p.id for p in rig.held_parts()}),  # type: ignore[misc]
                    "the interrupted parts held after the restart",
                )
                for part_id, step in in_flight.items():
                    note = rig.journal.get_part(part_id).note
                    if step.kind == "machine":
                        assert note.startswith("needs inspection"), note
                    else:
                        assert note == INTERRUPTED_TRANSFER, note
            finally:
                proc.send_signal(signal.SIGKILL)
                await proc.wait()
        assert kills
        # The last run: the operator releases what is held; it ends on SIGINT.
        starts = log.read_text(errors="replace").count("and the PLC: running")
        proc = await spawn_controller(directory, log)
        try:
            await rig.wait_for(
                lambda: log.read_text(errors="replace").count("and the PLC: running") > starts,
                "the controller up",
            )
            for _ in range(10):
                await operator_inspects(rig)
                await rig.wait_for(
                    lambda: rig.all_done() or rig.held_parts(), "done, or held again", timeout=90
                )
                if rig.all_done():
                    break
        finally:
            if proc.returncode is None:
                proc.send_signal(signal.SIGINT)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(30):
                    await proc.wait()
        assert proc.returncode == 0, log.read_text(errors="replace")[-3000:]

        assert rig.all_done(), rig.describe()
        # From the mills' own execution logs: no program ran twice on one physical part.
        assert rig.cut_twice() == {}, f"kills: {kills}\n{rig.describe()}"
        assert sorted(rig.cell.outfeed) == ["P1", "P2", "P3"], rig.describe()
        assert all(r == {"cnc1": 1, "cnc2": 1} for r in rig.cell.runs_per_part().values())
        held = {r.part_id for r in rig.reports("part-held")}
        assert held, f"no kill landed in a step: {kills}"


@pytest.mark.virtual
async def test_a_pulse_left_high_by_a_killed_controller_is_lowered_at_start(
    tmp_path: Path,
) -> None:
    """Killed between the two writes of a pulse, a controller leaves its coil high; the next
    one lowers it first, so its own first pulse is a rising edge the conveyor hears."""
    async with CellRig(tmp_path / "cell") as rig:
        plc = rig.cell.plc
        plc.coils["pallet_request"] = True  # as the dead controller left it: no pallet came
        plc.coils["go_1"] = True
        rig.post("wax-robot-base", 1, "A")
        await rig.start_controller()
        await rig.wait_for(rig.all_done, "order A done")
        assert [a.text for a in rig.journal.alarms()] == [], rig.describe()
        assert plc.pallets_delivered == 1 and plc.coils["go_1"] is False
        assert rig.cut_twice() == {}


@pytest.mark.timeout(120)
async def test_ctrl_c_with_its_output_pipe_gone_still_lets_the_steps_finish(
    tmp_path: Path,
) -> None:
    """`cellctl run | tee run.log`, and one Ctrl-C: the terminal sends it to both, tee goes
    first, and the controller's next line meets a closed pipe. The stop is still the clean
    one (the steps in flight finish, nothing held), and its exit status 0."""
    directory = tmp_path / "cell"
    errors = tmp_path / "stderr"
    async with CellRig(directory, time_scale=300.0) as rig:
        rig.post("wax-robot-base", 1, "A")
        read, write = os.pipe()
        with errors.open("wb") as err:
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "cellctl", "--cell", str(directory), "run", "--no-live",
                stdout=write, stderr=err, env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )  # fmt: skip
        os.close(write)
        try:
            await rig.wait_for(lambda: rig.open_steps("machine"), "a cut in flight", timeout=60)
            os.close(read)  # tee is gone
            proc.send_signal(signal.SIGINT)
            async with asyncio.timeout(60):
                await proc.wait()
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
        said = errors.read_text(errors="replace")
        assert proc.returncode == 0, said[-3000:]
        assert "Traceback" not in said, said[-3000:]
        assert rig.held_parts() == [], rig.describe()
        assert rig.journal.open_steps() == [] and all(
            s.state == "finished" for s in rig.journal.steps()
        ), rig.describe()
