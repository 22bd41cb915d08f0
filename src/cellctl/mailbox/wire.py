"""The MQTT payloads between a cell and the factory, declared once (docs/factory.md).

Both ends build and read them here: the cell's :class:`~cellctl.mailbox.mqtt.MqttBridge`
and the factory's :class:`~cellctl.factory.controller.FactoryController`::

    payload = report_message(cell="cell1", epoch=mailbox.epoch, report=r).model_dump_json()
    report = parse_report(payload)          # a ReportMessage, or WireError saying why not

Every payload is JSON with ``"v": 1``; one that fails its model raises :class:`WireError`
(a :class:`~cellctl.errors.ProtocolError` with the first bytes attached) and nothing else.
Before any parser sees a payload it must be at most :data:`MAX_PAYLOAD` bytes and nest at
most :data:`MAX_DEPTH` levels, so no payload can make a parser recurse or allocate without
bound. Numbers are integers within 64 bits or finite floats; strings and tables have lengths.
"""

from __future__ import annotations

import re
from typing import Annotated, Any, Final, Literal, TypeVar

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    JsonValue,
    SerializerFunctionWrapHandler,
    Tag,
    TypeAdapter,
    ValidationError,
    model_serializer,
    model_validator,
)

from cellctl.cell.config import MAX_MACHINES as CELL_MAX_MACHINES
from cellctl.cell.config import MAX_NAME as CELL_MAX_NAME
from cellctl.cell.config import MAX_PART_TYPES as CELL_MAX_PART_TYPES
from cellctl.cell.orders import ReportKind
from cellctl.errors import ProtocolError, printable
from cellctl.mailbox.base import MAX_QTY, Report

__all__ = [
    "MAX_DEPTH",
    "MAX_PAYLOAD",
    "MAX_REASON",
    "VERSION",
    "AskMessage",
    "CancelMessage",
    "MachineState",
    "OrderMessage",
    "PartTypeState",
    "ReportKind",
    "ReportMessage",
    "StateMessage",
    "ToCell",
    "WireError",
    "nesting",
    "parse_report",
    "parse_state",
    "parse_status",
    "parse_to_cell",
    "report_message",
]

#: The payloads' format version: a change old readers cannot take gets a new number.
VERSION: Final = 1
#: Largest payload read, in bytes (a state of 32 machines and 100 part types is ~8 KiB).
MAX_PAYLOAD: Final = 64 * 1024
#: Deepest nesting of objects and arrays read (the state's is 3; a report's data adds 4).
MAX_DEPTH: Final = 8
#: Longest name (cell, part type, machine), order or part id (the cell's own limits, which
#: ``cellctl cell check`` enforces); longest report text.
MAX_NAME: Final = CELL_MAX_NAME
MAX_TEXT: Final = 2000
#: Longest reason given with a cancel (kept in the factory's events and the cell's note).
MAX_REASON: Final = 500
#: Most entries of a state's tables (as a cell may hold) and of a report's data.
MAX_PART_TYPES: Final = CELL_MAX_PART_TYPES
MAX_MACHINES: Final = CELL_MAX_MACHINES
MAX_DATA_KEYS: Final = 32
INT64_MAX: Final = 2**63 - 1
#: Latest Unix time taken (the year 5138): beyond it a time is not a clock's.
MAX_TIME: Final = 1e11

# Names and reasons end up in logs and on operators' terminals: printable, as order ids.
Name = Annotated[str, Field(min_length=1, max_length=MAX_NAME), AfterValidator(printable)]
Text = Annotated[str, Field(max_length=MAX_TEXT)]
Count = Annotated[int, Field(ge=0, le=INT64_MAX)]
Seconds = Annotated[float, Field(ge=0, le=MAX_TIME)]
#: A mailbox's epoch: lowercase hex, made with the mailbox (:attr:`Mailbox.epoch`).
Epoch = Annotated[str, Field(pattern=r"^[0-9a-f]{8,32}$")]
Seq = Annotated[int, Field(ge=1, le=INT64_MAX)]


class WireError(ProtocolError):
    """A payload that is not what its topic carries; ``reason`` says why in a few words."""

    #: The longest reason kept: one log line, whatever the payload held.
    MAX_REASON = 200

    def __init__(self, reason: str, raw: bytes = b"") -> None:
        if len(reason) > self.MAX_REASON:
            reason = reason[: self.MAX_REASON - 1] + "…"
        self.reason = reason
        super().__init__(reason, raw[:64])


class _Strict(BaseModel):
    # strict: "2" is not 2 and true is not 1; no NaN or infinity; no unknown field.
    model_config = ConfigDict(
        strict=True, extra="forbid", frozen=True, allow_inf_nan=False, defer_build=True
    )


class _Message(_Strict):
    v: Literal[1] = VERSION


class OrderMessage(_Message):
    """``PREFIX/orders``, factory → cell: make ``qty`` parts of ``part_type``, by ``due``
    (unix seconds) if given.

    ``due`` is left out of the payload when there is none: a cell of an older cellctl takes
    no field it does not know (it drops such an order unanswered), so an order without a due
    time is the payload it always was; one with a due time is for a cell that takes it."""

    id: Name
    part_type: Name
    qty: Annotated[int, Field(ge=1, le=MAX_QTY)]
    priority: Annotated[int, Field(ge=-(2**63), le=INT64_MAX)] = 0
    expires: Seconds | None = None
    due: Seconds | None = None

    @model_serializer(mode="wrap")
    def _without_no_due(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        data: dict[str, Any] = handler(self)
        if self.due is None:
            data.pop("due", None)
        return data


class AskMessage(_Message):
    """``PREFIX/orders``, factory → cell: publish again every report after ``after`` of the
    mailbox ``epoch`` (the factory missed some, or heard a new epoch from the middle)."""

    ask: Literal["reports"]
    epoch: Epoch
    after: Annotated[int, Field(ge=0, le=INT64_MAX)]


class CancelMessage(_Message):
    """``PREFIX/orders``, factory → cell: cancel order ``id`` as the cell's own operator
    would (``orders.cancel``), on behalf of ``by`` at the factory, for ``reason``.

    ``asked`` (the factory's time of the request) names the request: the cell answers each
    one once, with its ``order-cancelled`` report or a ``cancel-refused`` whose ``data``
    carries ``asked`` back."""

    cancel: Literal["order"]
    id: Name
    by: Name
    reason: Annotated[str, Field(max_length=MAX_REASON), AfterValidator(printable)] = ""
    asked: Seconds


class ReportMessage(_Message):
    """``PREFIX/reports``, cell → factory: report ``seq`` of the cell's mailbox ``epoch``.

    ``withdrawn`` marks an acceptance the cell took back before it could tell it (the order
    expired): it keeps the numbering whole and changes nothing at the factory."""

    cell: Name
    epoch: Epoch
    seq: Seq
    kind: ReportKind
    order_id: Name | None = None
    part_id: Name | None = None
    text: Text = ""
    time: Seconds
    data: Annotated[dict[str, JsonValue], Field(max_length=MAX_DATA_KEYS)] = {}
    withdrawn: bool = False


class PartTypeState(_Strict):
    """One part type a cell makes: what one more part adds to its bound, and the machines a
    part of it needs (the robot, the mills of its route; a cell of an older cellctl sends
    none: the factory then counts every machine of the cell as needed)."""

    bound_s: Seconds
    machines: Annotated[tuple[Name, ...], Field(max_length=MAX_MACHINES)] = ()


class MachineState(_Strict):
    kind: Name
    state: Text
    in_service: bool


class StateMessage(_Message):
    """``PREFIX/state`` (retained), cell → factory: what the cell makes and how busy it is."""

    cell: Name
    time: Seconds
    paused: bool
    part_types: Annotated[dict[Name, PartTypeState], Field(max_length=MAX_PART_TYPES)]
    machines: Annotated[dict[Name, MachineState], Field(max_length=MAX_MACHINES)]
    orders_open: Count
    parts_open: Count
    finish_estimate_s: Seconds
    #: A cell that plans its own work (``[mailbox] plan_period``): when it last played its
    #: state forward (unix seconds), and how long after that its plan finishes every open
    #: order. Both or neither; a cell that does not plan leaves them out of the payload.
    plan_finish_s: Seconds | None = None
    planned_at: Seconds | None = None

    @model_validator(mode="after")
    def _plan(self) -> StateMessage:
        if (self.plan_finish_s is None) != (self.planned_at is None):
            raise ValueError("plan_finish_s and planned_at come together")
        return self


#: ``PREFIX/status`` (retained), cell → anyone allowed: plain text, not JSON.
Status = Literal["online", "offline"]
STATUSES: Final = ("online", "offline")

_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)
_BRACKET = re.compile(rb"[\[\]{}]")


def nesting(payload: bytes, limit: int = MAX_DEPTH) -> int:
    """How deep ``payload``'s objects and arrays nest (brackets inside strings do not count),
    or ``limit + 1`` as soon as it is deeper than ``limit``: a scan, no parser."""
    depth = deepest = 0
    for match in _BRACKET.finditer(_STRING.sub(b"", payload)):
        if match.group() in (b"[", b"{"):
            depth += 1
            if depth > limit:
                return limit + 1
            deepest = max(deepest, depth)
        else:
            depth -= 1
    return deepest


def _guard(payload: bytes, what: str) -> None:
    if len(payload) > MAX_PAYLOAD:
        raise WireError(f"{what} of {len(payload)} bytes: more than {MAX_PAYLOAD}", payload)
    if nesting(payload) > MAX_DEPTH:
        raise WireError(f"{what} nested deeper than {MAX_DEPTH} levels", payload)


def _reason(error: ValidationError) -> str:
    first = error.errors(include_url=False, include_input=False)[0]
    where = ".".join(str(p) for p in first["loc"]) or "payload"
    more = error.error_count() - 1
    text = f"{where}: {str(first['msg']).removeprefix('Value error, ')}" + (
        f" (and {more} more)" if more else ""
    )
    return text


M = TypeVar("M", bound=BaseModel)


def _parse(model: type[M], payload: bytes, what: str) -> M:
    _guard(payload, what)
    try:
        return model.model_validate_json(payload)
    except ValidationError as e:
        raise WireError(f"{what}: {_reason(e)}", payload) from None


def _to_cell_kind(value: Any) -> str:
    if isinstance(value, dict) and "ask" in value:
        return "ask"
    return "cancel" if isinstance(value, dict) and "cancel" in value else "order"


#: What the factory sends on a cell's ``orders`` topic.
ToCell = OrderMessage | AskMessage | CancelMessage

_TO_CELL: TypeAdapter[ToCell] = TypeAdapter(
    Annotated[
        Annotated[OrderMessage, Tag("order")]
        | Annotated[AskMessage, Tag("ask")]
        | Annotated[CancelMessage, Tag("cancel")],
        Discriminator(_to_cell_kind),
    ]
)


def parse_to_cell(payload: bytes) -> ToCell:
    """A message on a cell's ``orders`` topic: an order, the factory asking for reports, or
    the factory cancelling an order."""
    _guard(payload, "order")
    try:
        return _TO_CELL.validate_json(payload)
    except ValidationError as e:
        raise WireError(f"order: {_reason(e)}", payload) from None


def parse_report(payload: bytes) -> ReportMessage:
    """A message on a cell's ``reports`` topic."""
    return _parse(ReportMessage, payload, "report")


def parse_state(payload: bytes) -> StateMessage:
    """A message on a cell's ``state`` topic."""
    return _parse(StateMessage, payload, "state")


def parse_status(payload: bytes) -> Status:
    """A message on a cell's ``status`` topic: ``online`` or ``offline``."""
    text = payload[:16].decode("utf-8", "replace").strip()
    if text == "online" and len(payload) < 16:
        return "online"
    if text == "offline" and len(payload) < 16:
        return "offline"
    raise WireError("status is neither online nor offline", payload)


def report_message(
    cell: str, epoch: str, report: Report, *, withdrawn: bool = False
) -> ReportMessage:
    """The message of a mailbox's report (its text cut to :data:`MAX_TEXT` characters).

    A report made in the cell beyond the wire's limits (an order id of 200 characters posted
    from the command line, say) still goes out, so the numbering stays whole: without the
    ids and data that do not fit."""
    fields: dict[str, Any] = {
        "cell": cell,
        "epoch": epoch,
        "seq": report.seq,
        "kind": ReportKind(report.kind),
        "order_id": report.order_id,
        "part_id": report.part_id,
        "text": report.text[:MAX_TEXT],
        "time": report.time,
        "data": report.data,
        "withdrawn": withdrawn,
    }
    try:
        return ReportMessage(**fields)
    except ValidationError:
        for key in ("order_id", "part_id"):
            if not 1 <= len(fields[key] or "x") <= MAX_NAME:
                fields[key] = None
        return ReportMessage(**{**fields, "data": {}})
