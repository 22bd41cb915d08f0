"""``cellctl cell check``: every problem of a bad cell.toml, and a non-zero exit."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from cellctl.cell.config import check_cell, load_cell
from cellctl.cell.controller import ControllerOptions
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.errors import UsageError
from cellctl.ui.cli import main


def example_copy(tmp_path: Path) -> Path:
    directory = tmp_path / "cell"
    shutil.copytree(EXAMPLE_CELL, directory)
    return directory


def edit(directory: Path, old: str, new: str) -> None:
    toml = directory / "cell.toml"
    text = toml.read_text(encoding="utf-8")
    assert old in text, old
    toml.write_text(text.replace(old, new, 1), encoding="utf-8")


def cell_check(directory: Path) -> tuple[int, str]:
    result = CliRunner().invoke(
        main, ["--cell", str(directory), "cell", "check"], env={"COLUMNS": "500"}
    )
    return result.exit_code, result.output


def test_the_example_cell_is_ok(tmp_path: Path) -> None:
    code, out = cell_check(example_copy(tmp_path))
    assert code == 0, out
    assert "ok: robot robot, mills cnc1, cnc2, 5 robot programs" in out
    config = load_cell(EXAMPLE_CELL)
    assert [m.name for m in config.mills] == ["cnc1", "cnc2"]
    assert config.parts["wax-robot-base"].transfers() == [
        "conveyor_to_cnc1",
        "cnc1_to_cnc2",
        "cnc2_to_conveyor",
    ]
    options = ControllerOptions.from_config(config)
    assert (options.retries, options.fail_limit, options.poll_period) == (2, 3, 0.5)


def test_every_problem_is_printed(tmp_path: Path) -> None:
    directory = example_copy(tmp_path)
    edit(directory, 'kind = "ibm7545"', 'kind = "puma560"')  # robot of an unknown kind
    edit(directory, 'setup = "programs/cnc2_setup.dyn"\n', "")  # a mill without setup
    edit(directory, 'go_output = "go_1"', 'go_output = "go_9"')  # no such PLC coil
    edit(directory, "poll_period = 0.5", "poll_period = 0")
    edit(directory, '"robot/cnc1_to_cnc2.aml"', '"robot/missing.aml"')
    edit(
        directory,
        '{ mill = "cnc2", program = "programs/toy_mill_table_finish_cnc2.dyn" }',
        '{ mill = "cnc3", program = "programs/toy_mill_table_finish_cnc2.dyn" }',
    )
    code, out = cell_check(directory)
    assert code != 0
    expected = [
        "[machines.robot] kind: 'puma560'",
        "[machines.cnc2] setup: a mill needs its setup program",
        "[machines.cnc1] go_output: no PLC coil 'go_9'",
        "[cell] poll_period: Input should be greater than 0, not 0 (line 12)",
        "[robot_programs] cnc1_to_cnc2:",
        "[parts.wax-toy-mill-table] route[2].mill: unknown mill 'cnc3'",
        "problem(s) in",
    ]
    for text in expected:
        assert text in out, f"{text!r} missing from:\n{out}"
    # The robot's kind said once: not again as "[cell] robot: no robot machine 'robot'".
    assert "[cell] robot:" not in out, out
    with pytest.raises(UsageError, match="puma560"):
        load_cell(directory)


def test_broken_programs_are_found(tmp_path: Path) -> None:
    directory = example_copy(tmp_path)
    (directory / "programs" / "robot_base_rough_cnc1.dyn").write_text(
        "this is not DYNALAN\n", encoding="ascii"
    )
    (directory / "robot" / "conveyor_to_cnc1.aml").write_text("MOVE(\n", encoding="utf-8")
    config, problems = check_cell(directory)
    assert config is None
    assert any("robot_base_rough_cnc1.dyn" in p for p in problems), problems
    assert any(p.startswith("[robot_programs] conveyor_to_cnc1") for p in problems), problems
    code, out = cell_check(directory)
    assert code != 0
    assert "robot_base_rough_cnc1.dyn" in out and "conveyor_to_cnc1" in out


def test_missing_sections_and_files(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    code, out = cell_check(empty)
    assert code != 0
    assert "no such file" in out

    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "cell.toml").write_text("[cell\nname = 1\n", encoding="utf-8")
    code, out = cell_check(bad)
    assert code != 0 and "not valid TOML" in out

    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "cell.toml").write_text('[cell]\nname = "nothing"\n', encoding="utf-8")
    config, problems = check_cell(bare)
    assert config is None
    assert "[plc]: missing (url of the cell's Modbus/TCP PLC)" in problems
    assert "[parts]: no part types: the cell has nothing to make" in problems
    assert any(p.startswith("[cell] robot:") for p in problems)
    code, out = cell_check(bare)
    assert code != 0 and f"{len(problems)} problem(s)" in out


def test_a_part_needs_every_transfer_program(tmp_path: Path) -> None:
    directory = example_copy(tmp_path)
    edit(directory, 'cnc2_to_conveyor = "robot/cnc2_to_conveyor.aml"\n', "")
    config, problems = check_cell(directory)
    assert config is None
    assert "[parts.wax-robot-base] needs robot program 'cnc2_to_conveyor' in [robot_programs]" in (
        problems
    )
    assert len([p for p in problems if "cnc2_to_conveyor" in p]) == 2  # both part types


def test_a_declared_part_type_with_a_problem_is_not_told_as_none(tmp_path: Path) -> None:
    """Part types declared, each with a problem of its own: that problem is told, and no
    false "no part types" beside it; no [parts] at all (or an empty one) still says so."""
    directory = example_copy(tmp_path)
    (directory / "programs" / "robot_base_rough_cnc1.dyn").unlink()
    (directory / "programs" / "toy_mill_table_finish_cnc2.dyn").unlink()
    code, out = cell_check(directory)
    assert code != 0
    assert "[parts.wax-robot-base] route[1].program:" in out and "no such file" in out
    assert "[parts.wax-toy-mill-table] route[2].program:" in out
    assert "no part types" not in out
    assert "2 problem(s)" in out

    toml = directory / "cell.toml"
    without_parts = toml.read_text(encoding="utf-8").split("[parts.", 1)[0]
    for tail in ("", "[parts]\n"):
        toml.write_text(without_parts + tail, encoding="utf-8")
        config, problems = check_cell(directory)
        assert config is None
        assert problems == ["[parts]: no part types: the cell has nothing to make"], tail
    # Not a table: told once, as what it is.
    toml.write_text("parts = 3\n" + without_parts, encoding="utf-8")
    problems = check_cell(directory)[1]
    assert [p for p in problems if p.startswith("[parts]")] == ["[parts]: must be a table, not int"]


def test_a_vise_opening_program_names_a_mill(tmp_path: Path) -> None:
    directory = example_copy(tmp_path)
    edit(directory, "open_vise_cnc2 =", "open_vise_cnc3 =")
    code, out = cell_check(directory)
    assert code != 0
    assert (
        "[robot_programs] open_vise_cnc3: no mill 'cnc3' (open_vise_<mill> opens that mill's "
        "vise; mills: cnc1, cnc2)"
    ) in " ".join(out.split())  # one line however wide the terminal


def test_a_cell_beyond_what_the_factory_carries_is_refused(tmp_path: Path) -> None:
    """Names and counts past the wire's limits are told by `cell check`, not dropped later."""
    from cellctl.mailbox import wire

    directory = example_copy(tmp_path)
    route = (
        'route = [{ mill = "cnc1", program = "programs/robot_base_rough_cnc1.dyn" }, '
        '{ mill = "cnc2", program = "programs/robot_base_finish_cnc2.dyn" }]\n'
    )
    names = [f"extra-{i}" for i in range(wire.MAX_PART_TYPES)] + ["p" * (wire.MAX_NAME + 1)]
    edit(
        directory, 'name = "CIM laboratory machining cell"', f'name = "{"c" * (wire.MAX_NAME + 1)}"'
    )
    with (directory / "cell.toml").open("a", encoding="utf-8") as toml:
        toml.write("".join(f"\n[parts.{n}]\n{route}" for n in names))
    code, out = cell_check(directory)
    assert code == 1
    assert f"{wire.MAX_NAME + 1} characters: at most {wire.MAX_NAME}" in out
    assert f"{len(names) + 2} entries: a cell has at most {wire.MAX_PART_TYPES}" in out
    assert out.count("characters: at most") == 2, out
