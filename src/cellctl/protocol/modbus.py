"""Modbus/TCP application data units (ADUs): the frames of the cell PLC's protocol. No I/O.

What the cell's PLC speaks (Modbus application protocol v1.1b3, Modbus messaging on TCP/IP
v1.0b): an MBAP header (transaction id, protocol id 0, length, unit id) and a PDU of one of
the three functions the controller uses, 01 Read Coils, 02 Read Discrete Inputs and
05 Write Single Coil, or an exception response (function code + 0x80, exception code)::

    frame = encode_read(7, unit=1, function=READ_DISCRETE_INPUTS, address=0, count=12)
    reader = AduReader()
    for adu in reader.feed(frame):                     # whole ADUs, however the bytes came
        request = decode_request(adu)                  # IllegalRequest: answer its .code
        reply = encode_bits_response(adu.transaction, adu.unit, request.function, bits)
    response = decode_response(next(iter(AduReader().feed(reply))), request)
    response.bits                                      # (True, False, ...), request.count long

The in-process PLC (``[plc] url = "mem://NAME"``) carries these frames over a ``mem://``
line between :class:`cellctl.drivers.plc.ModbusPlc` and
:class:`cellctl.emulators.plc.PlcEmulator`; over real TCP pymodbus does the same framing.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from cellctl.errors import FramingError, ProtocolError, UnexpectedReply

__all__ = [
    "FUNCTIONS",
    "MAX_ADU",
    "MAX_READ_BITS",
    "MBAP_SIZE",
    "READ_COILS",
    "READ_DISCRETE_INPUTS",
    "WRITE_SINGLE_COIL",
    "Adu",
    "AduReader",
    "IllegalRequest",
    "Request",
    "Response",
    "decode_request",
    "decode_response",
    "encode_bits_response",
    "encode_exception",
    "encode_read",
    "encode_write_coil",
    "encode_write_coil_response",
]

READ_COILS = 0x01
READ_DISCRETE_INPUTS = 0x02
WRITE_SINGLE_COIL = 0x05

#: The functions this codec knows, by code: what a request of it does.
FUNCTIONS: Mapping[int, str] = MappingProxyType(
    {
        READ_COILS: "read coils",
        READ_DISCRETE_INPUTS: "read discrete inputs",
        WRITE_SINGLE_COIL: "write single coil",
    }
)

#: MBAP header: transaction id, protocol id, length (of unit id + PDU), unit id.
MBAP_SIZE = 7
_MBAP = struct.Struct(">HHHB")
#: A PDU is at most 253 bytes; an ADU on TCP at most 260.
MAX_PDU = 253
MAX_ADU = MBAP_SIZE + MAX_PDU
#: The most bits one read may ask for (01 and 02: 1..2000).
MAX_READ_BITS = 2000
#: Write Single Coil's two values: ON and OFF (any other is illegal data value, 03).
COIL_ON = 0xFF00
COIL_OFF = 0x0000
_EXCEPTION = 0x80

# Exception codes the server answers with (names in cellctl.protocol.plc.MODBUS_EXCEPTIONS).
ILLEGAL_FUNCTION = 1
ILLEGAL_DATA_ADDRESS = 2
ILLEGAL_DATA_VALUE = 3


@dataclass(frozen=True)
class Adu:
    """One Modbus/TCP frame: its MBAP fields and its PDU (function code first)."""

    transaction: int
    unit: int
    pdu: bytes

    def encode(self) -> bytes:
        """The frame's bytes."""
        return _frame(self.transaction, self.unit, self.pdu)

    @property
    def function(self) -> int:
        """The PDU's function code (0x80 set on an exception response)."""
        return self.pdu[0]


def _frame(transaction: int, unit: int, pdu: bytes) -> bytes:
    if not 0 <= transaction <= 0xFFFF or not 0 <= unit <= 0xFF:
        raise ValueError(f"transaction id 0..65535 and unit 0..255, not {transaction}, {unit}")
    if not 1 <= len(pdu) <= MAX_PDU:
        raise ValueError(f"a PDU is 1..{MAX_PDU} bytes, not {len(pdu)}")
    return _MBAP.pack(transaction, 0, len(pdu) + 1, unit) + pdu


class AduReader:
    """Cuts a byte stream into ADUs (feed it whatever arrived; a frame may span feeds).

    Raises :class:`FramingError` with the header's bytes for a frame that cannot be
    Modbus/TCP (protocol id other than 0, a length outside 2..254): the stream cannot be
    resynchronised after that, so the connection must be closed.
    """

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[Adu]:
        """The whole ADUs ``data`` completes, in order (the rest is kept for the next feed)."""
        self._buf += data
        out: list[Adu] = []
        buf = self._buf
        while len(buf) >= MBAP_SIZE:
            transaction, protocol, length, unit = _MBAP.unpack_from(buf)
            if protocol != 0 or not 2 <= length <= MAX_PDU + 1:
                raw = bytes(buf[:MBAP_SIZE])
                buf.clear()
                raise FramingError(
                    f"not a Modbus/TCP frame (protocol id {protocol}, length {length})", raw
                )
            end = MBAP_SIZE - 1 + length
            if len(buf) < end:
                break
            out.append(Adu(transaction, unit, bytes(buf[MBAP_SIZE:end])))
            del buf[:end]
        return out

    @property
    def pending(self) -> bytes:
        """Bytes of a frame not complete yet."""
        return bytes(self._buf)


# -- requests ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Request:
    """A request the controller sends: a read of ``count`` bits from ``address`` (01, 02), or
    a write of ``value`` to coil ``address`` (05; ``count`` 1)."""

    transaction: int
    unit: int
    function: int
    address: int
    count: int = 1
    value: bool = False

    def describe(self) -> str:
        """The request in words (for messages)."""
        if self.function == WRITE_SINGLE_COIL:
            return f"write coil {self.address} = {int(self.value)}"
        return f"{FUNCTIONS[self.function]} {self.address}..{self.address + self.count - 1}"


class IllegalRequest(ProtocolError):
    """A request the server refuses: ``code`` is the exception code to answer with."""

    def __init__(self, message: str, code: int, function: int, raw: bytes = b"") -> None:
        super().__init__(message, raw)
        self.code = code
        self.function = function


def _check_address(address: int, count: int) -> None:
    if not 0 <= address <= 0xFFFF:
        raise ValueError(f"address must be 0..65535, not {address}")
    if not 1 <= count <= MAX_READ_BITS or address + count > 0x10000:
        raise ValueError(f"a read takes 1..{MAX_READ_BITS} bits within 0..65535, not {count}")


def encode_read(transaction: int, unit: int, function: int, address: int, count: int) -> bytes:
    """A Read Coils (01) or Read Discrete Inputs (02) request."""
    if function not in (READ_COILS, READ_DISCRETE_INPUTS):
        raise ValueError(f"not a read function: {function}")
    _check_address(address, count)
    return _frame(transaction, unit, struct.pack(">BHH", function, address, count))


def encode_write_coil(transaction: int, unit: int, address: int, value: bool) -> bytes:
    """A Write Single Coil (05) request."""
    _check_address(address, 1)
    word = COIL_ON if value else COIL_OFF
    return _frame(transaction, unit, struct.pack(">BHH", WRITE_SINGLE_COIL, address, word))


def decode_request(adu: Adu) -> Request:
    """What ``adu`` asks; :class:`IllegalRequest` (with the exception code to answer) for a
    function this codec does not serve or a malformed one."""
    pdu = adu.pdu
    function = pdu[0]
    if function not in FUNCTIONS:
        raise IllegalRequest(
            f"Modbus function {function} is not served", ILLEGAL_FUNCTION, function, pdu
        )
    if len(pdu) != 5:
        raise IllegalRequest(
            f"{FUNCTIONS[function]}: a request is 5 bytes, not {len(pdu)}",
            ILLEGAL_DATA_VALUE,
            function,
            pdu,
        )
    _, address, word = struct.unpack(">BHH", pdu)
    if function == WRITE_SINGLE_COIL:
        if word not in (COIL_ON, COIL_OFF):
            raise IllegalRequest(
                f"write single coil: value {word:#06x} is neither ON nor OFF",
                ILLEGAL_DATA_VALUE,
                function,
                pdu,
            )
        return Request(adu.transaction, adu.unit, function, address, 1, word == COIL_ON)
    if not 1 <= word <= MAX_READ_BITS:
        raise IllegalRequest(
            f"{FUNCTIONS[function]}: count {word} is not 1..{MAX_READ_BITS}",
            ILLEGAL_DATA_VALUE,
            function,
            pdu,
        )
    if address + word > 0x10000:
        raise IllegalRequest(
            f"{FUNCTIONS[function]}: {address}+{word} runs past address 65535",
            ILLEGAL_DATA_ADDRESS,
            function,
            pdu,
        )
    return Request(adu.transaction, adu.unit, function, address, word)


# -- responses -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Response:
    """A server's answer: ``bits`` for a read, ``value`` echoed for a write, or an exception
    (``exception`` its code, nothing else set)."""

    transaction: int
    unit: int
    function: int
    bits: tuple[bool, ...] = ()
    value: bool = False
    exception: int | None = None

    def isError(self) -> bool:  # pymodbus's name: the driver asks any response this
        """True for an exception response (what the driver asks of any response)."""
        return self.exception is not None

    @property
    def exception_code(self) -> int:
        """The exception code (0 when this is not an exception response)."""
        return self.exception or 0


def _pack_bits(bits: tuple[bool, ...] | list[bool]) -> bytes:
    out = bytearray((len(bits) + 7) // 8)
    for i, bit in enumerate(bits):
        if bit:
            out[i // 8] |= 1 << (i % 8)
    return bytes(out)


def encode_bits_response(
    transaction: int, unit: int, function: int, bits: tuple[bool, ...] | list[bool]
) -> bytes:
    """The answer to a read (01/02): byte count, then the bits, first bit in the lowest bit."""
    if function not in (READ_COILS, READ_DISCRETE_INPUTS):
        raise ValueError(f"not a read function: {function}")
    if not 1 <= len(bits) <= MAX_READ_BITS:
        raise ValueError(f"a read answers 1..{MAX_READ_BITS} bits, not {len(bits)}")
    packed = _pack_bits(bits)
    return _frame(transaction, unit, bytes((function, len(packed))) + packed)


def encode_write_coil_response(transaction: int, unit: int, address: int, value: bool) -> bytes:
    """The answer to Write Single Coil: the request echoed."""
    return encode_write_coil(transaction, unit, address, value)


def encode_exception(transaction: int, unit: int, function: int, code: int) -> bytes:
    """An exception response to ``function`` with exception ``code``."""
    if not 0 < function < _EXCEPTION or not 0 < code <= 0xFF:
        raise ValueError(f"function 1..127 and code 1..255, not {function}, {code}")
    return _frame(transaction, unit, bytes((function | _EXCEPTION, code)))


def decode_response(adu: Adu, request: Request) -> Response:
    """The answer ``adu`` gives to ``request``.

    Raises :class:`UnexpectedReply` (with the PDU's bytes) for an answer to another
    transaction or function, :class:`FramingError` for a malformed one.
    """
    pdu = adu.pdu
    if adu.transaction != request.transaction:
        raise UnexpectedReply(
            f"answer to transaction {adu.transaction}, expected {request.transaction}", pdu
        )
    function = pdu[0]
    if function == request.function | _EXCEPTION:
        if len(pdu) != 2:
            raise FramingError("an exception response is 2 bytes", pdu)
        return Response(adu.transaction, adu.unit, request.function, exception=pdu[1])
    if function != request.function:
        raise UnexpectedReply(
            f"answer with function {function} to a {FUNCTIONS[request.function]} request", pdu
        )
    if function == WRITE_SINGLE_COIL:
        expected = encode_write_coil(0, 0, request.address, request.value)[MBAP_SIZE:]
        if pdu != expected:
            raise UnexpectedReply("write single coil: the answer does not echo the request", pdu)
        return Response(adu.transaction, adu.unit, function, value=request.value)
    size = (request.count + 7) // 8
    if len(pdu) != 2 + size or pdu[1] != size:
        raise FramingError(
            f"{FUNCTIONS[function]}: {request.count} bits take {size} bytes, "
            f"the answer has {len(pdu) - 2} (byte count {pdu[1] if len(pdu) > 1 else '-'})",
            pdu,
        )
    data = pdu[2:]
    bits = tuple(bool(data[i // 8] >> (i % 8) & 1) for i in range(request.count))
    return Response(adu.transaction, adu.unit, function, bits=bits)
