"""How a control-API method is declared: its parameters' model and its :class:`Method` entry.

Parameters are pydantic models on :class:`P` (unknown keys refused); a :class:`Method` ties a
name to its parameters, its handler, its doc and the least role that may call it::

    class IdParams(P):
        id: str = Field(min_length=1, max_length=100)

    Method("orders.cancel", IdParams, _cancel, "Cancel an order that has not started.", True)

The cell's own methods (:data:`cellctl.service.methods.METHODS`) are declared with these, and
so are a server's own (``CellAccess.methods()``, e.g. a DNC server's).
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from cellctl.cell.causes import PRIORITIES
from cellctl.cell.journal import MAX_SHELVE, PART_STATUSES
from cellctl.clock import current_clock
from cellctl.errors import UsageError
from cellctl.kinds.menu import PrintableText
from cellctl.mailbox import ORDER_STATES
from cellctl.mailbox.base import MAX_QTY
from cellctl.service.access import CellAccess
from cellctl.service.audit import MAX_ENTRIES
from cellctl.service.functions import Progress
from cellctl.service.orderdue import resolve_due
from cellctl.service.token import ROLES

#: Integers a parameter may hold: 64 bits, signed (SQLite's and most clients' limit).
INT64_MAX = 2**63 - 1
#: The most entries a list parameter may hold.
MAX_LIST = 20


class P(BaseModel):
    """Base of the methods' parameters: unknown keys are refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, defer_build=True)


class NoParams(P):
    pass


class EstopParams(P):
    reason: PrintableText = Field(default="", max_length=500)


class SubmitParams(P):
    """``orders.submit``: ``due`` is unix seconds, or text as ``cellctl plan --until`` takes
    it (``FRI 18:00``, ``18:00``, ``2026-12-04T18:00``), read on the cell's clock as the call
    comes (:func:`cellctl.service.orderdue.resolve_due`) and held as unix seconds."""

    part_type: PrintableText = Field(min_length=1, max_length=100)
    qty: int = Field(default=1, ge=1, le=MAX_QTY)
    priority: int = Field(default=0, ge=-1_000_000, le=1_000_000)
    id: PrintableText | None = Field(default=None, min_length=1, max_length=100)
    due: float | None = None

    @field_validator("due", mode="before")
    @classmethod
    def _due(cls, value: Any) -> float | None:
        try:
            return resolve_due(value, current_clock().now())
        except UsageError as e:  # said after the field's name: "due: time 'x': write ..."
            raise ValueError(str(e)) from None


class OrdersParams(P):
    states: list[Literal[ORDER_STATES]] | None = Field(  # type: ignore[valid-type]
        default=None, max_length=MAX_LIST
    )


class IdParams(P):
    id: PrintableText = Field(min_length=1, max_length=100)


class AlarmsParams(P):
    all: bool = False


class AlarmParams(P):
    id: int = Field(ge=1, le=INT64_MAX)


class ShelveParams(P):
    id: int = Field(ge=1, le=INT64_MAX)
    seconds: float = Field(gt=0, le=MAX_SHELVE, allow_inf_nan=False)


class HistoryParams(P):
    since: float | None = Field(default=None, ge=0, le=1e11, allow_inf_nan=False)
    machine: PrintableText | None = Field(default=None, min_length=1, max_length=100)
    priority: Literal[PRIORITIES] | None = None  # type: ignore[valid-type]
    limit: int = Field(default=1000, ge=1, le=10_000)


class PartsParams(P):
    statuses: list[Literal[PART_STATUSES]] | None = Field(  # type: ignore[valid-type]
        default=None, max_length=MAX_LIST
    )
    order: PrintableText | None = Field(default=None, min_length=1, max_length=100)


class ReleaseParams(P):
    id: PrintableText = Field(min_length=1, max_length=100)
    redo: bool = False
    at: PrintableText | None = Field(default=None, min_length=1, max_length=50)


class ScrapParams(P):
    id: PrintableText = Field(min_length=1, max_length=100)
    reason: PrintableText = Field(default="scrapped by operator", min_length=1, max_length=500)
    #: The operator says the part is out of every machine it may be in (needed for one that
    #: may be: the cell loads that machine again at once).
    taken_out: bool = False


class MachineParams(P):
    machine: PrintableText = Field(min_length=1, max_length=100)
    reason: PrintableText = Field(default="", max_length=500)


class TrafficParams(P):
    machine: PrintableText = Field(min_length=1, max_length=100)
    limit: int = Field(default=100, ge=1, le=2000)


class StepsParams(P):
    since: float | None = Field(default=None, allow_inf_nan=False, ge=0, le=1e11)


class ShiftParams(P):
    """``report.shift``: the window, s since the epoch (default: the 8 h before ``until``,
    ``until`` now); at most a week."""

    since: float | None = Field(default=None, allow_inf_nan=False, ge=0, le=1e11)
    until: float | None = Field(default=None, allow_inf_nan=False, ge=0, le=1e11)


class PreviewParams(P):
    machine: PrintableText = Field(min_length=1, max_length=100)
    program: PrintableText = Field(min_length=1, max_length=500)


class AuditParams(P):
    since: float | None = Field(default=None, allow_inf_nan=False, ge=0, le=1e11)
    who: PrintableText | None = Field(default=None, min_length=1, max_length=100)
    limit: int = Field(default=200, ge=1, le=MAX_ENTRIES)


class MachineCallParams(BaseModel):
    """A manual function: ``machine`` (optional when the cell has one of the family), and
    the function's own parameters beside it."""

    model_config = ConfigDict(extra="allow", frozen=True, defer_build=True)
    machine: PrintableText | None = Field(default=None, min_length=1, max_length=100)


Handler = Callable[[CellAccess, Any, Progress | None], Awaitable[Any]]


@dataclass(frozen=True)
class Method:
    name: str
    params: type[BaseModel]
    handler: Handler
    doc: str
    acts: bool  # changes something (a read-only GET never calls one of these)
    #: The least role that may call it (:data:`~cellctl.service.token.ROLES`); left out, an
    #: acting method needs an operator and a read a viewer.
    role: str = field(default="", kw_only=True)
    #: Ends when its WebSocket client goes away (it touches no machine: a plan's play, whose
    #: CPU nobody waits for any more); every other call runs to its end.
    abandoned: bool = field(default=False, kw_only=True)

    def __post_init__(self) -> None:
        if not self.role:
            object.__setattr__(self, "role", "operator" if self.acts else "viewer")
        assert self.role in ROLES, self.role
