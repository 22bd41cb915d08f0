"""A factory of two kinds of cell: the cobot-tending cell (examples/cell-tending: a UR5e, an
iso-cnc control and a Dyna 2400) and the example lab cell, each emulated from its own
template, a real Mosquitto, each cell's ``cellctl run`` and ``cellctl factory run`` as their
own processes. The factory gives each order to the cell that makes its part type; the
tending cell makes its brackets (the emulators' own record: each on the conveyor, cut once);
and ``cellctl factory cells`` / ``orders`` show the tending cell with its machines, their
kinds, and its orders done: nothing in the factory's code knows a UR from a 7545."""

from __future__ import annotations

import asyncio
import json
import signal
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from cellctl.cell.config import load_cell
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.factory.config import load_factory
from cellctl.factory.store import DONE
from cellctl.ui.cli import main as cli_main
from tests.conftest import CELLCTL
from tests.factory_plant import CLI_S, Plant

TENDING = Path(__file__).resolve().parent.parent / "examples" / "cell-tending"


@pytest.fixture
async def plant(tmp_path: Path) -> AsyncIterator[Plant]:
    """cell1 the tending cell, cell2 the lab cell; their controllers and the factory's."""
    async with Plant(tmp_path / "plant", cells=2, templates=[TENDING]) as p:
        await p.start_all()
        yield p


async def factory_cli(plant: Plant, *args: str) -> str:
    """What ``cellctl factory --dir PLANT ARGS`` prints (through click, in a worker thread:
    the plant's emulators keep running in this loop)."""
    argv = ["factory", "--dir", str(plant.directory), *args]

    def invoke() -> Any:
        return CliRunner().invoke(cli_main, argv, env={"COLUMNS": "200"})

    async with asyncio.timeout(CLI_S):
        result = await asyncio.to_thread(invoke)
    assert result.exit_code == 0, f"{args}: {result.output}\n{plant.describe()}"
    return str(result.output)


@pytest.mark.timeout(120)  # beyond the plant's own deadlines: they say more
async def test_a_factory_with_a_cobot_tending_cell(plant: Plant) -> None:
    tending, lab = plant.names
    brackets = sorted(plant.part_types(tending))
    lab_types = sorted(plant.part_types(lab))
    assert not set(brackets) & set(lab_types), "the test needs types only one cell makes"
    batch = [
        ("T1", brackets[0], 2),
        ("L1", lab_types[0], 1),
        ("T2", brackets[0], 1),
        ("L2", lab_types[-1], 1),
    ]
    plant.submit(batch)
    await plant.wait_for(
        lambda: len(plant.done()) == len(batch) and plant.reports_caught_up(),
        "every order done, the factory up to date with both cells' reports",
        timeout=90,
    )
    state = plant.describe()
    orders = {o.id: o for o in plant.store.orders()}
    for oid, part_type, qty in batch:
        maker = tending if part_type in brackets else lab
        o = orders[oid]
        assert (o.cell, o.state, o.done) == (maker, DONE, qty), f"{oid}\n{state}"
        assert plant.mailboxes[maker].get_order(oid).state == DONE, state
    # The tending cell's emulators: every bracket on the conveyor, cut once on each mill
    # that names it (the iso-cnc's run may start, its operator's, before a part is clamped).
    made = sum(qty for _, part_type, qty in batch if part_type in brackets)
    cell = plant.cell(tending)
    assert sorted(cell.outfeed) == [f"P{n}" for n in range(1, made + 1)], state
    runs = cell.runs_per_part()
    assert {p: r.get("cnc2") for p, r in runs.items()} == dict.fromkeys(cell.outfeed, 1), state
    assert all(n == 1 for r in runs.values() for n in r.values()), state
    assert len(plant.cell(lab).outfeed) == sum(q for _, t, q in batch if t in lab_types), state

    # What the factory shows: the tending cell, its machines with their kinds, its orders.
    cells = {c["cell"]: c for c in json.loads(await factory_cli(plant, "cells", "--json"))}
    shown = cells[tending]
    assert (shown["status"], shown["makes"]) == ("online", brackets), shown
    config = load_cell(plant.cell_dir(tending))
    # Its robot and mills, each with its kind, and the PLC of its doors and vises.
    machines = {m.name: m.kind for m in [config.robot, *config.mills]} | {"plc": "plc"}
    assert {m: v["kind"] for m, v in shown["machines"].items()} == machines, shown
    assert all(v["state"] and v["in_service"] for v in shown["machines"].values()), shown
    listed = json.loads(await factory_cli(plant, "orders", "--json"))
    at_tending = {o["id"]: o["state"] for o in listed if o["cell"] == tending}
    assert at_tending == {oid: DONE for oid, t, _ in batch if t in brackets}, listed
    # The operator's table: the tending cell's row names each of its machines and its type.
    table = await factory_cli(plant, "cells", "--wide")
    row = [line for line in table.splitlines() if f" {tending} " in line]
    assert row and brackets[0] in row[0], table
    assert all(f"{name}:" in table for name in machines), table


async def test_cellctl_emulate_factory_takes_a_template_per_cell(tmp_path: Path) -> None:
    """``cellctl emulate factory --template DIR``: cell1 emulates DIR (its machines, its part
    types in the commands it prints), the cells past the templates the example cell."""
    directory = tmp_path / "plant"
    args = ["emulate", "factory", "--cells", "2", "--template", str(TENDING), str(directory)]
    proc = await asyncio.create_subprocess_exec(
        *CELLCTL, *args, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT
    )
    assert proc.stdout is not None
    said: list[str] = []
    try:
        # The commands to try (one order per cell's first part type), then that it serves.
        while not said or not said[-1].startswith("serving until Ctrl-C"):
            try:
                async with asyncio.timeout(60):
                    line = (await proc.stdout.readline()).decode()
            except TimeoutError:
                raise AssertionError(f"no more within 60 s: {''.join(said)}") from None
            assert line, f"it exited: {''.join(said)}"
            said.append(line)
        text = "".join(said)
        tending, lab = load_cell(directory / "cell1"), load_cell(directory / "cell2")
        template, example = load_cell(TENDING), load_cell(EXAMPLE_CELL)
        assert tending.robot.kind == template.robot.kind != example.robot.kind
        assert [m.kind for m in tending.mills] == [m.kind for m in template.mills]
        assert [m.kind for m in lab.mills] == [m.kind for m in example.mills]
        assert (set(tending.parts), set(lab.parts)) == (set(template.parts), set(example.parts))
        for part_type in [*template.parts][:1] + [*example.parts][:1]:
            assert f"submit {part_type} " in text, text
        assert f"emulates {TENDING}" in text, text
        assert set(load_factory(directory).cells) == {"cell1", "cell2"}
    finally:
        if proc.returncode is None:
            proc.send_signal(signal.SIGINT)
            try:
                async with asyncio.timeout(30):
                    await proc.wait()
            except TimeoutError:
                proc.kill()
                await proc.wait()


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--cells", "1", "--template", str(TENDING), "--template", str(TENDING)], "2 --template"),
        (["--template", str(TENDING / "robot")], "no cell.toml"),
        (["--template", "{robotless}"], "no robot machine to emulate"),
    ],
)
def test_emulate_factory_refuses_templates_it_cannot_serve(
    tmp_path: Path, args: list[str], words: str
) -> None:
    """Refused before a broker or a machine starts, or a file is written."""
    robotless = tmp_path / "robotless"
    robotless.mkdir()
    (robotless / "cell.toml").write_text('[cell]\nname = "no machines"\n')
    args = [a.format(robotless=robotless) for a in args]
    result = CliRunner().invoke(cli_main, ["emulate", "factory", *args, str(tmp_path / "p")])
    assert result.exit_code == 2, result.output
    assert words in result.output
    assert not (tmp_path / "p").exists()


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--template", str(TENDING)], "--template is for --factory"),
        (["--factory", "2", *["--template", str(TENDING)] * 3], "3 --template for 2 cells"),
    ],
)
def test_the_demo_refuses_templates_it_cannot_use(
    tmp_path: Path, args: list[str], words: str
) -> None:
    out = tmp_path / "demo-out"
    result = CliRunner().invoke(cli_main, ["demo", *args, "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert words in result.output
    assert not (out / "factory").exists()
