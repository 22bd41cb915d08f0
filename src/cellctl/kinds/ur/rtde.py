"""RTDE (Real-Time Data Exchange, the controller's port 30004): packets as bytes, no I/O.

Every packet is a header and a payload, big-endian::

    uint16 size (header included) | uint8 type | payload

Types (one byte, an ASCII letter): ``V`` request protocol version, ``v`` get URControl
version, ``M`` text message, ``U`` data package, ``O`` setup outputs, ``I`` setup inputs,
``S`` start, ``P`` pause. A session negotiates the protocol version (2, else 1), may ask the
controller's version, sets up an output recipe (version 2: a frequency, then the field names,
comma-separated) and input recipes, then starts: the controller sends a data package of the
output recipe at that frequency, and takes data packages of an input recipe from the host.
In version 2 a data package starts with its recipe id::

    packet = encode(PacketType.SETUP_OUTPUTS, setup_outputs_payload(125.0, ["actual_q"]))
    packet_type, payload, used = decode(buffer)        # used == 0: need more bytes
    recipe = parse_setup_outputs_reply(payload)        # id 1, ("VECTOR6D",)
    values = unpack_data(recipe, data_payload)         # {"actual_q": (0.0, ...)}

The field names and types the emulator offers are one table, :data:`OUTPUTS` and
:data:`INPUTS`; the types' wire formats another, :data:`TYPES`. Anything that does not
follow the protocol is a :class:`~cellctl.errors.ProtocolError` carrying its bytes.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from cellctl.errors import ProtocolError

HEADER = struct.Struct(">HB")
#: The largest packet a uint16 size allows.
MAX_PACKET = 0xFFFF
#: The protocol versions a controller speaks (PolyScope 3.3 and later speak 2).
PROTOCOL_VERSIONS = (1, 2)
#: Output frequencies: CB3 at most 125 Hz, e-Series at most 500 Hz.
MAX_FREQUENCY_CB3 = 125.0
MAX_FREQUENCY_E_SERIES = 500.0


class PacketType(enum.IntEnum):
    """The packet types, by their letter."""

    REQUEST_PROTOCOL_VERSION = ord("V")
    GET_URCONTROL_VERSION = ord("v")
    TEXT_MESSAGE = ord("M")
    DATA_PACKAGE = ord("U")
    SETUP_OUTPUTS = ord("O")
    SETUP_INPUTS = ord("I")
    START = ord("S")
    PAUSE = ord("P")


#: Field type -> struct format (big-endian) of its value.
TYPES: dict[str, str] = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
#: What a recipe answers for a name the controller does not have / an input someone else holds.
NOT_FOUND = "NOT_FOUND"
IN_USE = "IN_USE"


def _registers(prefix: str, kind: str) -> dict[str, str]:
    return {f"{prefix}_{n}": kind for n in range(48)}


#: The output fields the emulator offers (a subset of the controller's), name -> type.
OUTPUTS: dict[str, str] = {
    "timestamp": "DOUBLE",
    "target_q": "VECTOR6D",
    "target_qd": "VECTOR6D",
    "actual_q": "VECTOR6D",
    "actual_qd": "VECTOR6D",
    "actual_TCP_pose": "VECTOR6D",
    "target_TCP_pose": "VECTOR6D",
    "actual_TCP_speed": "VECTOR6D",
    "joint_mode": "VECTOR6INT32",
    "robot_mode": "INT32",
    "safety_mode": "INT32",
    "safety_status": "INT32",
    "runtime_state": "UINT32",
    "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32",
    "actual_digital_input_bits": "UINT64",
    "actual_digital_output_bits": "UINT64",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
    "actual_execution_time": "DOUBLE",
    "output_bit_registers0_to_31": "UINT32",
    "output_bit_registers32_to_63": "UINT32",
    **_registers("output_int_register", "INT32"),
    **_registers("output_double_register", "DOUBLE"),
}
#: The input fields the emulator takes, name -> type.
INPUTS: dict[str, str] = {
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    **_registers("input_int_register", "INT32"),
    **_registers("input_double_register", "DOUBLE"),
}


# -- framing --------------------------------------------------------------------------------------


def encode(packet_type: int, payload: bytes = b"") -> bytes:
    """One packet: header and ``payload``."""
    size = HEADER.size + len(payload)
    if size > MAX_PACKET:
        raise ProtocolError(f"RTDE packet of {size} bytes: at most {MAX_PACKET}")
    return HEADER.pack(size, packet_type) + payload


def decode(data: bytes | bytearray) -> tuple[int, bytes, int]:
    """The first packet of ``data``: ``(type, payload, bytes used)``; used 0: need more.

    A size below the header's own is a ProtocolError with the bytes.
    """
    if len(data) < HEADER.size:
        return 0, b"", 0
    size, packet_type = HEADER.unpack_from(data)
    if size < HEADER.size:
        raise ProtocolError(f"RTDE packet size {size} is below its header's", bytes(data[:8]))
    if len(data) < size:
        return 0, b"", 0
    return packet_type, bytes(data[HEADER.size : size]), size


# -- the handshake --------------------------------------------------------------------------------


def request_protocol_version(version: int) -> bytes:
    """Payload of ``V`` from the host: the version it wants."""
    return struct.pack(">H", version)


def parse_request_protocol_version(payload: bytes) -> int:
    return int(_unpack(">H", payload, "protocol version request")[0])


def protocol_version_reply(accepted: bool) -> bytes:
    return struct.pack(">B", int(accepted))


def parse_protocol_version_reply(payload: bytes) -> bool:
    return bool(_unpack(">B", payload, "protocol version reply")[0])


@dataclass(frozen=True)
class ControllerVersion:
    """URControl's version: major 3 is a CB3, 5 an e-Series."""

    major: int
    minor: int
    bugfix: int
    build: int

    def __str__(self) -> str:
        return f"{self.major}.{self.minor}.{self.bugfix}.{self.build}"

    @property
    def e_series(self) -> bool:
        return self.major >= 5

    @property
    def max_frequency(self) -> float:
        return MAX_FREQUENCY_E_SERIES if self.e_series else MAX_FREQUENCY_CB3


def controller_version_reply(version: ControllerVersion) -> bytes:
    return struct.pack(">IIII", version.major, version.minor, version.bugfix, version.build)


def parse_controller_version_reply(payload: bytes) -> ControllerVersion:
    return ControllerVersion(*_unpack(">IIII", payload, "controller version"))


# -- recipes --------------------------------------------------------------------------------------


def setup_outputs_payload(frequency: float | None, names: Sequence[str]) -> bytes:
    """Payload of ``O`` from the host: version 2 gives a frequency, version 1 none."""
    text = ",".join(names).encode("ascii")
    return (b"" if frequency is None else struct.pack(">d", frequency)) + text


def parse_setup_outputs(payload: bytes, version: int) -> tuple[float | None, list[str]]:
    """What the host asked in ``O``: its frequency (None in version 1) and field names."""
    frequency = None
    if version >= 2:
        frequency = _unpack(">d", payload[:8], "output setup frequency")[0]
        payload = payload[8:]
    return frequency, _names(payload)


def setup_inputs_payload(names: Sequence[str]) -> bytes:
    return ",".join(names).encode("ascii")


def parse_setup_inputs(payload: bytes) -> list[str]:
    return _names(payload)


@dataclass(frozen=True)
class Recipe:
    """A recipe as the controller answered it: its id, its fields and their types."""

    recipe_id: int
    names: tuple[str, ...]
    types: tuple[str, ...]

    @property
    def ok(self) -> bool:
        """Every field known and free: the controller will stream (or take) it."""
        return all(t in TYPES for t in self.types)

    def refused(self) -> list[str]:
        """The fields the controller refused, with why (``NOT_FOUND``, ``IN_USE``)."""
        return [
            f"{n} ({t})" for n, t in zip(self.names, self.types, strict=False) if t not in TYPES
        ]

    @property
    def size(self) -> int:
        return struct.calcsize(_format(self.types)) if self.ok else 0


def recipe_for(
    recipe_id: int,
    names: Sequence[str],
    table: Mapping[str, str],
    in_use: frozenset[str] = frozenset(),
) -> Recipe:
    """The controller's answer to a recipe of ``names`` from its ``table`` of fields."""
    types = tuple(IN_USE if n in in_use else table.get(n, NOT_FOUND) for n in names)
    return Recipe(recipe_id, tuple(names), types)


def setup_reply(recipe: Recipe, version: int) -> bytes:
    """The controller's answer to ``O`` or ``I``: (version 2) the recipe id, then the types."""
    head = struct.pack(">B", recipe.recipe_id) if version >= 2 else b""
    return head + ",".join(recipe.types).encode("ascii")


def parse_setup_reply(payload: bytes, names: Sequence[str], version: int = 2) -> Recipe:
    """The recipe the controller answered for ``names``."""
    recipe_id = 0
    if version >= 2:
        if not payload:
            raise ProtocolError("RTDE setup reply without its recipe id", payload)
        recipe_id, payload = payload[0], payload[1:]
    types = tuple(_names(payload))
    if len(types) != len(names):
        raise ProtocolError(
            f"RTDE setup reply has {len(types)} types for {len(names)} fields", payload
        )
    return Recipe(recipe_id, tuple(names), types)


def start_reply(accepted: bool) -> bytes:
    return struct.pack(">B", int(accepted))


def parse_start_reply(payload: bytes) -> bool:
    return bool(_unpack(">B", payload, "start/pause reply")[0])


# -- data packages --------------------------------------------------------------------------------


def _format(types: Sequence[str]) -> str:
    return ">" + "".join(TYPES[t] for t in types)


def pack_data(recipe: Recipe, values: Mapping[str, Any], version: int = 2) -> bytes:
    """A data package's payload: (version 2) the recipe id, then each field's value."""
    flat: list[Any] = []
    for name, kind in zip(recipe.names, recipe.types, strict=True):
        value = values[name]
        if kind.startswith("VECTOR"):
            flat.extend(value)
        else:
            flat.append(value)
    head = struct.pack(">B", recipe.recipe_id) if version >= 2 else b""
    try:
        return head + struct.pack(_format(recipe.types), *flat)
    except struct.error as e:
        raise ProtocolError(f"RTDE data package does not fit its recipe: {e}") from None


def unpack_data(recipe: Recipe, payload: bytes, version: int = 2) -> dict[str, Any]:
    """A data package's values by field name (vectors as tuples)."""
    if version >= 2:
        if not payload or payload[0] != recipe.recipe_id:
            got = payload[0] if payload else None
            raise ProtocolError(
                f"RTDE data package of recipe {got}, expected {recipe.recipe_id}", payload[:16]
            )
        payload = payload[1:]
    fmt = _format(recipe.types)
    if len(payload) != struct.calcsize(fmt):
        raise ProtocolError(
            f"RTDE data package of {len(payload)} bytes, its recipe takes {struct.calcsize(fmt)}",
            payload[:32],
        )
    flat = list(struct.unpack(fmt, payload))
    out: dict[str, Any] = {}
    for name, kind in zip(recipe.names, recipe.types, strict=True):
        count = int(TYPES[kind][0]) if TYPES[kind][0].isdigit() else 1
        if count > 1:
            out[name], flat = tuple(flat[:count]), flat[count:]
        else:
            out[name], flat = flat[0], flat[1:]
    return out


# -- text messages --------------------------------------------------------------------------------

#: Text message levels (version 2).
EXCEPTION, ERROR, WARNING, INFO = 0, 1, 2, 3


def text_message(message: str, source: str = "RTDE", level: int = ERROR) -> bytes:
    """A controller's text message (version 2): message, source, level."""
    m = message.encode("utf-8")[:255]
    s = source.encode("utf-8")[:255]
    return bytes([len(m)]) + m + bytes([len(s)]) + s + bytes([level])


def parse_text_message(payload: bytes) -> tuple[str, str, int]:
    """``(message, source, level)`` of a version 2 text message."""
    try:
        n = payload[0]
        message = payload[1 : 1 + n]
        m = payload[1 + n]
        source = payload[2 + n : 2 + n + m]
        level = payload[2 + n + m]
    except IndexError:
        raise ProtocolError("RTDE text message cut short", payload) from None
    return message.decode("utf-8", "replace"), source.decode("utf-8", "replace"), level


def _unpack(fmt: str, payload: bytes, what: str) -> tuple[Any, ...]:
    if len(payload) != struct.calcsize(fmt):
        raise ProtocolError(f"RTDE {what}: {len(payload)} bytes", payload[:32])
    return struct.unpack(fmt, payload)


def _names(payload: bytes) -> list[str]:
    try:
        text = payload.decode("ascii")
    except UnicodeDecodeError:
        raise ProtocolError("RTDE field names are not ASCII", payload[:64]) from None
    return [n.strip() for n in text.split(",") if n.strip()]
