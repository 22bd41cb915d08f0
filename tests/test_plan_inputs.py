"""What a planner types to `cellctl plan` (durations, times, --add, --fault, --policy, the
orders file, a saved inputs.json): only UsageError comes out of anything, what is valid reads
back as written, and a plan's inputs are refused before anything runs for a machine, fault,
part type or policy the cell does not have."""

from __future__ import annotations

import json
from dataclasses import replace
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from cellctl.cell.config import load_cell
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.errors import UsageError
from cellctl.plan.engine import FaultWindow, PartAt, PlanInputs, PlanOrder
from cellctl.plan.inputs import inputs_dict, parse_inputs
from cellctl.plan.orders_file import orders_csv, parse_orders, read_orders_file
from cellctl.plan.run import play
from cellctl.plan.spec import (
    AddSpec,
    check_inputs,
    parse_add,
    parse_fault,
    plan_inputs,
    policies_of,
)
from cellctl.plan.when import (
    MAX_HORIZON_S,
    parse_duration,
    parse_poll,
    parse_start,
    resolve_when,
)

FAST = settings(max_examples=150, deadline=2000)
#: A Wednesday, 06:00 local time: the plans' start in these tests.
START = datetime(2026, 11, 25, 6, 0).timestamp()

_PIECES = st.sampled_from(
    ["8h", "90m", "1h30m", "2d", "45s", "0h", "FRI", "fri", "18:00", "6:30", "24:00", "9:60",
     "2026-11-27T18:00", "2026-11-27 18:00+01:00", "1999-01-01T00:00", "9999-12-31T23:59",
     ":", "@", "-", "=", " ", "wax-robot-base", "cnc2", "down", "stall", "noise=3e-4,7",
     "40", "-5", "+7", "99999999", "1e9", "é", "\x00", "\n", ",", "\"", "#"]
)  # fmt: skip
TYPED = st.one_of(st.text(max_size=60), st.lists(_PIECES, max_size=8).map("".join))


@FAST
@given(TYPED)
@example("1e400h")
@example("999999d")
def test_anything_typed_as_a_duration_or_time_is_read_or_refused(text: str) -> None:
    for read in (
        parse_duration,
        lambda t: resolve_when(t, START),
        lambda t: parse_start(t, START),
        parse_add,
        lambda t: parse_fault(t, START),
        policies_of,
    ):
        try:
            read(text)
        except UsageError as e:
            assert str(e)


@FAST
@given(
    st.integers(0, 40), st.integers(0, 59), st.integers(0, 59), st.integers(0, 3)
)  # fmt: skip
def test_durations_read_as_written(h: int, m: int, s: int, d: int) -> None:
    text = (f"{d}d" if d else "") + (f"{h}h" if h else "") + (f"{m}m" if m else "") + f"{s}s"
    total = d * 86400 + h * 3600 + m * 60 + s
    if total == 0 or total > MAX_HORIZON_S:
        with pytest.raises(UsageError):
            parse_duration(text)
    else:
        assert parse_duration(text) == total


FORMS = "write a number and a unit, e.g. 8h, 90m, 1h30m, 2d"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("9999..h", f"duration '9999..h': {FORMS} ('9999..' is not a number)"),
        ("1..5h", f"duration '1..5h': {FORMS} ('1..5' is not a number)"),
        ("h", f"duration 'h': {FORMS} (no number before h)"),
        ("30", f"duration '30': {FORMS} (no unit after 30: d, h, m or s)"),
        ("8 hours", f"duration '8 hours': {FORMS} ('hours' is no unit: d, h, m or s)"),
        ("30m 1h", f"duration '30m 1h': {FORMS} (each unit once, the largest first: 1d 4h"),
        ("", f"duration '': {FORMS}"),
        # A number and a unit, too far: said so, not "write a number and a unit".
        ("1234567h", "duration '1234567h': a plan looks at most 31 days ahead"),
        ("9" * 60 + "h", f"duration '{'9' * 40}'...: {FORMS} ({'9' * 20}: too many digits)"),
    ],
)
def test_a_duration_not_understood_is_echoed_with_how_to_write_one(text: str, message: str) -> None:
    with pytest.raises(UsageError) as refused:
        parse_duration(text)
    assert str(refused.value).startswith(message), str(refused.value)
    assert parse_duration("1d 4h") == parse_duration("1d4h") == 28 * 3600


@FAST
@given(st.integers(0, 6), st.integers(0, 23), st.integers(0, 59), st.integers(0, 14 * 24 * 60))
def test_a_day_and_time_is_the_next_one_after_the_start(
    day: int, hour: int, minute: int, offset_min: int
) -> None:
    start = START + offset_min * 60.0
    name = ["MON", "tue", "Wed", "THURSDAY", "fri", "Sat", "sunday"][day]
    found = datetime.fromtimestamp(resolve_when(f"{name} {hour}:{minute:02d}", start))
    assert (found.weekday(), found.hour, found.minute) == (day, hour, minute)
    assert 0 < found.timestamp() - start <= 7 * 86400 + 3600  # next, within a week (DST)
    plain = datetime.fromtimestamp(resolve_when(f"{hour:02d}:{minute:02d}", start))
    assert (plain.hour, plain.minute) == (hour, minute)
    assert 0 < plain.timestamp() - start <= 86400 + 3600


def test_times_the_issue_names() -> None:
    wednesday = datetime.fromtimestamp(START)
    friday = datetime.fromtimestamp(resolve_when("FRI 18:00", START))
    assert friday == wednesday.replace(hour=18) + timedelta(days=2)
    assert parse_duration("8h") == 8 * 3600
    assert datetime.fromtimestamp(resolve_when("2026-11-27T18:00", START)) == friday
    with pytest.raises(UsageError, match="not after the plan's start"):
        resolve_when("2026-11-24T18:00", START)
    with pytest.raises(UsageError, match="31 days"):
        resolve_when("2027-11-24T18:00", START)


@pytest.mark.parametrize(
    ("given", "shown"),
    [
        ("0", "'0'"),
        (601, "601"),
        ("x" * 100_000, "'" + "x" * 40 + "'..."),
        (2**5000, "(a number of more than 38 digits)"),
        (True, "(true or false)"),
        ([[5]] * 100_000, "(a list)"),
        ({"a": 1}, "(an object)"),
    ],
)
def test_a_poll_period_is_refused_in_few_words_whatever_is_sent(given: Any, shown: str) -> None:
    nested: Any = 1
    for _ in range(5000):  # deeper than any repr goes
        nested = [nested]
    for value in (given, nested) if shown == "(a list)" else (given,):
        with pytest.raises(UsageError) as refused:
            parse_poll(value)
        assert str(refused.value) == f"poll {shown}: seconds, more than 0 and at most 600"
    assert parse_poll("0.5") == 0.5 and parse_poll(600) == 600.0


@FAST
@given(
    st.from_regex(r"[a-z][a-z0-9\-]{0,20}", fullmatch=True),
    st.integers(1, 10_000),
    st.one_of(st.none(), st.integers(-1_000_000, 1_000_000)),
)
def test_add_reads_back(part: str, qty: int, priority: int | None) -> None:
    text = f"{part}:{qty}" + ("" if priority is None else f"@{priority}")
    assert parse_add(text) == AddSpec(part, qty, priority or 0)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("wax-robot-base", "PART:QTY"),
        ("wax-robot-base:0", "1 to 10000"),
        ("wax-robot-base:40@9999999", "priority"),
        ("wax robot:4", "PART:QTY"),
    ],
)
def test_add_refusals_say_how_to_write_it(text: str, message: str) -> None:
    with pytest.raises(UsageError, match=message):
        parse_add(text)


def test_fault_windows_the_issue_names() -> None:
    window = parse_fault("cnc2:down@10:00-11:00", START)
    assert window == FaultWindow("cnc2", "down", START + 4 * 3600, START + 5 * 3600)
    overnight = parse_fault("plc:stuck-door=2@23:00-01:00", START)
    assert overnight.arg == "2" and overnight.end == overnight.start + 2 * 3600
    open_ended = parse_fault("cnc1:noise=3e-4,7@FRI 09:30", START)
    assert open_ended.end is None and open_ended.arg == "3e-4,7"
    assert datetime.fromtimestamp(open_ended.start).strftime("%a %H:%M") == "Fri 09:30"


@pytest.fixture(scope="module")
def config() -> Any:
    return load_cell(EXAMPLE_CELL)


@pytest.mark.parametrize(
    ("fault", "message"),
    [
        ("cnc9:down@10:00-11:00", r"no such machine \(known: robot, cnc1, cnc2, plc\)"),
        ("cnc2:melt@10:00-11:00", r"'melt' on cnc2: unknown \(known: down, never-ready"),
        ("plc:down@10:00-11:00", r"'down' on plc: unknown"),
        ("robot:servo-error@15:00", "opens after the plan ends"),
    ],
)
def test_an_unknown_machine_or_fault_is_refused_before_anything_runs(
    fault: str, message: str
) -> None:
    with pytest.raises(UsageError, match=message):
        plan_inputs(EXAMPLE_CELL, start=START, adds=["wax-robot-base:1"], faults=[fault])


def test_unknown_part_types_and_policies_are_refused(config: Any) -> None:
    with pytest.raises(UsageError, match=r"makes no 'gear' \(known: wax-robot-base"):
        check_inputs(config, [PlanOrder("A", "gear", 1)], [])
    with pytest.raises(UsageError, match="policy 'fastest': unknown"):
        check_inputs(config, [], [], policies_of("fastest"))
    assert len(policies_of("all")) >= 2


def test_a_policy_typo_in_a_factory_plan_is_said_once_not_as_one_cells(tmp_path: Path) -> None:
    """``--policy`` goes to every cell of a factory: a name no policy has is the planner's
    typo, said as ``cellctl plan`` says it, not blamed on the first cell checked."""
    import shutil

    from click.testing import CliRunner

    from cellctl.ui.cli import main

    plant = tmp_path / "plant"
    plant.mkdir()
    (plant / "factory.toml").write_text(
        '[broker]\nurl = "mqtt://127.0.0.1:1883"\ncredentials = "factory.credentials"\n\n'
        '[cells.cell1]\nprefix = "cellctl/cell1"\n\n[cells.cell2]\nprefix = "cellctl/cell2"\n',
        encoding="utf-8",
    )
    for name in ("cell1", "cell2"):
        shutil.copytree(EXAMPLE_CELL, plant / name)
    for policy in ("defualt", "default,defualt"):
        args = ["factory", "--dir", str(plant), "plan", "--shift", "2m", "--policy", policy]
        result = CliRunner().invoke(main, args)
        assert result.exit_code == 2, result.output
        said = " ".join(result.output.split())
        assert said.startswith("error: policy 'defualt': unknown (known: default,"), said
        assert "cell1" not in said


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("default,default", "default is named twice: name each policy once"),
        ("shortest-first, one-at-a-time,shortest-first", "shortest-first is named twice"),
        ("downstream-first,downstream-first", "downstream-first is named twice"),
        ("default,downstream-first", "default is downstream-first: name it once"),
        ("downstream-first,default", "default is downstream-first: name it once"),
    ],
)
def test_a_policy_named_twice_is_refused(
    config: Any, tmp_path: Path, text: str, message: str
) -> None:
    """Each policy is played once: named twice (or as default and downstream-first, the
    same policy), the command line refuses it in its words, and so does a saved
    inputs.json's list, before anything is played."""
    with pytest.raises(UsageError, match=f"--policy '{text}': {message}"):
        policies_of(text)
    named = tuple(p.strip() for p in text.split(","))
    with pytest.raises(UsageError, match=f"policies {', '.join(named)}: {message}"):
        check_inputs(config, [], [], named)
    inputs, _ = plan_inputs(EXAMPLE_CELL, start=START, adds=["wax-robot-base:1"])
    with pytest.raises(UsageError, match=message):
        play(inputs, named, tmp_path / "play")
    assert not (tmp_path / "play").exists()
    # Each once, in the order named.
    assert policies_of("one-at-a-time,default") == ("one-at-a-time", "default")


def test_plan_inputs_take_what_the_planner_typed() -> None:
    inputs, policies = plan_inputs(
        EXAMPLE_CELL,
        start=START,
        until="FRI 18:00",
        orders=[PlanOrder("plan-add1", "wax-robot-base", 3)],
        adds=["wax-robot-base:40@5", "wax-toy-mill-table:2"],
        faults=["cnc2:down@10:00-11:00"],
        policy="all",
        seed=7,
    )
    assert [o.order_id for o in inputs.orders] == ["plan-add1", "plan-add2", "plan-add3"]
    assert inputs.orders[1] == PlanOrder("plan-add2", "wax-robot-base", 40, 5)
    assert inputs.until == resolve_when("FRI 18:00", START)
    assert inputs.seed == 7 and policies == policies_of("all")
    with pytest.raises(UsageError, match="not both"):
        plan_inputs(EXAMPLE_CELL, start=START, shift="8h", until="18:00")


ORDERS = """# the week's orders
id,part_type,qty,priority,due
A,wax-robot-base,20,5,FRI 18:00
B,wax-toy-mill-table,10,,2026-11-27T12:00

C,wax-robot-base,4
"""


def test_an_orders_file_reads_and_writes_back() -> None:
    orders = parse_orders(ORDERS, START)
    assert orders == (
        PlanOrder("A", "wax-robot-base", 20, 5, resolve_when("FRI 18:00", START)),
        PlanOrder("B", "wax-toy-mill-table", 10, 0, resolve_when("2026-11-27T12:00", START)),
        PlanOrder("C", "wax-robot-base", 4, 0, None),
    )
    assert parse_orders(orders_csv(orders), START) == orders


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "no orders"),
        ("id,part_type\nA,x\n", "header must name"),
        ("id,part_type,qty,colour\nA,x,1,red\n", "header must name"),
        ("id,part_type,qty\nA,x,1\nA,x,2\n", "line 3: order A is in the file twice"),
        ("id,part_type,qty\nA,x,many\n", "line 2: qty must be a whole number"),
        ("id,part_type,qty,due\nA,x,1,someday\n", "line 2: due: time 'someday'"),
        ("id,part_type,qty\nA,x,1,2\n", "line 2: 4 fields, the header names 3"),
        ("id,part_type,qty,due\nA,x\n", r"line 2: 2 fields, the header names 4 \(no qty\)"),
        ("qty,id,part_type\n3,A\n", r"line 2: 2 fields, the header names 3 \(no part_type\)"),
        ("id,part_type,qty\nA B,x,1\n", "one word"),
        ("id,part_type,qty\nA,x,1\nB,gear,1\n", r"line 3: the cell makes no 'gear' \(it makes: x"),
    ],
)
def test_orders_file_refusals_name_the_line(text: str, message: str) -> None:
    with pytest.raises(UsageError, match=message):
        parse_orders(text, START, "week.csv", ("x", "y"))


def test_an_orders_file_saved_in_a_code_page_is_refused_at_its_line(tmp_path: Path) -> None:
    """A spreadsheet's plain "CSV" (Windows-1252: an accent in a name): the file and the
    line, as any refusal of a line, and how to save it; not "not a text file"."""
    week = tmp_path / "week.csv"
    week.write_bytes("id,part_type,qty\nA,x,1\nMüller,x,2\n".encode("cp1252"))
    with pytest.raises(UsageError) as refused:
        read_orders_file(week, START, ("x",))
    assert str(refused.value) == (
        f"{week}, line 3: not UTF-8 text (byte 25): save the file as UTF-8 (a spreadsheet's "
        '"CSV UTF-8")'
    )
    week.write_bytes("id,part_type,qty\nA,x,1\nMüller,x,2\n".encode())
    assert [o.order_id for o in read_orders_file(week, START, ("x",))] == ["A", "Müller"]


@FAST
@given(st.one_of(TYPED, st.lists(st.lists(TYPED, max_size=6), max_size=5)))
@example("id,part_type,qty\n\x00")
@example('id,part_type,qty\n"A')
def test_any_orders_file_is_read_or_refused(content: Any) -> None:
    text = content if isinstance(content, str) else "\n".join(",".join(r) for r in content)
    for candidate in (text, "id,part_type,qty,priority,due\n" + text):
        try:
            for order in parse_orders(candidate, START):
                assert order.qty >= 1 and order.order_id
        except UsageError as e:
            assert str(e)


JSONISH = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=10)),
    lambda inner: st.one_of(
        st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=10), inner, max_size=4)
    ),
    max_leaves=20,
)


#: An order of a running cell: one of its parts cut at cnc1, waiting there.
UNDER_WAY = PlanOrder("A", "wax-robot-base", 2, 1, START + 3600, (PartAt("cnc1", 1),))


def _saved() -> dict[str, Any]:
    inputs = PlanInputs(
        cell_dir=Path("cell"),
        orders=(UNDER_WAY,),
        start=START,
        until=START + 8 * 3600,
        faults=(FaultWindow("cnc2", "down", START + 60, START + 120),),
        seed=3,
        poll_period=2.0,
    )
    return inputs_dict(inputs, ("default",))


@FAST
@given(st.sampled_from(sorted(_saved())), JSONISH)
def test_a_saved_inputs_file_with_anything_in_a_field_is_read_or_refused(
    key: str, value: Any
) -> None:
    data = _saved() | {key: value}
    try:
        parse_inputs(json.loads(json.dumps(data)), Path("/plans"))
    except UsageError as e:
        assert str(e).startswith("plan inputs:")


def test_saved_inputs_read_back() -> None:
    inputs, policies = parse_inputs(json.loads(json.dumps(_saved())), Path("/plans"))
    assert inputs.cell_dir == Path("/plans/cell") and policies == ("default",)
    assert inputs.orders == (UNDER_WAY,)
    assert inputs.faults == (FaultWindow("cnc2", "down", START + 60, START + 120),)
    assert (inputs.start, inputs.until, inputs.seed) == (START, START + 8 * 3600, 3)
    assert inputs.poll_period == 2.0
    # Saved before plans had a poll period of their own: played at the cell's, as then.
    older = {k: v for k, v in _saved().items() if k != "poll_period"}
    assert parse_inputs(older, Path("/plans"))[0].poll_period == 0.0
    # Saved before plans took parts up where they are: none under way.
    orders = [{k: v for k, v in o.items() if k != "under_way"} for o in _saved()["orders"]]
    [order] = parse_inputs(_saved() | {"orders": orders}, Path("/plans"))[0].orders
    assert order == replace(UNDER_WAY, under_way=())
    # No orders: nothing to play, refused as the command line refuses it.
    with pytest.raises(UsageError, match="orders: nothing to plan"):
        parse_inputs(_saved() | {"orders": []}, Path("/plans"))


def test_a_fault_window_that_ends_as_it_opens_is_refused() -> None:
    start = datetime(2026, 11, 25, 6, 0).timestamp()
    for text in ("cnc1:down@23:00-23:00", "cnc1:stall@FRI 10:00-fri  10:00"):
        with pytest.raises(UsageError, match="the window ends as it opens: write when it ends"):
            parse_fault(text, start)
    window = parse_fault("cnc1:down@23:00-01:00", start)
    assert window.end is not None and window.end - window.start == 2 * 3600
