"""The cell's status model: its difference (applied to the old status it gives the new one),
its JSON (what a client holds and is pushed), its schema, and docs/api.md's tables generated
from it. The surfaces that read it are tested with a real cell in test_api, test_console,
test_dashboard and test_opcua; here, that none of them takes words apart."""

from __future__ import annotations

import re
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.kinds import Condition
from cellctl.service.status import (
    STATUS_EVENTS,
    AlarmInfo,
    CellInfo,
    CellMode,
    CellStatus,
    ErrorInfo,
    EventInfo,
    MachineStatus,
    OrderInfo,
    PartInfo,
    ProgressInfo,
    StatusUpdate,
    StepInfo,
    StepKind,
    apply_update,
    apply_update_json,
    difference,
    status_schema,
    status_tables,
)

ROOT = Path(__file__).resolve().parent.parent
NAMES = ["robot", "cnc1", "cnc2", "plc", "saw"]
WORDS = st.sampled_from(["", "Executing", "machining", "error: no answer", "ok", "é ≠ ascii"])
TIMES = st.floats(min_value=0, max_value=2e9, allow_nan=False)

steps = st.none() | st.builds(
    StepInfo,
    what=st.sampled_from(StepKind),
    program=st.none() | st.sampled_from(["conveyor_cnc1", "robot_base_rough"]),
    part_id=st.none() | st.sampled_from(["A-1", "A-2"]),
    started=st.none() | TIMES,
)
progresses = st.none() | st.builds(
    ProgressInfo,
    phase=st.sampled_from(["downloading", "sending", "machining"]),
    done=st.integers(0, 5000),
    total=st.integers(0, 5000),
    unit=st.sampled_from(["bytes", "records"]),
    fraction=st.floats(0, 1),
    block=st.none() | st.integers(1, 9),
    blocks=st.none() | st.integers(1, 9),
    rate_per_s=st.none() | st.floats(0, 1e4),
    time_left_s=st.none() | st.floats(0, 1e4),
)


def machine(name: str) -> st.SearchStrategy[MachineStatus]:
    return st.builds(
        MachineStatus,
        name=st.just(name),
        kind=st.sampled_from(["ibm7545", "dyna2400", "plc"]),
        family=st.sampled_from(["robot", "mill", "plc"]),
        condition=st.sampled_from(Condition),
        state=WORDS,
        step=steps,
        part=st.none() | st.sampled_from(["A-1", "B-1"]),
        progress=progresses,
        error=st.none() | st.builds(ErrorInfo, code=st.none() | st.integers(0, 255), text=WORDS),
        failures=st.integers(0, 3),
        busy_s=st.floats(0, 1e5),
        utilization=st.floats(0, 1),
        in_service=st.booleans(),
        out_reason=WORDS,
        manual=st.booleans(),
    )


# Each machine there or not; the strategies built once (a flatmap built them anew every draw,
# and drawing took forty times what the test itself does).
machine_sets = st.fixed_dictionaries({}, optional={n: machine(n) for n in NAMES})
cells = st.builds(
    CellInfo,
    name=st.just("lab"),
    directory=st.just("/cell"),
    access=st.sampled_from(["attached", "standalone"]),
    mode=st.sampled_from(CellMode),
    paused=st.booleans(),
    started_at=st.just(1.0),
    pid=st.just(42),
    time=TIMES,
)
orders = st.lists(
    st.builds(
        OrderInfo,
        id=st.sampled_from(["A", "B"]),
        part_type=st.just("base"),
        qty=st.integers(1, 3),
        priority=st.integers(-1, 1),
        state=st.sampled_from(["posted", "done"]),
        created=st.just(1.0),
        updated=TIMES,
        parts=st.dictionaries(st.sampled_from(["waiting", "done"]), st.integers(0, 3)),
    ),
    max_size=3,
)
parts = st.lists(
    st.builds(
        PartInfo,
        id=st.sampled_from(["A-1", "A-2"]),
        order_id=st.just("A"),
        part_type=st.just("base"),
        seq_in_order=st.integers(1, 2),
        route_index=st.integers(0, 2),
        location=st.sampled_from(["conveyor", "cnc1", "out"]),
        status=st.sampled_from(["waiting", "active", "held"]),
        updated=TIMES,
    ),
    max_size=3,
)
alarms = st.lists(
    st.builds(
        AlarmInfo,
        id=st.integers(1, 5),
        raised=TIMES,
        machine=st.sampled_from(NAMES),
        code=st.just("link"),
        text=WORDS,
        state=st.just("active"),
    ),
    max_size=3,
)


@st.composite
def status_pairs(draw: st.DrawFn) -> tuple[CellStatus, CellStatus]:
    """Two statuses of one cell, the second later: the events are two windows on one log."""
    log = [EventInfo(time=float(i), text=f"event {i}") for i in range(draw(st.integers(0, 80)))]
    seen = draw(st.integers(0, len(log)))

    def status(upto: int) -> CellStatus:
        return CellStatus(
            cell=draw(cells),
            machines=draw(machine_sets),
            orders=draw(orders),
            parts=draw(parts),
            alarms=draw(alarms),
            events=log[:upto][-STATUS_EVENTS:],
        )

    old = status(seen)
    new = status(len(log))
    if draw(st.booleans()):  # often only a little changed
        new = old.model_copy(
            update={"machines": {**old.machines, **new.machines}, "events": new.events}
        )
    return old, new


@settings(max_examples=300, deadline=None)
@given(status_pairs())
def test_a_difference_applied_to_the_old_status_gives_the_new(
    pair: tuple[CellStatus, CellStatus],
) -> None:
    old, new = pair
    update = difference(old, new)
    assert apply_update(old, update).stable() == new.stable()
    # What is sent is sent whole and as it is now; what is not sent did not change.
    for name, m in (update.machines or {}).items():
        assert m == new.machines[name]
    for name in set(old.machines) & set(new.machines) - set(update.machines or {}):
        assert old.machines[name].stable() == new.machines[name].stable()
    # The JSON a client holds and is pushed gives the same status.
    pushed = StatusUpdate.model_validate(update.as_json())
    assert pushed == update
    held = apply_update_json(old.model_dump(mode="json"), update.as_json())
    assert CellStatus.model_validate(held).stable() == new.stable()
    # Only new events travel.
    assert not set(update.events or []) & set(old.events)


@settings(max_examples=100, deadline=None)
@given(status_pairs())
def test_nothing_changed_sends_nothing(pair: tuple[CellStatus, CellStatus]) -> None:
    old, _ = pair
    later = old.model_copy(update={"cell": old.cell.model_copy(update={"time": 3e9})})
    assert difference(old, old).empty()
    assert difference(old, later).empty()  # the clock alone moved
    # ... and so does a machine's busy time while its step runs (it counts as it goes).
    busier = later.model_copy(
        update={
            "machines": {
                n: m.model_copy(update={"busy_s": m.busy_s + 1.0}) for n, m in old.machines.items()
            }
        }
    )
    assert difference(old, busier).empty()
    assert set(difference(None, old).as_json()) == {
        "time",
        "cell",
        "orders",
        "parts",
        "alarms",
        *(["machines"] if old.machines else []),
        *(["events"] if old.events else []),
    }


def test_a_machine_taken_out_is_one_machine_in_the_update() -> None:
    cell = CellInfo(
        name="lab",
        directory="/c",
        access="attached",
        mode=CellMode.RUNNING,
        paused=False,
        started_at=0.0,
        pid=1,
        time=5.0,
    )
    base = {
        "kind": "dyna2400",
        "family": "mill",
        "state": "Initialized",
        "failures": 0,
        "busy_s": 1.0,
        "utilization": 0.2,
        "in_service": True,
        "out_reason": "",
        "manual": False,
    }
    old = CellStatus(
        cell=cell,
        machines={
            n: MachineStatus(name=n, condition=Condition.IDLE, **base) for n in ("cnc1", "cnc2")
        },
        orders=[],
        parts=[],
        alarms=[],
        events=[],
    )
    out = old.machines["cnc2"].model_copy(
        update={"condition": Condition.OUT_OF_SERVICE, "in_service": False, "utilization": 0.1}
    )
    new = old.model_copy(update={"machines": {**old.machines, "cnc2": out}})
    assert difference(old, new).as_json() == {
        "time": 5.0,
        "machines": {"cnc2": out.model_dump(mode="json")},
    }


def test_the_schema_is_the_models_and_the_docs_tables_are_generated_from_it() -> None:
    schema = status_schema()
    assert set(schema["status"]["required"]) == {
        "cell",
        "machines",
        "orders",
        "parts",
        "alarms",
        "events",
    }
    conditions = schema["status"]["$defs"]["Condition"]["enum"]
    assert conditions == [c.value for c in Condition]
    text = (ROOT / "docs" / "api.md").read_text()
    match = re.search(
        r"<!-- status tables: begin -->\n(.*?)<!-- status tables: end -->", text, re.S
    )
    assert match is not None, "docs/api.md has no generated status tables"
    assert match.group(1) == status_tables()


# -- no surface takes words apart ---------------------------------------------------------------

SRC = ROOT / "src" / "cellctl"


def test_no_surface_parses_words() -> None:
    dashboard = {p.name: p.read_text() for p in (SRC / "ui" / "dashboard" / "static").glob("*.js")}
    for name, text in dashboard.items():
        assert 'startsWith("error")' not in text, name
        assert ".exec(machine.step" not in text and "step.split(" not in text, name
        assert "String(machine.state)" not in text, name
    opcua = "".join(
        (SRC / "factory" / "opcua" / f).read_text() for f in ("space.py", "server.py", "figures.py")
    )
    assert "FAULT_WORDS" not in opcua
    assert not re.search(r'in str\(view\.get\("state"', opcua)
    assert not re.search(r"word in state", opcua)
    board = (SRC / "ui" / "console" / "widgets.py").read_text()
    assert '.get("state"' not in board and 'startswith("error' not in board
