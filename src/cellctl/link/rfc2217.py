"""RFC 2217 (Telnet COM port control) client: ``rfc2217://host:port``.

Device servers such as ser2net carry the serial line over Telnet and, unlike a raw TCP
server, also the line settings and the modem lines. This client is asyncio-native (one
protocol object per link, no reader thread) so a controller can hold many such links; the
option codes come from pyserial's ``serial.rfc2217``.

Open: Telnet BINARY, SGA and COM-PORT-OPTION are negotiated, then baud, data size, parity,
stop size and flow control are set and each answer awaited (a server that does not answer
is not an RFC 2217 server: LinkError). The modem state (CTS) arrives in NOTIFY-MODEMSTATE
messages, pushed by the server on change and polled by :meth:`Rfc2217Link.cts`. Bytes
that came during the negotiation are not read (they may be an earlier session's): they are
in ``opened_with``, for a driver that can tell.
"""

from __future__ import annotations

import asyncio
import struct

from serial import rfc2217 as r

from cellctl.clock import Clock
from cellctl.errors import LinkClosed, LinkError, LinkTimeout
from cellctl.link.settings import LineSettings
from cellctl.link.tcp import TcpLink
from cellctl.link.trace import TrafficLog

IAC, SB, SE = r.IAC[0], r.SB[0], r.SE[0]
WILL, WONT, DO, DONT = r.WILL[0], r.WONT[0], r.DO[0], r.DONT[0]
BINARY, SGA, ECHO, COM_PORT = r.BINARY[0], r.SGA[0], r.ECHO[0], r.COM_PORT_OPTION[0]

_WE_SUPPORT = {BINARY, SGA, COM_PORT}
_THEY_SUPPORT = {BINARY, SGA, COM_PORT, ECHO}
_PARITY = {"N": 1, "O": 2, "E": 3, "M": 4, "S": 5}
_STOPSIZE = {1: 1, 2: 2, 1.5: 3}
_SETTING_ANSWERS = {
    r.SERVER_SET_BAUDRATE[0]: "baud rate",
    r.SERVER_SET_DATASIZE[0]: "data size",
    r.SERVER_SET_PARITY[0]: "parity",
    r.SERVER_SET_STOPSIZE[0]: "stop size",
}

_NORMAL, _IAC, _NEGOTIATE, _SUB, _SUB_IAC = range(5)


class Rfc2217Link(TcpLink):
    """A serial line through an RFC 2217 server, with its modem lines."""

    has_modem_lines = True

    def __init__(
        self,
        url: str,
        settings: LineSettings,
        trace: TrafficLog | None,
        label: str,
        *,
        clock: Clock | None = None,
    ):
        super().__init__(url, settings, trace, label, clock=clock)
        self._mode = _NORMAL
        self._command = 0
        self._sub = bytearray()
        self._we: set[int] = set(_WE_SUPPORT)
        self._they: set[int] = set()
        self._refused: set[tuple[int, int]] = set()
        self._answered: set[int] = set()
        self.modem_state: int | None = None
        """Last modem state the server reported (MODEMSTATE_MASK_* bits), None before any."""
        self._modem_event = asyncio.Event()
        self.server_settings: dict[str, int] = {}
        self.opened_with = b""
        """What the device sent while the link was being opened (not in the read buffer)."""

    async def _negotiate(self, timeout: float) -> None:
        s = self.settings
        out = bytearray()
        for opt in (BINARY, SGA, COM_PORT):
            out += bytes([IAC, WILL, opt, IAC, DO, opt])
        out += _sub(r.SET_BAUDRATE, struct.pack("!I", s.baudrate))
        out += _sub(r.SET_DATASIZE, bytes([s.bytesize]))
        out += _sub(r.SET_PARITY, bytes([_PARITY[s.parity]]))
        out += _sub(r.SET_STOPSIZE, bytes([_STOPSIZE[s.stopbits]]))
        flow = r.SET_CONTROL_USE_HW_FLOW_CONTROL if s.rtscts else r.SET_CONTROL_USE_NO_FLOW_CONTROL
        out += _sub(r.SET_CONTROL, flow)
        out += _sub(r.SET_CONTROL, r.SET_CONTROL_DTR_ON)
        if not s.rtscts:
            out += _sub(r.SET_CONTROL, r.SET_CONTROL_RTS_ON)
        out += _sub(r.SET_MODEMSTATE_MASK, b"\xff")
        out += _sub(r.NOTIFY_MODEMSTATE)
        self._raw_write(bytes(out))
        deadline = self.clock.monotonic() + timeout
        while len(self._answered) < len(_SETTING_ANSWERS):
            try:
                await self._wait_event(deadline)
            except LinkClosed as e:
                raise LinkClosed(self._closed_at_open()) from e
            except LinkTimeout as e:
                missing = sorted(set(_SETTING_ANSWERS.values()) - self._answered_names())
                raise LinkError(
                    f"{self.url} does not answer as an RFC 2217 server "
                    f"(no answer for {', '.join(missing)}); for a raw TCP server use socket://"
                ) from e
        # Bytes that arrived during negotiation may be leftovers of an earlier session (a
        # server buffers what the device sent while nobody listened): out of the read
        # buffer, so no driver takes them for an answer to what it asks next. Kept aside for
        # a driver whose protocol can tell what in them still holds (a control's alarm
        # report as the link opens): the link cannot.
        self.opened_with = self.reset_input()

    def _closed_at_open(self) -> str:
        """Why a server closed the connection before the line was set up, in its own words
        where it gave some (ser2net: "Port already in use", "Device open failure: ..."), and
        what to do about it."""
        said = "".join(c for c in self.pending().decode("ascii", "replace") if c.isprintable())
        said = said.strip()[:80]
        if not said:
            advice = (
                "another client may hold that port (a device server takes one at a time), or "
                "the server has no device there: check the port number and the server"
            )
        elif "in use" in said.lower():
            advice = (
                "another client (another host, a terminal program) holds that port, as a "
                "device server takes one at a time: end that one"
            )
        else:
            advice = "see to it at the server (its serial device, its configuration)"
        words = f', saying "{said}"' if said else ""
        return f"{self.url}: the server closed the connection as it opened{words}: {advice}"

    def _answered_names(self) -> set[str]:
        return {_SETTING_ANSWERS[c] for c in self._answered}

    async def _wait_event(self, deadline: float) -> None:
        self._modem_event.clear()
        remaining = deadline - self.clock.monotonic()
        if remaining <= 0:
            raise LinkTimeout(f"{self.url}: no RFC 2217 answer in time")
        try:
            async with self.clock.timeout(remaining):
                await self._modem_event.wait()
        except TimeoutError as e:
            raise LinkTimeout(f"{self.url}: no RFC 2217 answer in time") from e
        if self._closed_exc is not None:
            raise self._closed_exc

    def _raw_write(self, data: bytes) -> None:
        if self._transport is not None and not self._transport.is_closing():
            self._transport.write(data)

    async def _send(self, data: bytes) -> None:
        await super()._send(data.replace(r.IAC, r.IAC_DOUBLED))

    def _feed_closed(self, exc: LinkError | None = None) -> None:
        super()._feed_closed(exc)
        self._modem_event.set()

    def _on_wire_data(self, data: bytes) -> None:
        if self._mode == _NORMAL and IAC not in data:
            self._feed(data)  # the common case: plain data, no Telnet commands
            return
        plain = bytearray()
        for b in data:
            if self._mode == _NORMAL:
                if b == IAC:
                    self._mode = _IAC
                else:
                    plain.append(b)
            elif self._mode == _IAC:
                if b == IAC:
                    plain.append(IAC)
                    self._mode = _NORMAL
                elif b == SB:
                    self._sub.clear()
                    self._mode = _SUB
                elif b in (WILL, WONT, DO, DONT):
                    self._command = b
                    self._mode = _NEGOTIATE
                else:
                    self._mode = _NORMAL  # NOP, GA and friends carry nothing for us
            elif self._mode == _NEGOTIATE:
                self._negotiation(self._command, b)
                self._mode = _NORMAL
            elif self._mode == _SUB:
                if b == IAC:
                    self._mode = _SUB_IAC
                else:
                    self._sub.append(b)
            else:  # _SUB_IAC
                if b == IAC:
                    self._sub.append(IAC)
                    self._mode = _SUB
                else:
                    if b == SE:
                        self._subnegotiation(bytes(self._sub))
                    self._mode = _NORMAL
        if plain:
            self._feed(bytes(plain))

    def _negotiation(self, command: int, option: int) -> None:
        if command == DO:
            if option in _WE_SUPPORT:
                if option not in self._we:
                    self._we.add(option)
                    self._raw_write(bytes([IAC, WILL, option]))
            elif (command, option) not in self._refused:
                self._refused.add((command, option))
                self._raw_write(bytes([IAC, WONT, option]))
        elif command == DONT:
            if option in self._we:
                self._we.discard(option)
                self._raw_write(bytes([IAC, WONT, option]))
        elif command == WILL:
            if option in _THEY_SUPPORT:
                if option not in self._they:
                    self._they.add(option)
                    if option not in (BINARY, SGA, COM_PORT):  # those we asked for already
                        self._raw_write(bytes([IAC, DO, option]))
            elif (command, option) not in self._refused:
                self._refused.add((command, option))
                self._raw_write(bytes([IAC, DONT, option]))
        elif command == WONT and option in self._they:
            self._they.discard(option)
            self._raw_write(bytes([IAC, DONT, option]))

    def _subnegotiation(self, sub: bytes) -> None:
        if len(sub) < 2 or sub[0] != COM_PORT:
            return
        code, value = sub[1], sub[2:]
        if code in _SETTING_ANSWERS:
            self._answered.add(code)
            if code == r.SERVER_SET_BAUDRATE[0] and len(value) == 4:
                self.server_settings["baudrate"] = struct.unpack("!I", value)[0]
            elif value:
                self.server_settings[_SETTING_ANSWERS[code]] = value[0]
        elif code == r.SERVER_NOTIFY_MODEMSTATE[0] and value:
            self.modem_state = value[0]
        self._modem_event.set()

    async def cts(self) -> bool:
        """CTS as the server last reported it (it pushes every change; asked if never told).

        Raises LinkClosed once the server closed the connection: the level it last reported
        is no longer the machine's (a mill would pass for ready on a dead line).
        """
        self.check_open()
        if self.modem_state is None:
            self._raw_write(_sub(r.NOTIFY_MODEMSTATE))
            deadline = self.clock.monotonic() + 2.0
            while self.modem_state is None:
                try:
                    await self._wait_event(deadline)
                except LinkTimeout as e:
                    raise LinkError(f"{self.url}: the server does not report modem lines") from e
        return bool(self.modem_state & r.MODEMSTATE_MASK_CTS)

    async def _wait_modem(self, deadline: float, level: bool) -> None:
        # Servers push changes; ask again now and then for those that only answer polls.
        poll_at = min(deadline, self.clock.monotonic() + 0.5)
        try:
            await self._wait_event(poll_at)
        except LinkTimeout:
            if self.clock.monotonic() >= deadline:
                raise LinkTimeout(
                    f"{self.url}: CTS did not go {'high' if level else 'low'} in time"
                ) from None
            self._raw_write(_sub(r.NOTIFY_MODEMSTATE))


def _sub(code: bytes, value: bytes = b"") -> bytes:
    return (
        r.IAC + r.SB + r.COM_PORT_OPTION + code + value.replace(r.IAC, r.IAC_DOUBLED) + r.IAC + r.SE
    )
