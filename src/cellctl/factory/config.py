"""The factory described in one file: ``factory.toml`` in the factory directory.

::

    [factory]
    name = "lab factory"
    resend = 2.0             # s between re-sends of an order its cell has not answered
    accept_timeout = 30.0    # s a cell has to take an order before it may go elsewhere
    poll_period = 0.5        # s: how often the controller looks at new orders and deadlines

    [broker]
    url = "mqtt://127.0.0.1:1883"        # or mqtts://HOST:8883
    credentials = "factory.credentials"  # username and password (TOML, mode 0600)
    # ca = "broker-ca.pem"               # mqtts:// with a private CA

    [dispatch]
    estimate = "bound"       # or "plan": a cell's own plan's finish when it is fresh
    plan_age = 600.0         # s a cell's plan stays fresh

    [cells.cell1]
    prefix = "cellctl/cell1"             # the path of the cell's [mailbox] url

:func:`load_factory` returns the checked :class:`FactoryConfig` or raises
:class:`UsageError` naming every problem. The part types each cell makes are not here: they
come from the cell's own retained state message.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from cellctl.errors import UsageError
from cellctl.factory.dispatch import BOUND, PLAN_AGE_S, EstimateKind

FACTORY_FILE = "factory.toml"
#: The factory's own state (orders, what each cell said), in the factory directory.
STATE_FILE = Path("state") / "factory.db"
_PREFIX = re.compile(r"[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*")


class _Table(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, defer_build=True)


class FactoryTable(_Table):
    name: str = Field(default="factory", min_length=1, max_length=80)
    resend: float = Field(default=2.0, gt=0, le=3600)
    accept_timeout: float = Field(default=30.0, gt=0, le=86400)
    poll_period: float = Field(default=0.5, gt=0, le=60)


class BrokerTable(_Table):
    url: str
    credentials: str
    ca: str | None = None

    @field_validator("url")
    @classmethod
    def _url(cls, value: str) -> str:
        parts = urlsplit(value)
        plain = parts.path in ("", "/")
        if parts.scheme not in ("mqtt", "mqtts") or not parts.hostname or not plain:
            raise ValueError(f"url = {value!r}: expected mqtt://HOST:PORT or mqtts://HOST:PORT")
        return value


class CellTable(_Table):
    prefix: str

    @field_validator("prefix")
    @classmethod
    def _prefix(cls, value: str) -> str:
        if not _PREFIX.fullmatch(value):
            raise ValueError(f"prefix = {value!r}: words joined by '/', no wildcards")
        return value


class DispatchTable(_Table):
    estimate: EstimateKind = BOUND
    plan_age: float = Field(default=PLAN_AGE_S, gt=0, le=86400)


class FactoryFile(_Table):
    factory: FactoryTable = FactoryTable()
    broker: BrokerTable
    dispatch: DispatchTable = DispatchTable()
    cells: dict[str, CellTable] = Field(min_length=1)


@dataclass(frozen=True)
class FactoryConfig:
    """The checked factory.toml, paths made absolute."""

    directory: Path
    name: str
    resend: float
    accept_timeout: float
    poll_period: float
    broker_url: str
    credentials: Path
    ca: Path | None
    cells: dict[str, str]  # cell name -> topic prefix
    estimate: EstimateKind = BOUND  # [dispatch] estimate: "bound" or "plan"
    plan_age: float = PLAN_AGE_S  # [dispatch] plan_age: s a cell's plan stays fresh

    @property
    def state_path(self) -> Path:
        return self.directory / STATE_FILE

    def cell_url(self, cell: str) -> str:
        """The ``[mailbox] url`` that cell's cell.toml names."""
        return f"{self.broker_url.rstrip('/')}/{self.cells[cell]}"


def factory_lock_path(directory: Path | str) -> Path:
    """The lock ``cellctl factory run`` holds on the factory in ``directory``."""
    return Path(directory) / "state" / "factory.lock"


def load_factory(directory: Path | str) -> FactoryConfig:
    """The checked ``<directory>/factory.toml``; UsageError listing every problem otherwise."""
    directory = Path(directory)
    path = directory / FACTORY_FILE
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UsageError(
            f"{path}: no such file (make one with `cellctl emulate factory --cells 3 {directory}`"
            " or see docs/factory.md)"
        ) from None
    except (OSError, UnicodeDecodeError) as e:
        raise UsageError(f"{path}: cannot read: {e}") from None
    except tomllib.TOMLDecodeError as e:
        raise UsageError(f"{path}: not TOML: {e}") from None
    try:
        file = FactoryFile.model_validate(raw)
    except ValidationError as e:
        problems = [
            f"{'.'.join(str(p) for p in err['loc']) or 'file'}: {err['msg']}" for err in e.errors()
        ]
        raise UsageError(f"{path}: " + "; ".join(problems)) from None
    prefixes = [c.prefix for c in file.cells.values()]
    if len(set(prefixes)) != len(prefixes):
        raise UsageError(f"{path}: two cells have the same prefix")
    return FactoryConfig(
        directory=directory,
        name=file.factory.name,
        resend=file.factory.resend,
        accept_timeout=file.factory.accept_timeout,
        poll_period=file.factory.poll_period,
        broker_url=file.broker.url,
        credentials=directory / file.broker.credentials,
        ca=directory / file.broker.ca if file.broker.ca else None,
        cells={name: table.prefix for name, table in file.cells.items()},
        estimate=file.dispatch.estimate,
        plan_age=file.dispatch.plan_age,
    )
