"""The cell PLC's IO map: which Modbus coil or discrete input means what. Pure, no I/O.

The PLC holds the cell's sensors and actuators. The controller writes **coils** and reads
**discrete inputs** over Modbus/TCP; :class:`PlcMap` says which address each signal has::

    plc_map = PlcMap.from_toml(load_cell_file(cell_dir)["plc"])
    plc_map.coils["door_1"]           # 4: the coil that opens the door of CNC 1
    describe("door_closed_1")         # 'door of CNC 1 closed'

``cell.toml`` carries the map in a ``[plc]`` table; every key is optional, a given ``coils``
or ``inputs`` table must name every required signal of its kind::

    [plc]
    url = "modbus://127.0.0.1:5020"   # modbus://HOST[:PORT], port 502 if left out;
                                      # mem://NAME: an emulated PLC in the same event loop
    unit = 1                          # Modbus unit (slave) id
    timeout = 1.0                     # seconds each request may take
    poll = 0.05                       # seconds between reads while waiting for an input
    coils = { pallet_request = 0, pallet_release = 1, clamp_1 = 2, ... }
    inputs = { pallet_present = 0, outfeed_clear = 1, ... }

Signal names end in ``_1`` / ``_2`` for CNC 1 / CNC 2; ``clamp[1]`` and ``clamp1`` are
accepted for ``clamp_1`` wherever a name is taken. The source gives no wiring: the default addresses
(:data:`DEFAULT_COILS`, :data:`DEFAULT_INPUTS`) are **assumed**, coils and inputs each numbered
from 0 in the order of :data:`SIGNALS`.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Literal
from urllib.parse import urlsplit

from cellctl.errors import UsageError

__all__ = [
    "COIL",
    "DEFAULT_COILS",
    "DEFAULT_INPUTS",
    "DEFAULT_URL",
    "EXAMPLE_WIRING",
    "INPUT",
    "MILLS",
    "MODBUS_EXCEPTIONS",
    "OPTIONAL_INPUTS",
    "SIGNALS",
    "PlcMap",
    "PlcTiming",
    "RobotWiring",
    "Signal",
    "canonical",
    "check_plc_url",
    "describe",
    "parse_modbus_url",
    "plc_mem_name",
    "signal_name",
]

COIL: Literal["coil"] = "coil"
INPUT: Literal["input"] = "input"
MILLS = (1, 2)
DEFAULT_URL = "modbus://127.0.0.1:5020"
MODBUS_PORT = 502
#: Modbus allows at most 2000 bits in one read; the driver reads all inputs at once.
MAX_READ_BITS = 2000


@dataclass(frozen=True)
class Signal:
    """One PLC signal: its kind, what it means, and how a wait for it failing is said.

    ``not_true``/``not_false`` complete "… within 5 s" when a wait for 1 / 0 runs out.
    """

    kind: Literal["coil", "input"]
    meaning: str
    not_true: str = ""
    not_false: str = ""


def _mill_signals() -> dict[str, Signal]:
    out: dict[str, Signal] = {}
    for n in MILLS:
        out[f"clamp_{n}"] = Signal(COIL, f"vise of CNC {n}: 1 = clamp, 0 = unclamp")
    for n in MILLS:
        out[f"door_{n}"] = Signal(COIL, f"door of CNC {n}: 1 = open, 0 = close")
    for n in MILLS:
        out[f"go_{n}"] = Signal(COIL, f"GO of CNC {n}: a pulse starts the loaded mill program")
    return out


def _mill_inputs() -> dict[str, Signal]:
    out: dict[str, Signal] = {}
    for n in MILLS:
        out[f"clamp_closed_{n}"] = Signal(
            INPUT,
            f"vise of CNC {n} clamped",
            f"vise of CNC {n} did not clamp",
            f"vise of CNC {n} did not unclamp",
        )
    for n in MILLS:
        out[f"door_open_{n}"] = Signal(
            INPUT,
            f"door of CNC {n} fully open",
            f"door of CNC {n} did not open",
            f"door of CNC {n} did not leave its open position",
        )
    for n in MILLS:
        out[f"door_closed_{n}"] = Signal(
            INPUT,
            f"door of CNC {n} closed",
            f"door of CNC {n} did not close",
            f"door of CNC {n} did not leave its closed position",
        )
    for n in MILLS:
        out[f"part_present_{n}"] = Signal(
            INPUT,
            f"a part sits in the vise of CNC {n}",
            f"no part arrived in the vise of CNC {n}",
            f"the part was not taken out of the vise of CNC {n}",
        )
    return out


#: Every signal the controller knows: name -> kind and meaning. Coils first, then inputs; the
#: order gives the default addresses.
SIGNALS: Mapping[str, Signal] = MappingProxyType(
    {
        "pallet_request": Signal(COIL, "ask the conveyor for the next pallet (rising edge)"),
        "pallet_release": Signal(COIL, "send the pallet at the pick-up away (rising edge)"),
        **_mill_signals(),
        "pallet_present": Signal(
            INPUT,
            "a pallet stands at the conveyor pick-up",
            "no pallet arrived at the conveyor pick-up",
            "the pallet at the conveyor pick-up did not leave",
        ),
        "outfeed_clear": Signal(
            INPUT,
            "the outfeed has room for a finished pallet",
            "the outfeed did not clear",
            "no pallet entered the outfeed",
        ),
        **_mill_inputs(),
        "estop_ok": Signal(
            INPUT,
            "emergency stop circuit closed (1 = safe to move)",
            "the emergency stop was not released",
            "the emergency stop did not trip",
        ),
    }
)

#: Inputs a cell may leave unwired (no sensor): reads then leave them out.
OPTIONAL_INPUTS = frozenset({"outfeed_clear", "part_present_1", "part_present_2"})

#: Assumed coil addresses (the source gives no wiring).
DEFAULT_COILS: Mapping[str, int] = MappingProxyType(
    {name: i for i, name in enumerate(n for n, s in SIGNALS.items() if s.kind == COIL)}
)
#: Assumed discrete-input addresses (the source gives no wiring).
DEFAULT_INPUTS: Mapping[str, int] = MappingProxyType(
    {name: i for i, name in enumerate(n for n, s in SIGNALS.items() if s.kind == INPUT)}
)

#: Modbus exception codes and their names (Modbus application protocol v1.1b3, 7).
MODBUS_EXCEPTIONS: Mapping[int, str] = MappingProxyType(
    {
        1: "illegal function",
        2: "illegal data address",
        3: "illegal data value",
        4: "server device failure",
        5: "acknowledge",
        6: "server device busy",
        8: "memory parity error",
        10: "gateway path unavailable",
        11: "gateway target device failed to respond",
    }
)


@dataclass(frozen=True)
class PlcTiming:
    """How long the PLC's machinery takes, in machine seconds (all **assumed**; the source
    gives none). The PLC emulator runs on it (divided by its time scale) and the cell's
    physical bound (:mod:`cellctl.cell.estimate`) counts with it."""

    conveyor_s: float = 8.0  # a requested pallet reaches the pick-up
    release_s: float = 3.0  # a released pallet leaves the pick-up
    outfeed_s: float = 5.0  # the outfeed carries a part or pallet off
    clamp_s: float = 0.5  # a vise reaches the position its coil asks for
    door_s: float = 2.0  # a door travels from one end position to the other


@dataclass(frozen=True)
class RobotWiring:
    """Which PLC signals the robot's digital lines are tied to (the example cell's wiring,
    as its AML programs expect it; **assumed**, the source gives none)."""

    #: PLC input -> robot input line that follows it.
    inputs: Mapping[str, int]
    #: PLC input -> robot input line that follows its negation.
    inverted: Mapping[str, int]
    #: Robot output -> the mill whose vise coil (``clamp_N``) it drives.
    vise_outputs: Mapping[int, int]
    blank_taken_output: int  # lifts the blank off its pallet
    part_placed_output: int  # fills the outfeed

    def input_of(self, port: int) -> tuple[str, bool] | None:
        """The PLC input behind robot input ``port`` and whether it is inverted."""
        for name, line in self.inputs.items():
            if line == port:
                return name, False
        for name, line in self.inverted.items():
            if line == port:
                return name, True
        return None


#: The example cell's wiring (examples/cell/robot/*.aml say the same in their comments).
EXAMPLE_WIRING = RobotWiring(
    inputs=MappingProxyType(
        {
            "pallet_present": 1,
            "door_open_1": 2,
            "clamp_closed_1": 4,
            "door_open_2": 5,
            "clamp_closed_2": 7,
            "outfeed_clear": 8,
        }
    ),
    inverted=MappingProxyType({"clamp_closed_1": 3, "clamp_closed_2": 6}),
    vise_outputs=MappingProxyType({1: 1, 2: 2}),
    blank_taken_output=7,
    part_placed_output=5,
)

_MEM_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")

# "clamp[1]" and "clamp1" both mean "clamp_1".
_INDEXED = re.compile(r"^([a-z_]*[a-z])(?:\[(\d+)\]|(\d+))$")


def canonical(name: str) -> str:
    """``"clamp[1]"``, ``"clamp1"`` -> ``"clamp_1"``; other names unchanged (stripped)."""
    name = name.strip()
    m = _INDEXED.match(name)
    return f"{m.group(1)}_{m.group(2) or m.group(3)}" if m else name


def signal_name(base: str, mill: int) -> str:
    """``signal_name("door_open", 2)`` -> ``"door_open_2"``; refuses a mill other than 1, 2."""
    if mill not in MILLS:
        raise UsageError(f"mill number must be 1 or 2, not {mill}")
    name = f"{base}_{mill}"
    if name not in SIGNALS:
        raise UsageError(f"no PLC signal {name!r}")
    return name


def describe(name: str) -> str:
    """What signal ``name`` means, in words."""
    return SIGNALS[canonical(name)].meaning


def parse_modbus_url(url: str) -> tuple[str, int]:
    """``"modbus://10.0.0.5:5020"`` -> ``("10.0.0.5", 5020)``; port 502 if left out."""
    parts = urlsplit(url)
    if parts.scheme not in ("modbus", "tcp") or not parts.hostname:
        raise UsageError(f"PLC address {url!r}: write modbus://HOST[:PORT]")
    try:
        port = parts.port
    except ValueError:
        raise UsageError(f"PLC address {url!r}: the port is not a number 0..65535") from None
    return parts.hostname, MODBUS_PORT if port is None else port


def plc_mem_name(url: str) -> str | None:
    """``"mem://plc"`` -> ``"plc"``: a PLC in the same event loop (the in-process Modbus/TCP
    pair, :mod:`cellctl.protocol.modbus` over a ``mem://`` line); None for any other URL."""
    scheme, sep, name = url.partition("://")
    if scheme != "mem" or not sep:
        return None
    if not _MEM_NAME.fullmatch(name):
        raise UsageError(f"PLC address {url!r}: a mem:// name is letters, digits, '.', '_' and '-'")
    return name


def check_plc_url(url: str) -> None:
    """Refuse a PLC URL that is neither ``modbus://HOST[:PORT]`` nor ``mem://NAME``."""
    if plc_mem_name(url) is None:
        parse_modbus_url(url)


def _addresses(table: object, kind: str, defaults: Mapping[str, int]) -> dict[str, int]:
    """Check one ``coils``/``inputs`` table: known names, int addresses, no duplicates."""
    key = "coils" if kind == COIL else "inputs"
    if table is None:
        return dict(defaults)
    if not isinstance(table, Mapping):
        raise UsageError(f"[plc] {key}: expected a table of NAME = ADDRESS")
    out: dict[str, int] = {}
    seen: dict[int, str] = {}
    for raw, address in table.items():
        name = canonical(str(raw))
        sig = SIGNALS.get(name)
        if sig is None or sig.kind != kind:
            known = ", ".join(n for n, s in SIGNALS.items() if s.kind == kind)
            other = " (that is a coil)" if sig is not None and kind == INPUT else ""
            other = " (that is an input)" if sig is not None and kind == COIL else other
            raise UsageError(f"[plc] {key}.{raw}: unknown {kind}{other}; known: {known}")
        if name in out:
            raise UsageError(f"[plc] {key}.{raw}: given twice")
        if isinstance(address, bool) or not isinstance(address, int) or not 0 <= address <= 65535:
            raise UsageError(f"[plc] {key}.{raw}: address must be 0..65535, not {address!r}")
        if address in seen:
            raise UsageError(
                f"[plc] {key}.{raw}: address {address} is already {key}.{seen[address]}"
            )
        seen[address] = name
        out[name] = address
    required = [n for n, s in SIGNALS.items() if s.kind == kind and n not in OPTIONAL_INPUTS]
    missing = [n for n in required if n not in out]
    if missing:
        raise UsageError(f"[plc] {key}: missing {', '.join(missing)}")
    return out


_TOP_KEYS = ("url", "unit", "timeout", "poll", "coils", "inputs")


@dataclass(frozen=True)
class PlcMap:
    """Where the PLC is and which address each signal has (defaults **assumed**).

    ``coils`` and ``inputs`` map signal names (see :data:`SIGNALS`) to Modbus addresses;
    an optional input left out of ``inputs`` is not wired. ``timeout`` bounds each request,
    ``poll`` is the period of reads while waiting for an input.
    """

    url: str = DEFAULT_URL
    unit: int = 1
    coils: Mapping[str, int] = field(default_factory=lambda: dict(DEFAULT_COILS))
    inputs: Mapping[str, int] = field(default_factory=lambda: dict(DEFAULT_INPUTS))
    timeout: float = 1.0
    poll: float = 0.05

    @classmethod
    def from_toml(cls, table: Mapping[str, Any]) -> PlcMap:
        """Read the ``[plc]`` table of ``cell.toml``; :class:`UsageError` names a bad key."""
        if not isinstance(table, Mapping):
            raise UsageError("[plc]: expected a table")
        for key in table:
            if key not in _TOP_KEYS:
                raise UsageError(f"[plc] {key}: unknown key; known: {', '.join(_TOP_KEYS)}")
        url = table.get("url", DEFAULT_URL)
        if not isinstance(url, str):
            raise UsageError(f"[plc] url: expected a string, not {url!r}")
        check_plc_url(url)
        unit = table.get("unit", 1)
        if isinstance(unit, bool) or not isinstance(unit, int) or not 0 <= unit <= 255:
            raise UsageError(f"[plc] unit: must be 0..255, not {unit!r}")
        numbers: dict[str, float] = {}
        for key, default in (("timeout", 1.0), ("poll", 0.05)):
            value = table.get(key, default)
            if isinstance(value, bool) or not isinstance(value, int | float) or value <= 0:
                raise UsageError(f"[plc] {key}: must be seconds > 0, not {value!r}")
            numbers[key] = float(value)
        plc_map = cls(
            url=url,
            unit=unit,
            coils=_addresses(table.get("coils"), COIL, DEFAULT_COILS),
            inputs=_addresses(table.get("inputs"), INPUT, DEFAULT_INPUTS),
            timeout=numbers["timeout"],
            poll=numbers["poll"],
        )
        first, count = plc_map.input_block
        if count > MAX_READ_BITS:
            raise UsageError(
                f"[plc] inputs: addresses {first}..{first + count - 1} span more than "
                f"{MAX_READ_BITS}, too many for one Modbus read"
            )
        return plc_map

    @property
    def input_block(self) -> tuple[int, int]:
        """(first address, count) of the one read that covers every mapped input."""
        if not self.inputs:
            return 0, 0
        low, high = min(self.inputs.values()), max(self.inputs.values())
        return low, high - low + 1

    @property
    def coil_block(self) -> tuple[int, int]:
        """(first address, count) of the one read that covers every mapped coil."""
        if not self.coils:
            return 0, 0
        low, high = min(self.coils.values()), max(self.coils.values())
        return low, high - low + 1

    def kind_of(self, name: str) -> Literal["coil", "input"]:
        """``"coil"`` or ``"input"`` for a mapped signal; :class:`UsageError` otherwise."""
        name = canonical(name)
        sig = SIGNALS.get(name)
        if sig is None:
            raise UsageError(f"no PLC signal {name!r}; known: {', '.join(SIGNALS)}")
        table = self.coils if sig.kind == COIL else self.inputs
        if name not in table:
            raise UsageError(f"PLC signal {name!r} is not wired in this cell's [plc] map")
        return sig.kind

    def address(self, name: str) -> int:
        """The Modbus address of a mapped signal (coil or input by its name)."""
        name = canonical(name)
        kind = self.kind_of(name)
        return (self.coils if kind == COIL else self.inputs)[name]
