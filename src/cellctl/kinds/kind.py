"""What a machine kind declares, once: :class:`MachineKind`.

A kind is a small declared object in its own package, registered under the entry-point group
``cellctl.machine_kinds`` (see :mod:`cellctl.kinds.registry` and docs/kinds.md)::

    SAW = MachineKind(
        name="saw1",
        family="mill",
        maker="Acme",
        model="Saw 1",
        line="9600,8N1",
        options=SawOptions,                 # a pydantic model: cell.toml's options table
        open_driver=open_saw,               # async (DriverSpec) -> a driver of the family
        emulator=saw_emulator,              # (EmulatorSpec) -> an EmulatedDevice
        states=SawState,                    # its state numbers, an IntEnum
        condition=lambda status: status.kind_condition,
        language=ProgramLanguage(check=check_cut_list, suffix=".cut"),
        menu=lambda: MENU,                  # its manual functions (console, CLI, API)
        faults=FAULTS,                      # its emulator's fault switches
    )

docs/kinds.md walks through a whole kind (tests/plugins/cellctl_saw).

The host never imports a kind: it asks the registry for the one a machine's ``kind`` names,
and calls these hooks.
"""

from __future__ import annotations

import ast
import contextlib
import enum
import functools
import importlib
import inspect
import itertools
import logging
import textwrap
from collections.abc import Awaitable, Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, ValidationError

from cellctl.clock import Clock, emulator_clock
from cellctl.errors import CellctlError, UsageError
from cellctl.link import LineSettings, TrafficLog

if TYPE_CHECKING:
    import click

    from cellctl.drivers.state import StateStore
    from cellctl.emulators.serve import EmulatedDevice
    from cellctl.kinds.families import StartOutput
    from cellctl.kinds.menu import MachineFunction

log = logging.getLogger(__name__)

Family = Literal["robot", "mill"]
#: The families a kind belongs to: what the cell does with it (a PLC stays what it is).
FAMILIES: tuple[Family, ...] = ("robot", "mill")


class ProgramRole(enum.StrEnum):
    """What a program is for, as the cell's config names it."""

    SETUP = "setup"
    """A mill's setup program (``[machines.NAME] setup``)."""
    MILLING = "milling"
    """A route step's program (``[parts.NAME] route``)."""
    TRANSFER = "transfer"
    """A robot's transfer program (``[robot_programs]``)."""


@dataclass(frozen=True)
class CheckedProgram:
    """A program the kind's language checked: what the cell needs to know of it."""

    problems: tuple[str, ...] = ()
    """Every problem found, each in the user's words with its file and line."""
    lines: int = 0
    machining_s: float = 0.0
    """The kind's estimate of the program's run time, s (0 when it has none)."""
    compiled: Any = None
    """What the kind sends (a robot's compiled program); None where it sends the file."""
    tally: str = ""
    """The problems counted in words where the list stops short of them (the kind's check
    stopped: "1318 problems found before checking stopped at line 3 (the first 100
    listed)"); empty where every problem is listed."""

    @property
    def ok(self) -> bool:
        return not self.problems

    @property
    def counted(self) -> str:
        """How many problems, in words: ``"3 problem(s)"``, or :attr:`tally`."""
        return self.tally or f"{len(self.problems)} problem(s)"


@dataclass(frozen=True)
class Preview:
    """A program's toolpath drawn as SVG text, and how many blocks it goes in."""

    svg: str
    blocks: int


@dataclass(frozen=True)
class ProgramLanguage:
    """A kind's program language, as hooks: each may be None where the kind has none.

    ``check(path, role, options)`` reads and checks a file (never raising for a bad program:
    its problems are returned); ``compile(source, name, origin)`` turns a source into what
    the machine takes (``origin`` names the file in its errors); ``split(text)`` cuts a long
    program into what the machine holds at once; ``preview(text, name, options)`` draws the
    toolpath (UsageError when there is none to draw).
    """

    suffix: str
    """The file name ending of its programs (``.dyn``, ``.aml``), for pickers."""
    check: Callable[[Path, ProgramRole, BaseModel], CheckedProgram]
    compile: Callable[[str, str, str], Any] | None = None
    split: Callable[[str], list[str]] | None = None
    preview: Callable[[str, str, BaseModel], Preview] | None = None


@dataclass(frozen=True)
class DriverSpec:
    """Everything a kind's driver is built from: the one place the controller and the
    standalone service describe a machine to its kind."""

    url: str
    name: str
    settings: LineSettings
    options: BaseModel
    """The kind's checked options (an instance of :attr:`MachineKind.options`)."""
    store: StateStore | None = None
    trace: TrafficLog | None = None
    start_output: StartOutput | None = None
    """A mill's cycle-start input, wired through the cell's PLC (None: no GO)."""
    clock: Clock | None = None
    """What the driver times its waits on (None: its link's, the running loop's)."""


@dataclass(frozen=True)
class EmulatorSpec:
    """How to build a kind's emulator: its clock and, for the emulated cell, an automatic
    operator (``operator_s``: seconds the operator takes for a setup, 0 = at once).

    ``clock`` is what the emulator runs on; ``time_scale`` alone is shorthand for
    ``RealClock(time_scale)``, and with a clock it is the clock's. Neither (or a scale of 1):
    the running loop's clock, resolved when used, so the same emulator runs on virtual time.
    A kind builds its emulator with ``clock=spec.emulator_clock()``.
    """

    time_scale: float = 1.0
    readiness: str = "modem"
    operator: bool = True
    extra: dict[str, Any] = field(default_factory=dict)
    clock: Clock | None = None

    def __post_init__(self) -> None:
        clock = emulator_clock(self.clock, None if self.time_scale == 1.0 else self.time_scale)
        if clock is not None:
            object.__setattr__(self, "time_scale", clock.time_scale)

    def emulator_clock(self) -> Clock | None:
        """The clock to hand the emulator (None: the running loop's, resolved when used)."""
        return emulator_clock(self.clock, self.time_scale)


@dataclass(frozen=True)
class Origin:
    """Where a kind comes from: the distribution that declared it and its module."""

    distribution: str
    module: str

    def __str__(self) -> str:
        return f"{self.distribution} ({self.module})"


@dataclass(frozen=True)
class MachineKind:
    """One machine kind, declared once (see module docstring)."""

    name: str
    family: Family
    maker: str
    model: str
    line: str
    """Default line settings, e.g. ``"4800,7E2"``."""
    options: type[BaseModel]
    """The kind's options (``[machines.NAME] options``): unknown keys are refused."""
    open_driver: Callable[[DriverSpec], Awaitable[Any]]
    """Open the machine's link and return its driver (one of the family's protocol)."""
    emulator: Callable[[EmulatorSpec], EmulatedDevice]
    states: type[MachineState]
    """The kind's state numbers, by name."""
    condition: Callable[[Any], Any]
    """The :class:`~cellctl.kinds.Condition` a driver's status record shows."""
    language: ProgramLanguage | None = None
    menu: Callable[[], Sequence[MachineFunction]] | None = None
    """The console's and API's manual functions (the source's menu for the 1988 kinds)."""
    commands: Callable[[], Sequence[tuple[str, click.Command]]] | None = None
    """CLI commands the kind contributes: (group, command); group ``""`` is the top level."""
    command_names: tuple[tuple[str, str], ...] | None = None
    """(group, name) of each command ``commands`` gives, so that the CLI imports the kind's
    commands only when one of them is used (``cellctl dnc`` imports no robot's CLI). None:
    they are imported whenever ``cellctl`` looks for a command it does not know."""
    emulated_options: Callable[[float], dict[str, float]] | None = None
    """Options the emulated cell writes for a machine ``time_scale`` times faster (its
    deadlines scaled)."""
    needs_setup: bool = False
    """Whether a machine of this kind needs ``setup`` (a setup program) in cell.toml."""
    program_files: tuple[str, ...] = ()
    """File name endings of what its manual functions send (the console's program pickers);
    the language's ``suffix`` when empty."""
    check_text: Callable[[str, str, str, BaseModel], list[str]] | None = None
    """``check_text(function, name, text, options)``: every problem of a program that manual
    function ``function`` sends, one per line (empty: it may go). The console checks a
    dialog's program with it before a byte is sent."""
    faults: Mapping[str, str] = field(default_factory=dict)
    """Its emulator's fault switches (name -> what it does), for ``cellctl emulate cell``'s
    ``--fault MACHINE:NAME[=ARG]``."""
    timing: Callable[[], Any] | None = None
    """Its timing model for bounds from physics: a robot's
    :class:`~cellctl.kinds.families.RobotModel`, a mill's
    :class:`~cellctl.kinds.families.MillModel` (made on demand)."""
    description: str = ""
    origin: Origin | None = None
    """Set by the registry: where it was found."""

    @property
    def line_settings(self) -> LineSettings:
        return LineSettings.parse(self.line)

    @property
    def picked_files(self) -> tuple[str, ...]:
        """The file endings its program pickers show."""
        if self.program_files:
            return self.program_files
        return (self.language.suffix,) if self.language is not None else ()

    @property
    def title(self) -> str:
        """Maker and model, as a person names the machine: ``Dyna 2400 CNC mill``."""
        return f"{self.maker} {self.model}"

    def checked_options(self, options: dict[str, Any]) -> BaseModel:
        """The options of ``cell.toml`` as the kind's model; UsageError naming the field."""
        try:
            return self.options.model_validate(options)
        except ValidationError as e:
            problems = []
            for item in e.errors(include_url=False):
                where = ".".join(str(k) for k in item["loc"]) or "options"
                message = "unknown option" if item["type"] == "extra_forbidden" else item["msg"]
                problems.append(f"{where}: {str(message).removeprefix('Value error, ')}")
            raise UsageError(f"{self.name} options: " + "; ".join(problems)) from None

    def options_table(self) -> str:
        """Its options as a Markdown table (docs/kinds.md holds one per shipped kind)."""
        rows = ["| option | default | meaning |", "|---|---|---|"]
        for key, info in self.options.model_fields.items():
            default = (
                "required"
                if info.is_required()
                else repr(info.get_default(call_default_factory=True))
            )
            meaning = " ".join(
                (info.description or attribute_docs(self.options).get(key, "")).split()
            )
            rows.append(f"| `{key}` | {default} | {meaning} |")
        return "\n".join(rows) + "\n"

    def machine_words(self, machine: str) -> str:
        """Machine ``machine`` of this kind as an error names it: ``saw (kind saw1 from
        cellctl-saw)``."""
        where = f" from {self.origin.distribution}" if self.origin is not None else ""
        return f"{machine} (kind {self.name}{where})"

    async def open(self, spec: DriverSpec) -> Any:
        """Open a driver for ``spec`` (its options already checked by :meth:`checked_options`),
        held to its family's protocol: a driver missing a member is closed and refused, a
        mill's readings are checked as they come (``KindContractError`` naming the machine,
        the kind and where it comes from)."""
        from cellctl.kinds.families import KindContractError, checked_driver

        driver = await self.open_driver(spec)
        try:
            checked_driver(driver, self.family, self.machine_words(spec.name or spec.url))
        except KindContractError:
            close = getattr(driver, "close", None)
            if callable(close):
                with contextlib.suppress(Exception):  # a broken driver's close may fail too
                    await close()
            raise
        return driver


@functools.cache
def attribute_docs(model: type[BaseModel]) -> dict[str, str]:
    """The docstring under each field of ``model`` and its bases, read from their source
    when asked (docs tables): pydantic's ``use_attribute_docstrings`` would read it at
    every import, at every start of every command."""
    docs: dict[str, str] = {}
    for cls in reversed(model.__mro__):
        if not (isinstance(cls, type) and issubclass(cls, BaseModel)) or cls is BaseModel:
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
        except (OSError, TypeError, SyntaxError):
            continue  # no source (a frozen build): the table says less, nothing fails
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for field_stmt, doc in itertools.pairwise(body):
            if (
                isinstance(field_stmt, ast.AnnAssign)
                and isinstance(field_stmt.target, ast.Name)
                and isinstance(doc, ast.Expr)
                and isinstance(doc.value, ast.Constant)
                and isinstance(doc.value.value, str)
            ):
                docs[field_stmt.target.id] = inspect.cleandoc(doc.value.value)
    return docs


class BrokenKind(CellctlError):
    """An installed kind that cannot be used, said in words that name it, its package, what
    is wrong and what its author should fix: ``kind 'saw2' (package cellctl-saw2) is
    installed but broken: ImportError: ...``. A plug-in's mistake, never the user's."""


class LazyTable(Mapping[str, str]):
    """A table another module holds, imported when first read: ``faults=LazyTable(
    "mykind.emulator:FAULTS")`` keeps the declaration (read at every start) from importing
    the emulator.

    One that cannot be read (no such module or name, not a table of str -> str) makes its
    kind broken: :meth:`read` and a look-up (``name in table``, ``table[name]``) raise
    :class:`BrokenKind`; a listing (``len``, iteration: a help naming every kind's switches)
    warns once and lists nothing, so every other kind still shows. The registry gives each
    kind's table its kind's words (:meth:`owned`)."""

    def __init__(self, target: str, *, owner: str = "", field: str = "faults") -> None:
        self.target = target
        self._owner = owner
        self._field = field
        self._table: Mapping[str, str] | None = None
        self._broken: BrokenKind | None = None
        self._warned = False

    def owned(self, owner: str, field: str) -> LazyTable:
        """This table as kind ``owner`` declares it in ``field`` (its errors say both):
        ``owner`` as ``kind 'saw2' (package cellctl-saw2)``."""
        return LazyTable(self.target, owner=owner, field=field)

    def read(self) -> Mapping[str, str]:
        """The table, imported on first use; :class:`BrokenKind` if it cannot be read."""
        if self._broken is not None:
            raise self._broken
        if self._table is None:
            try:
                self._table = self._load()
            except Exception as e:  # a plug-in's mistake of any kind: said, not a traceback
                why = str(e) if isinstance(e, _NotATable) else f"{type(e).__name__}: {e}"
                self._broken = BrokenKind(
                    f"{self._owner or 'a kind'} is installed but broken: its {self._field} "
                    f"table {self!r} cannot be read: {why} (fix the target, "
                    '"module:NAME" of a dict of str -> str, in its MachineKind declaration)'
                )
                raise self._broken from None
        return self._table

    def _load(self) -> Mapping[str, str]:
        module, _, name = self.target.partition(":")
        table = getattr(importlib.import_module(module), name)
        if not isinstance(table, Mapping) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in table.items()
        ):
            raise _NotATable(f"{name} is a {type(table).__name__}, not a dict of str -> str")
        return table

    def _listed(self) -> Mapping[str, str]:
        # Listing every kind's tables (a help): a broken one is warned of and lists nothing.
        try:
            return self.read()
        except BrokenKind as e:
            if not self._warned:
                self._warned = True
                log.warning("machine %s", e)
            return {}

    def __getitem__(self, key: str) -> str:
        return self.read()[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._listed())

    def __len__(self) -> int:
        return len(self._listed())

    def __repr__(self) -> str:
        return f"LazyTable({self.target!r})"


class _NotATable(TypeError):
    """A LazyTable's target that is not a table (its words are the message)."""


class MachineState(enum.IntEnum):
    """A kind's state numbers, each with the machine's words for it (``.text``)::

    class MillState(MachineState):
        IDLE = 0, "Idle"
    """

    text: str

    def __new__(cls, value: int, text: str = "") -> MachineState:
        obj = int.__new__(cls, value)
        obj._value_ = value
        obj.text = text
        return obj

    @classmethod
    def words(cls, state: int) -> str:
        """State ``state`` in words (``state N`` for a number the kind does not know)."""
        try:
            return cls(state).text
        except ValueError:
            return f"state {state}"
