"""The DNC server's machines: ``SHOP/dnc.toml``, or a cell's ``cell.toml`` machines of kind
``iso-cnc``::

    [dnc]                                   # optional
    listen = "127.0.0.1:7130"               # the API and dashboard on TCP too (loopback)

    [machines.mill1]
    link = "/dev/ttyUSB0"                   # or rfc2217://device-server:4001, socket://...
    line = "9600,7E2"                       # optional: the kind's default otherwise
    options = { tolerance = 10 }            # the iso-cnc kind's options (`cellctl kinds`)

    [machines.mill1.request]                # optional: the remote-request convention
    program = 9999                          # O9999 (LOAD O1234) / O9999 (DRIP O1234)

::

    shop = load_shop(Path("SHOP"))                  # dnc.toml there
    shop = load_shop(Path("SHOP"), cell=Path("cell"))   # the cell's iso-cnc machines
    shop.machines["mill1"].url

Everything is checked before a link is opened: unknown keys, a missing link, a line that
does not parse, the kind's options (by their field name), a request program with more digits
than the control's O-numbers (``o_digits``), two machines on one link, a name that cannot be a
directory. Each refusal names the file and the table.
"""

from __future__ import annotations

import shlex
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from cellctl.errors import UsageError, unknown_machine
from cellctl.files import read_text
from cellctl.kinds.iso_cnc.dnc.request import RequestConvention
from cellctl.kinds.iso_cnc.dnc.store import check_machine_name
from cellctl.kinds.iso_cnc.driver import ISO_LINE, IsoCncOptions
from cellctl.link import LineSettings
from cellctl.link.keys import link_keys
from cellctl.link.listen import parse_listen

#: The kind the DNC server feeds (its own package's name for it).
KIND = "iso-cnc"
DNC_FILE = "dnc.toml"
#: Machines one server may feed (each is a link and a task).
MAX_MACHINES = 1024


class _Strict(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", defer_build=True)


class DncTable(_Strict):
    """``[dnc]``: the server itself."""

    listen: str | None = Field(default=None, max_length=200)
    """``HOST:PORT`` for the control API and dashboard on TCP (loopback unless allow_remote);
    the Unix socket ``SHOP/api.sock`` always."""
    allow_remote: bool = False
    """Answer on a non-loopback ``listen`` address (the token is still required)."""


class MachineTable(_Strict):
    """``[machines.NAME]``: one control on its own link."""

    kind: str = KIND
    """Only ``iso-cnc`` (the default)."""
    link: str = Field(min_length=1, max_length=500)
    """The control's link: a serial device, ``rfc2217://``, ``socket://`` or a pty."""
    line: str | None = Field(default=None, max_length=40)
    """Line settings, e.g. ``9600,7E2`` (the kind's default when left out)."""
    options: dict[str, Any] = Field(default_factory=dict)
    """The kind's driver options (buffer, tolerance, leader ...)."""
    request: RequestConvention = Field(default_factory=RequestConvention)
    """The remote-request convention."""


class DncFile(_Strict):
    dnc: DncTable = Field(default_factory=DncTable)
    machines: dict[str, MachineTable] = Field(default_factory=dict)


@dataclass(frozen=True)
class DncMachine:
    """A machine the server feeds, checked: its link, line, kind options and convention."""

    name: str
    url: str
    settings: LineSettings
    options: IsoCncOptions
    request: RequestConvention


@dataclass(frozen=True)
class ShopConfig:
    """The shop: its directory, machines and where its API answers."""

    root: Path
    machines: dict[str, DncMachine] = field(default_factory=dict)
    listen: str | None = None
    allow_remote: bool = False
    source: Path | None = None
    before: tuple[str, ...] = ()
    """What names this shop on a command line before ``dnc`` (``--cell DIR``)."""
    after: tuple[str, ...] = ()
    """... and after the subcommand (``--dir DIR``, ``--use-cell``): none for the default."""

    def command(self, words: str) -> str:
        """``cellctl dnc WORDS`` as a user types it to act on this shop, from any directory
        when the shop was named (``cellctl dnc stop mill1 --dir /srv/shop5``)."""
        before = "".join(f" {shlex.quote(x)}" for x in self.before)
        after = "".join(f" {shlex.quote(x)}" for x in self.after)
        return f"cellctl{before} dnc {words}{after}"


def _describe(e: ValidationError, table: str) -> str:
    problems = []
    for item in e.errors(include_url=False):
        where = ".".join(str(k) for k in item["loc"])
        message = "unknown key" if item["type"] == "extra_forbidden" else item["msg"]
        problems.append(f"{table}{'.' if where else ''}{where}: {message}")
    return "; ".join(problems)


def _load(path: Path) -> dict[str, Any]:
    try:
        return tomllib.loads(read_text(path))
    except FileNotFoundError:
        raise UsageError(
            f"no {path}: write one (docs/dnc.md), or feed a cell's iso-cnc machines with "
            "--cell DIR --use-cell"
        ) from None
    except tomllib.TOMLDecodeError as e:
        raise UsageError(f"{path}: not valid TOML: {e}") from None
    except UnicodeDecodeError as e:
        raise UsageError(f"{path}: not UTF-8 text: {e.reason}") from None
    except OSError as e:
        raise UsageError(f"{path}: cannot read: {e.strerror}") from None


def _machine(name: str, table: MachineTable, path: Path) -> DncMachine:
    where = f"{path}: [machines.{name}]"
    try:
        check_machine_name(name)
    except UsageError as e:
        raise UsageError(f"{where}: {e}") from None
    if table.kind != KIND:
        raise UsageError(f"{where}: kind {table.kind!r}: the DNC server feeds {KIND} controls")
    try:
        settings = LineSettings.parse(table.line or ISO_LINE)
    except (UsageError, ValueError) as e:
        raise UsageError(f"{where}: line = {table.line!r}: {e}") from None
    try:
        options = IsoCncOptions.model_validate(table.options)
    except ValidationError as e:
        problems = []
        for item in e.errors(include_url=False):
            key = ".".join(str(k) for k in item["loc"]) or "options"
            said = "unknown option" if item["type"] == "extra_forbidden" else item["msg"]
            problems.append(f"options.{key}: {said}")
        raise UsageError(f"{where}: " + "; ".join(problems)) from None
    request = _request_for(name, table.request, options, where)
    return DncMachine(name, table.link, settings, options, request)


def _request_for(
    name: str, request: RequestConvention, options: IsoCncOptions, where: str
) -> RequestConvention:
    """The machine's request convention, its program numbered as the control can: the
    default O9999 is the highest number of a 4-digit control, and a control with fewer
    digits gets its own highest (O999 on 3 digits). A request program given that the control
    cannot number (``program = 123456`` on a 4-digit control) is refused: it could never
    write or punch it, so no request would ever come. So is a load word that is the drip
    word (``load = "DRIP"``, or ``"drip"``: the words are read in any case): no request
    could ask for a load."""
    if request.enabled and request.load.upper() == request.drip.upper():
        # A request's words are read in any case (LOAD, load, Load): so are these two.
        raise UsageError(
            f"{where}: request.load = {request.load!r} and request.drip = {request.drip!r} "
            "are the same word (a request's words are read in any case): every request "
            f"would ask for a drip-feed, none for a load into memory; give two different "
            'words, e.g. load = "LOAD" and drip = "DRIP"'
        )
    digits = options.o_digits
    if not request.enabled or request.program < 10**digits:
        return request
    if "program" not in request.model_fields_set:
        return request.model_copy(update={"program": 10**digits - 1})
    raise UsageError(
        f"{where}: request.program = {request.program} has {len(str(request.program))} "
        f"digits, but {name}'s control takes {digits} (options.o_digits = {digits}): it could "
        f"never punch O{request.program}, so no remote request would ever come; give a "
        f"request program from 1 to {10**digits - 1}"
    )


def parse_dnc_file(data: dict[str, Any], root: Path, path: Path) -> ShopConfig:
    """A parsed dnc.toml, checked (see module docstring)."""
    try:
        parsed = DncFile.model_validate(data)
    except ValidationError as e:
        raise UsageError(f"{path}: {_describe(e, '')}".replace(": .", ": ")) from None
    if not parsed.machines:
        raise UsageError(f"{path}: no [machines.NAME] table: name at least one control")
    if len(parsed.machines) > MAX_MACHINES:
        raise UsageError(f"{path}: {len(parsed.machines)} machines, at most {MAX_MACHINES}")
    machines = {n: _machine(n, t, path) for n, t in parsed.machines.items()}
    _distinct_links(machines, path)
    if parsed.dnc.listen is not None:
        _check_listen(parsed.dnc.listen, parsed.dnc.allow_remote, path)
    return ShopConfig(root, machines, parsed.dnc.listen, parsed.dnc.allow_remote, source=path)


def _check_listen(text: str, allow_remote: bool, path: Path) -> None:
    """``[dnc] listen``: ``HOST:PORT``, on loopback unless ``allow_remote`` (said here, in
    the [dnc] table's words, when the shop's file is read)."""
    try:
        parse_listen(text, allow_remote, table="dnc", example="127.0.0.1:7130")
    except UsageError as e:
        raise UsageError(f"{path}: {e}") from None


def _distinct_links(machines: dict[str, DncMachine], path: Path) -> None:
    # Compared by canonical keys: localhost and 127.0.0.1, a symlink and its device, are one
    # link; a host that does not resolve now is compared by its name.
    seen: dict[str, DncMachine] = {}
    for m in machines.values():
        for key in link_keys(m.url, unresolved="name"):
            other = seen.setdefault(key, m)
            if other is not m:
                same = "" if other.url == m.url else f" ({other.url} is the same link)"
                raise UsageError(
                    f"{path}: [machines.{other.name}] and [machines.{m.name}] are both on "
                    f"{m.url}{same}: one link feeds one control"
                )


def _from_cell(cell: Path, root: Path) -> ShopConfig:
    path = cell / "cell.toml"
    data = _load(path)
    raw = data.get("machines", {})
    machines: dict[str, DncMachine] = {}
    for name, entry in raw.items() if isinstance(raw, dict) else ():
        if not isinstance(entry, dict) or entry.get("kind") != KIND:
            continue
        if not entry.get("link"):
            raise UsageError(f"{path}: [machines.{name}] has no link")
        table = MachineTable(
            link=str(entry["link"]),
            line=entry.get("line"),
            options=dict(entry.get("options", {})),
        )
        machines[name] = _machine(name, table, path)
    if not machines:
        raise UsageError(f"{path}: no machine of kind {KIND}: the DNC server has none to feed")
    _distinct_links(machines, path)
    return ShopConfig(root, machines, source=path)


def load_shop(root: Path, *, cell: Path | None = None) -> ShopConfig:
    """The shop in ``root``: its dnc.toml, or the ``iso-cnc`` machines of ``cell``'s cell.toml."""
    if cell is not None:
        return _from_cell(Path(cell), Path(root))
    path = Path(root) / DNC_FILE
    return parse_dnc_file(_load(path), Path(root), path)


def machine(config: ShopConfig, name: str) -> DncMachine:
    """The machine called ``name``; UsageError naming the known ones."""
    found = config.machines.get(name)
    if found is None:
        raise unknown_machine(name, sorted(config.machines), str(config.source))
    return found
