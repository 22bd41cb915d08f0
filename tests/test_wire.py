"""The MQTT payloads' models (cellctl.mailbox.wire): whatever bytes arrive on a topic, the
parser gives back a model or a WireError, never another exception, and never recurses or
reads more than its limits. Valid messages go through both ends unchanged."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from cellctl.mailbox import REPORT_KINDS, open_mailbox
from cellctl.mailbox.wire import (
    MAX_DEPTH,
    MAX_PAYLOAD,
    AskMessage,
    OrderMessage,
    ReportKind,
    ReportMessage,
    StateMessage,
    WireError,
    nesting,
    parse_report,
    parse_state,
    parse_status,
    parse_to_cell,
    report_message,
)

EPOCH = "0123456789abcdef"
PARSERS = {
    "orders": parse_to_cell,
    "reports": parse_report,
    "state": parse_state,
    "status": parse_status,
}

REPORT = {
    "v": 1,
    "cell": "cell1",
    "epoch": EPOCH,
    "seq": 3,
    "kind": "order-done",
    "order_id": "F1",
    "part_id": None,
    "text": "order F1 done",
    "time": 1.7e9,
    "data": {"alarm": 4},
}
STATE = {
    "v": 1,
    "cell": "cell1",
    "time": 1.7e9,
    "paused": False,
    "part_types": {"wax-robot-base": {"bound_s": 12.5, "machines": ["robot"]}},
    "machines": {"robot": {"kind": "ibm7545", "state": "idle", "in_service": True}},
    "orders_open": 1,
    "parts_open": 2,
    "finish_estimate_s": 40.0,
}
ORDER = {"v": 1, "id": "F1", "part_type": "wax-robot-base", "qty": 2, "priority": 0}
#: An order with a due time (unix seconds): a field the payload carries only when it has one.
DUE = {**ORDER, "id": "F2", "due": 1.8e9}
ASK = {"v": 1, "ask": "reports", "epoch": EPOCH, "after": 7}
GOOD = {"orders": [ORDER, DUE, ASK], "reports": [REPORT], "state": [STATE]}


def deep(levels: int, inner: str = "1") -> bytes:
    """The issue's payload: ``{"v":1,"seq":`` nested ``levels`` deep."""
    return ('{"v":1,"seq":' * levels + inner + "}" * levels).encode()


def refused_only(topic: str, payload: bytes) -> object:
    """Parse ``payload`` as ``topic`` carries it: a model, or None when refused."""
    try:
        return PARSERS[topic](payload)
    except WireError as e:
        assert e.reason and len(e.reason) <= 200 and len(e.raw) <= 64
        return None


@pytest.mark.parametrize("topic", list(PARSERS))
def test_the_issues_deep_report_and_a_deep_one_under_the_size_limit_are_refused(
    topic: str,
) -> None:
    for payload, why in (
        (deep(30_000), "more than"),  # finding 1 as filed: 420 kB
        (deep(3_000), "nested deeper"),  # 42 kB: under the size limit, refused for its depth
        (b"[" * 40_000 + b"]" * 40_000, "more than"),
        (b'{"data":' + b"[" * 30_000 + b"]" * 30_000 + b"}", "nested deeper"),
    ):
        if topic == "status":
            why = "neither online nor offline"
        with pytest.raises(WireError, match=why):
            PARSERS[topic](payload)


def test_valid_messages_go_through_both_ends_unchanged() -> None:
    for topic, messages in GOOD.items():
        for message in messages:
            model = PARSERS[topic](json.dumps(message).encode())
            assert isinstance(model, OrderMessage | AskMessage | ReportMessage | StateMessage)
            again = PARSERS[topic](model.model_dump_json().encode())
            assert again == model
            assert {k: v for k, v in model.model_dump(mode="json").items() if k in message} == (
                message
            )
    assert parse_status(b"online") == "online" and parse_status(b"offline") == "offline"
    # An older cell's state says no machines a part type needs: read as none said.
    older = {**STATE, "part_types": {"wax-robot-base": {"bound_s": 12.5}}}
    parsed = PARSERS["state"](json.dumps(older).encode())
    assert isinstance(parsed, StateMessage) and parsed.part_types["wax-robot-base"].machines == ()


def test_a_mailbox_report_becomes_its_message(tmp_path: Any) -> None:
    with open_mailbox(tmp_path) as mailbox:
        r = mailbox.post_report("alarm-raised", "x" * 5000, data={"alarm": 3})
        message = report_message("cell1", mailbox.epoch, r)
        assert message.kind is ReportKind.ALARM_RAISED and len(message.text) == 2000
        assert parse_report(message.model_dump_json().encode()) == message
        assert message.epoch == mailbox.epoch and message.seq == r.seq == 1
        # Beyond the wire's limits (a local order's id, many data keys): it goes out without.
        long = mailbox.post_report(
            "order-accepted", "ok", order_id="L" * 200, data={f"k{i}": i for i in range(40)}
        )
        cut = report_message("cell1", mailbox.epoch, long)
        assert (cut.seq, cut.order_id, cut.data, cut.text) == (2, None, {}, "ok")


def test_the_documented_report_kinds_are_the_enums() -> None:
    docs = (Path(__file__).resolve().parent.parent / "docs" / "factory.md").read_text()
    (row,) = [line for line in docs.splitlines() if line.startswith("| `kind` |")]
    assert re.findall(r"`([a-z-]+)`", row.split("|")[3]) == list(REPORT_KINDS)


def test_the_depth_scan_skips_strings() -> None:
    assert nesting(b'{"a": "[[[[{{{{", "b": [[1]]}') == 3
    assert nesting(b'["\\"[[[[[[[[[[[["]') == 1
    assert nesting(b"[" * 10_000) == MAX_DEPTH + 1


_SCALAR = (
    st.none()
    | st.booleans()
    | st.integers()
    | st.integers(min_value=2**63 - 2, max_value=2**80)
    | st.integers(min_value=-(2**80), max_value=-(2**63))
    | st.floats()
    | st.text(max_size=8)
)
_JSON = st.recursive(
    _SCALAR,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner),
    max_leaves=12,
)


def _mutants(base: dict[str, Any]) -> st.SearchStrategy[dict[str, Any]]:
    """``base`` with some fields replaced by any JSON, removed, or added."""
    return st.builds(
        lambda changes, dropped, extra: {
            **{k: v for k, v in base.items() if k not in dropped},
            **changes,
            **extra,
        },
        st.dictionaries(st.sampled_from(sorted(base)), _JSON, max_size=3),
        st.sets(st.sampled_from(sorted(base)), max_size=2),
        st.dictionaries(st.text(max_size=6), _JSON, max_size=1),
    )


def _raw(message: Any) -> bytes:
    return json.dumps(message).encode()


_PAYLOADS = st.one_of(
    st.binary(max_size=200),
    _JSON.map(_raw),
    st.sampled_from([m for ms in GOOD.values() for m in ms]).flatmap(_mutants).map(_raw),
    st.integers(1, 40_000).map(lambda n: b"[" * n + b"]" * n),
    st.integers(1, 40_000).map(lambda n: b'{"a":' * n + b"1" + b"}" * n),
    st.integers(1, 100_000).map(lambda n: b'{"v":1,"data":[' + b"1," * n + b"1]}"),
    st.integers(0, 4000).map(lambda n: _raw({**REPORT, "text": "x" * n})),
    st.integers(0, 2000).map(
        lambda n: _raw({**STATE, "part_types": {f"p{i}": {"bound_s": 1.0} for i in range(n)}})
    ),
    st.integers(0, 100).map(lambda n: _raw({**REPORT, "data": {f"k{i}": i for i in range(n)}})),
    st.sampled_from([b"NaN", b"Infinity", b'{"v":1,"qty":1e999}', b"1" * 5000]),
)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(sorted(PARSERS)), _PAYLOADS)
@example("reports", _raw({**REPORT, "seq": 2**63}))
@example("reports", _raw({**REPORT, "seq": 99998}))
@example("orders", _raw({**ORDER, "qty": "2"}))
@example("orders", _raw({**ORDER, "priority": 2**70}))
@example("orders", _raw({**DUE, "due": -1}))
@example("orders", _raw({**DUE, "due": "FRI 18:00"}))
@example("orders", _raw({**ASK, "after": -1}))
@example("state", _raw({**STATE, "finish_estimate_s": 1e308}))
@example("state", _raw({**STATE, "machines": ["robot"]}))
def test_any_payload_is_a_model_or_a_wire_error(topic: str, payload: bytes) -> None:
    model = refused_only(topic, payload)
    if len(payload) > MAX_PAYLOAD or nesting(payload) > MAX_DEPTH:
        assert model is None
    if model is not None and topic != "status":
        # What is taken fits in 64 bits and in the tables' limits; it goes out unchanged.
        assert PARSERS[topic](model.model_dump_json().encode()) == model  # type: ignore[attr-defined]
    if isinstance(model, ReportMessage):
        assert 1 <= model.seq < 2**63 and model.kind in REPORT_KINDS
    if isinstance(model, OrderMessage):
        assert 1 <= model.qty <= 10_000 and -(2**63) <= model.priority < 2**63
        assert model.due is None or 0 <= model.due <= 1e11  # what the cell's mailbox takes
