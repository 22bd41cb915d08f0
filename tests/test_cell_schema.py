"""cell.toml has one schema: every wrong value is a problem with its TOML path (never a crash),
the [api] table, and docs/cell.md's reference table is the schema's own rendering."""

from __future__ import annotations

import math
import re
import shutil
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from cellctl.cell.config import check_cell, load_cell, reference_table
from cellctl.errors import UsageError

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "cell"


@pytest.fixture(scope="module")
def cell_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("template") / "cell"
    shutil.copytree(EXAMPLE, directory)
    return directory


def _edited(template: Path, target: Path, old: str, new: str) -> Path:
    shutil.copytree(template, target)
    toml = target / "cell.toml"
    text = toml.read_text()
    assert old in text, old
    toml.write_text(text.replace(old, new, 1))
    return target


# The type-swapped values that crashed `cell check` before the schema, and nan.
SWAPPED = [
    ("poll_period = 0.5", 'poll_period = "fast"', "[cell] poll_period: Input should be"),
    ("poll_period = 0.5", "poll_period = nan", "[cell] poll_period: Input should be a finite"),
    ("poll_period = 0.5", "poll_period = inf", "[cell] poll_period: Input should be a finite"),
    ('mills = ["cnc1", "cnc2"]', "mills = true", "[cell] mills: Input should be a valid list"),
    ('robot = "robot"\nmills', 'robot = ["robot"]\nmills', "[cell] robot: Input should be"),
    (
        'kind = "ibm7545"',
        'kind = ["ibm7545"]',
        "[machines.robot] kind: Input should be a valid string",
    ),
    ('line = "4800,7E2"', 'line = "4800,7E2"\noptions = "x"', "[machines.robot] options:"),
    (
        '{ mill = "cnc1", program = "programs/robot_base_rough_cnc1.dyn" },',
        '"cnc1",',
        "[parts.wax-robot-base] route[1]: Input should be",
    ),
    (
        '[plc]\nurl = "modbus://192.0.2.20:502"',
        '[[plc]]\nurl = "modbus://192.0.2.20:502"',
        "[plc]: must be a table, not list",
    ),
    ("retries = 2", "retries = true", "[cell] retries: Input should be a valid integer"),
    ("done_output = 6", "done_output = 17", "[cell] done_output: Input should be less than"),
    ("[cell]", "[cell]\nspeed = 1", "[cell] speed: unknown key"),
    ("[plc]", "[api]\nlisten = 7125\n\n[plc]", "[api] listen: Input should be a valid string"),
    ("[plc]", '[api]\nlisten = "192.0.2.1:7125"\n\n[plc]', "not a loopback address"),
    ("[plc]", '[api]\nlisten = "nowhere"\n\n[plc]', 'write "HOST:PORT"'),
    (
        'program = "programs/robot_base_rough_cnc1.dyn"',
        'program = "programs/gone.dyn"',
        "[parts.wax-robot-base] route[1].program:",
    ),
]


@pytest.mark.parametrize(("old", "new", "problem"), SWAPPED)
def test_a_wrong_value_is_a_problem_with_its_path(
    cell_template: Path, tmp_path: Path, old: str, new: str, problem: str
) -> None:
    directory = _edited(cell_template, tmp_path / "cell", old, new)
    config, problems = check_cell(directory)
    assert config is None
    assert any(problem in p for p in problems), problems
    with pytest.raises(UsageError):
        load_cell(directory)


def test_problems_carry_their_line(cell_template: Path, tmp_path: Path) -> None:
    directory = _edited(cell_template, tmp_path / "cell", "poll_period = 0.5", "poll_period = -1")
    _, problems = check_cell(directory)
    text = (directory / "cell.toml").read_text().splitlines()
    [problem] = [p for p in problems if p.startswith("[cell] poll_period")]
    line = int(re.search(r"\(line (\d+)\)", problem).group(1))  # type: ignore[union-attr]
    assert text[line - 1].startswith("poll_period = -1")


def test_every_problem_at_once(cell_template: Path, tmp_path: Path) -> None:
    directory = _edited(cell_template, tmp_path / "cell", "poll_period = 0.5", "poll_period = nan")
    toml = directory / "cell.toml"
    toml.write_text(toml.read_text().replace('kind = "dyna2400"', "kind = 2400", 1))
    _, problems = check_cell(directory)
    assert any(p.startswith("[cell] poll_period") for p in problems)
    assert any(p.startswith("[machines.cnc1] kind") for p in problems)


def test_api_table_reaches_the_config(cell_template: Path, tmp_path: Path) -> None:
    config = load_cell(cell_template)
    assert (config.api_listen, config.api_allow_remote) == (None, False)
    directory = _edited(
        cell_template,
        tmp_path / "cell",
        "[plc]",
        '[api]\nlisten = "192.0.2.1:7125"\nallow_remote = true\n\n[plc]',
    )
    config = load_cell(directory)
    assert (config.api_listen, config.api_allow_remote) == ("192.0.2.1:7125", True)
    assert config.poll_period == 0.5 and config.raw["api"]["allow_remote"] is True


def test_docs_reference_is_the_schema() -> None:
    text = (ROOT / "docs" / "cell.md").read_text()
    match = re.search(r"<!-- reference: begin -->\n(.*?)<!-- reference: end -->", text, re.S)
    assert match is not None, "docs/cell.md has no generated reference table"
    assert match.group(1) == reference_table()


# -- property: type-swapped documents ------------------------------------------------------------

_SCALARS = st.one_of(
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
)
_VALUES = st.recursive(
    _SCALARS,
    lambda inner: st.one_of(
        st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=6), inner, max_size=3)
    ),
    max_leaves=6,
)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return '"' + "".join(c if c.isalnum() or c in " ._-/:" else "_" for c in value) + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    items = ", ".join(f'"{_toml_key(k)}" = {_toml_value(v)}' for k, v in value.items())
    return "{" + items + "}"


def _toml_key(key: str) -> str:
    return "".join(c if c.isalnum() or c in "_-" else "_" for c in key) or "k"


#: Every key of the example with its table: the property swaps some of them for anything.
_KEYS = [
    ("cell", "poll_period"),
    ("cell", "robot"),
    ("cell", "mills"),
    ("cell", "retries"),
    ("cell", "done_output"),
    ("machines.robot", "kind"),
    ("machines.robot", "link"),
    ("machines.robot", "line"),
    ("machines.cnc1", "setup"),
    ("machines.cnc1", "go_output"),
    ("machines.cnc1", "options"),
    ("plc", "url"),
    ("plc", "coils"),
    ("robot_programs", "conveyor_to_cnc1"),
    ("parts.wax-robot-base", "route"),
    ("api", "listen"),
    ("api", "allow_remote"),
]


@settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(swaps=st.dictionaries(st.sampled_from(_KEYS), _VALUES, min_size=1, max_size=4))
@example(swaps={("cell", "poll_period"): math.nan})
@example(swaps={("cell", "mills"): True})
@example(swaps={("machines.robot", "kind"): ["ibm7545"]})
@example(swaps={("parts.wax-robot-base", "route"): ["cnc1"]})
def test_type_swapped_documents_give_problems_not_crashes(
    cell_template: Path, tmp_path_factory: pytest.TempPathFactory, swaps: dict[Any, Any]
) -> None:
    directory = tmp_path_factory.mktemp("swapped")
    for name in ("programs", "robot"):
        (directory / name).symlink_to(cell_template / name)
    text = (cell_template / "cell.toml").read_text()
    for (table, key), value in swaps.items():
        line = f"{key} = {_toml_value(value)}"
        table_re = re.escape(table)
        pattern = re.compile(
            rf"^(\[{table_re}\]\n(?:(?!\[).*\n)*?){key} = .*(?:\n  .*)*(?:\n\]\n)?", re.M
        )
        if pattern.search(text):
            text = pattern.sub(lambda m, line=line: m.group(1) + line + "\n", text, count=1)
        else:
            text = text.replace(f"[{table}]\n", f"[{table}]\n{line}\n", 1)
            if f"[{table}]\n" not in text:
                text += f"\n[{table}]\n{line}\n"
    (directory / "cell.toml").write_text(text)
    config, problems = check_cell(directory)  # only typed results: no exception escapes
    assert (config is None) == bool(problems)
    assert all(isinstance(p, str) and p for p in problems)
