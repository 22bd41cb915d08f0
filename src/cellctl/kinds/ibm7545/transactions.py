"""The IBM 7545 controller's transactions on the line: the base of :class:`Ibm7545Robot`.

:class:`RobotTransactions` opens X and R transactions, waits through the controller's Xoffs,
reads its D and EG records and turns an EOT into the reject it stands for; the driver
(:mod:`cellctl.kinds.ibm7545.driver`) inherits it and says what to send. Spec
``ibm7545-robot.md``; host controls every transaction::

    X  -> Xoff [Xoff ...] Xon   operand CR LF -> Ack    (or Xoff [Xoff ...] Xon: 11, 23)
    R  -> Xoff [Xoff ...] Xon   operand CR LF -> D record, Ack -> EG, Ack
    N  -> Ack   rest of N record -> Ack   each record -> Ack   end record -> Ack

Every wait has a deadline: the first reply must come within ``reply_timeout`` (plus the wire
time of what was sent); while the controller is busy it repeats Xoff about every 25 s, and
each Xoff extends the wait, up to ``busy_ceiling`` in all; silence longer than
``busy_silence`` raises :class:`LinkTimeout`. EOT means the controller rejected the request:
the driver reads the reject status and raises :class:`DeviceError` with the source's words.
A D record with a bad checksum is acknowledged (so the controller finishes its transaction)
and the read is repeated, up to ``checksum_retries`` times; then :class:`ChecksumError`. A
garbled handshake (a byte other than Xoff, Xon or EOT where one belongs, before the operand
went out) is repeated the same way.

Before a retry the host sends a record the controller cannot take (``E`` CR LF), so whatever
it was receiving ends in a reject, and discards what comes back until the line is quiet.

A transaction cancelled half-way (Ctrl-C) would leave the controller waiting for the rest of
it, deaf to the next request: the host resyncs the same way before the cancellation goes on,
within a deadline. The driver saves that the line is out of step (a download from its first
byte; any transaction once cancelled) and clears it when the line is known to be in step
again, so a resync cut short (a second Ctrl-C, a killed process) is done before the next
transaction, by this driver or the next one to connect.

A reject does not change the host's state: the spec has no reject after which the controller
itself forgot its state or its partitions (48 "improper startup sequence" also answers a
request while a cycle runs).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from typing import NoReturn

from cellctl.drivers.base import LinkDriver
from cellctl.errors import (
    CellctlError,
    ChecksumError,
    DeviceError,
    FramingError,
    LinkTimeout,
    UnexpectedReply,
    format_raw,
)
from cellctl.kinds.ibm7545.options import RobotConfig
from cellctl.kinds.ibm7545.records import (
    ACK,
    EOT,
    XOFF,
    XON,
    ReadOperand,
    Record,
    decode_record,
    encode_operand,
    encode_record,
    reject_message,
    resync,
)
from cellctl.kinds.ibm7545.status import RobotCounters
from cellctl.link import ROBOT_LINE

#: Rejects that say the line garbled a download, not that the controller cannot take it:
#: 16 record format error (bad checksum, hex, count or terminator), 96 invalid identifier
#: (a garbled N), 112 Xoff time out (a lost terminator left it waiting), 0 no reject status
#: (the "EOT" was a garbled Ack). Only these are retried; 16 only while it moves: the host
#: decoded every record before sending, so a 16 is the line's, but the same record refused
#: twice is its content (the driver stops there).
TRANSMISSION_REJECTS = frozenset({0, 16, 96, 112})
#: Reject status "record format error".
RECORD_FORMAT_ERROR = 16
_ACK = bytes([ACK])
#: Sent before a retry: a record no controller state accepts, so a half-received record or
#: operand ends in a reject (EOT, discarded) and the controller waits for an identifier again.
_BREAK = b"E\r\n"
#: How long a resync may go on discarding a line that keeps talking, beyond the first answer.
_RESYNC_CHATTER_S = 1.0


class RobotTransactions(LinkDriver):
    """X, R and Ack exchanges with one controller, one at a time (``_lock``).

    The driver sets ``config``, ``counters``, ``_lock``, ``_in_reject_read`` and
    ``_out_of_step`` (from its saved state) and provides ``_save``.
    """

    config: RobotConfig
    counters: RobotCounters
    _lock: asyncio.Lock
    _in_reject_read: bool
    _out_of_step: bool

    def _save(self) -> None:
        """Save the host-kept state (``_out_of_step`` with it); the driver's."""
        raise NotImplementedError

    # -- keeping the line in step ---------------------------------------------------------------

    def _mark_out_of_step(self, value: bool) -> None:
        """Remember (saved) whether the controller may be half-way through a request."""
        if self._out_of_step != value:
            self._out_of_step = value
            self._save()

    @contextlib.asynccontextmanager
    async def _transaction(self) -> AsyncIterator[None]:
        """One transaction on the line: the lock, a resync first if the line is out of step,
        and a resync (with its deadline) if the caller cancels it half-way."""
        async with self._lock:
            if self._out_of_step and await self._resync():
                self._mark_out_of_step(False)
            try:
                yield
            except asyncio.CancelledError:
                self._mark_out_of_step(True)
                with contextlib.suppress(CellctlError):
                    if await self._resync():
                        self._mark_out_of_step(False)
                raise

    # -- low-level pieces --------------------------------------------------------------------------

    def _timeout(self, sent: int = 0, expect: int = 1) -> float:
        """Deadline for a reply: controller latency plus wire time both ways."""
        return self.config.reply_timeout + self.link.settings.wire_time(sent + expect)

    def _no_answer(self) -> str:
        """What a silent line says, and what to check, with the line settings in use (a
        wrong baud or parity is silence too: the controller takes no request from it)."""
        line = self.link.settings
        used = (
            f"{line}, the controller's default"
            if line == ROBOT_LINE
            else f"{line} here; the controller's default is {ROBOT_LINE}"
        )
        return (
            "no answer from the robot controller: check its power, the cable and the line "
            f"settings ({used}: cell.toml's line, or --line)"
        )

    async def _byte(self, timeout: float) -> int:
        return (await self.link.read(1, timeout=timeout))[0]

    async def _await_ready(self, what: str, first: int) -> None:
        """Having read ``first`` after an identifier, wait through Xoffs for Xon."""
        ceiling = self.clock.monotonic() + self.config.busy_ceiling
        byte = first
        while True:
            if byte == XON:
                return
            if byte == EOT:
                await self._rejected(what)
            if byte != XOFF:
                raise UnexpectedReply(
                    f"{self.name}: {what}: expected Xoff or Xon, got {byte:02X}", bytes([byte])
                )
            left = ceiling - self.clock.monotonic()
            if left <= 0:
                raise LinkTimeout(
                    f"{self.name}: {what}: controller stayed busy (Xoff) longer than "
                    f"{self.config.busy_ceiling:g} s"
                )
            try:
                byte = await self._byte(min(self.config.busy_silence, left))
            except LinkTimeout as e:
                raise LinkTimeout(
                    f"{self.name}: {what}: controller sent Xoff, then nothing for "
                    f"{min(self.config.busy_silence, left):g} s"
                ) from e

    async def _open_transaction(self, ident: bytes, what: str) -> None:
        """Send X or R and wait until the controller is ready (Xoff ... Xon)."""
        self.link.reset_input()
        await self.link.write(ident)
        self.counters.transactions += 1
        try:
            first = await self._byte(self._timeout(1))
        except LinkTimeout as e:
            raise LinkTimeout(f"{self.name}: {what}: {self._no_answer()}") from e
        if first not in (XOFF, EOT):
            raise UnexpectedReply(
                f"{self.name}: {what}: expected Xoff after {ident.decode()}, got {first:02X}",
                bytes([first]),
            )
        await self._await_ready(what, first)

    async def _execute(self, operand: int, what: str) -> None:
        """An X transaction: completes on Ack, or on Xoff ... Xon (return home, stop)."""
        async with self._transaction():
            await self._execute_unlocked(operand, what)

    async def _open_retrying(self, ident: bytes, what: str) -> None:
        """Open a transaction; a garbled handshake (before the operand) is tried again."""
        attempt = 0
        while True:
            try:
                await self._open_transaction(ident, what)
                return
            except UnexpectedReply:
                attempt += 1
                self.counters.handshake_retries += 1
                if attempt > self.config.checksum_retries:
                    raise
                await self._resync()

    async def _resync(self) -> bool:
        """End whatever the controller was receiving and discard its answer (see module
        docstring): wait for its first byte, then for ``retry_settle`` of quiet; all within
        the first answer's deadline and :data:`_RESYNC_CHATTER_S` (a line that keeps
        talking is left to the next transaction's own checks). True if the controller
        answered: it took the break, from any state, so it waits for an identifier now."""
        await self.link.write(_BREAK)
        timeout = self._timeout(len(_BREAK))
        deadline = self.clock.monotonic() + timeout + _RESYNC_CHATTER_S
        answered = False
        with contextlib.suppress(LinkTimeout):
            while (left := deadline - self.clock.monotonic()) > 0:
                await self.link.read(timeout=min(timeout, left))
                answered = True
                timeout = self.config.retry_settle
        self.link.reset_input()
        return answered

    async def _execute_unlocked(self, operand: int, what: str) -> None:
        record = encode_operand(operand)  # a bad operand is refused before X goes out
        await self._open_retrying(b"X", what)
        await self.link.write(record)
        try:
            byte = await self._byte(self._timeout(len(record)))
        except LinkTimeout as e:
            raise LinkTimeout(f"{self.name}: {what}: no Ack for operand {operand:02d}") from e
        if byte == ACK:
            return
        # Return home and stop answer Xoff at once, Xoff again while moving, Xon when done.
        await self._await_ready(what, byte)

    async def _read(self, operand: int, what: str, size: int) -> bytes:
        """An R transaction returning the D record's data (checksum verified, retried)."""
        async with self._transaction():
            return await self._read_unlocked(operand, what, size)

    async def _read_unlocked(self, operand: int, what: str, size: int) -> bytes:
        record_out = encode_operand(operand)  # a bad operand is refused before R goes out
        attempt = 0
        while True:
            await self._open_retrying(b"R", what)
            await self.link.write(record_out)
            record, raw_error = await self._read_data_record(what, size)
            await self.link.write(_ACK)
            await self._read_end_good(what)
            await self.link.write(_ACK)
            if raw_error is None:
                assert record is not None
                if len(record.data) != size:
                    raise UnexpectedReply(
                        f"{self.name}: {what}: expected {size} data bytes, got {len(record.data)}",
                        encode_record(record),
                    )
                return record.data
            attempt += 1
            self.counters.checksum_retries += 1
            if attempt > self.config.checksum_retries:
                raise ChecksumError(
                    f"{self.name}: {what}: transmission error, bad D-record checksum "
                    f"{attempt} times in a row",
                    raw_error.raw,
                )

    async def _read_data_record(
        self, what: str, size: int
    ) -> tuple[Record | None, ChecksumError | None]:
        buf = bytearray()
        timeout = self._timeout(4, 7 + 2 * size)
        deadline = self.clock.monotonic() + timeout
        while True:
            try:
                record, used = decode_record(buf)
            except ChecksumError as e:
                del buf[: resync(buf)]
                return None, e
            except FramingError as e:
                raise FramingError(f"{self.name}: {what}: malformed D record", e.raw) from e
            if used:
                skipped = bytes(buf[:used])
                del buf[:used]
                if record is None:
                    if EOT in skipped:
                        await self._rejected(what)
                    continue
                if record.ident != "D":
                    raise UnexpectedReply(
                        f"{self.name}: {what}: expected a D record", encode_record(record)
                    )
                return record, None
            left = deadline - self.clock.monotonic()
            try:
                buf += await self.link.read(timeout=max(left, 0.0))
            except LinkTimeout as e:
                got = f" (had {format_raw(bytes(buf))})" if buf else ""
                msg = f"{self.name}: {what}: no D record from the controller{got}"
                raise LinkTimeout(msg) from e

    async def _read_end_good(self, what: str) -> None:
        try:
            raw = await self.link.read_until(b"\n", timeout=self._timeout(1, 4))
        except LinkTimeout as e:
            raise LinkTimeout(f"{self.name}: {what}: no EG end record") from e
        record, _ = decode_record(raw.lstrip(b"\x00"))
        if record is None or not record.is_end_good:
            raise UnexpectedReply(f"{self.name}: {what}: expected EG (end, data good)", raw)

    async def _rejected(self, what: str) -> NoReturn:
        """The controller sent EOT: read the reject status and raise it."""
        if self._in_reject_read:
            raise DeviceError(0, "rejected while reading the reject status", detail=what)
        self._in_reject_read = True
        try:
            data = await self._read_unlocked(ReadOperand.REJECT_STATUS, "read reject status", 1)
            code = data[0]
        finally:
            self._in_reject_read = False
        self.counters.rejects.append(code)
        raise DeviceError(code, reject_message(code), detail=f"{self.name}: {what}")

    async def _expect_ack(self, piece: bytes, what: str) -> None:
        try:
            byte = await self._byte(self._timeout(len(piece)))
        except LinkTimeout as e:
            raise LinkTimeout(f"{self.name}: {what}: no Ack for record {piece[:24]!r}") from e
        if byte == ACK:
            return
        if byte == EOT:
            await self._rejected(what)
        raise UnexpectedReply(f"{self.name}: {what}: expected Ack, got {byte:02X}", bytes([byte]))


class _AckLost(LinkTimeout):
    """No Ack for a record after the controller had acknowledged earlier ones in the same
    download: a byte lost on the line, most likely (retried like a garbled one)."""


def _garbled(error: CellctlError) -> bool:
    """True if ``error`` says the line garbled a download (worth sending it again)."""
    if isinstance(error, DeviceError):
        return error.code in TRANSMISSION_REJECTS
    return isinstance(error, UnexpectedReply | _AckLost)
