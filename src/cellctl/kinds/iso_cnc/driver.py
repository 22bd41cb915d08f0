"""The iso-cnc driver: a DNC host for an ISO-code CNC control (Fanuc / Haas style) on RS-232,
and the mill family (:class:`cellctl.kinds.families.Mill`) over it::

    cnc = await IsoCncDriver.connect("rfc2217://10.0.0.7:7001", options=IsoCncOptions())
    report = await cnc.read_in(Path("O1234.nc").read_bytes(), progress=print)   # into memory
    report = await cnc.drip_feed(data, progress=print, timeout=3600)  # runs as it comes
    punched = await cnc.receive(timeout=600)                          # DC2 ... DC4

The line (spec iso-dnc-rs232.md): the control asks with DC1, stops the host with DC3 and
tolerates ``dc3_tolerance`` characters after it (Fanuc: about 10); an 11th is alarm 087.
Reading: wait for DC1, send the tape (``leader`` NULs, ``%`` LF, the blocks, ``%``, ``trailer``
NULs), stop on DC3, go on at DC1, done at the control's DC3 after the closing ``%``. Punch:
the control sends DC2, the tape, DC4. A control that reports its alarms sends NAK, the number,
LF: the driver raises :class:`ControlAlarm` with the spec's words and the raw bytes.

How it stays safe over a USB adapter or a device server
-------------------------------------------------------
A DC3 reaches the host late: a USB adapter passes received bytes on at its latency timer
(1-16 ms), a device server adds its network. At 9600 7E2 a character takes 1.15 ms, so at
16 ms a DC3 arrives 14 characters after the control sent it: no host that only reacts to DC3
can stay under a tolerance of 10. Two things keep this driver under it:

1. **Nothing queued.** It writes ``burst`` characters at a time and writes the next burst only
   when its own clock (the line rate from the line settings) says the previous one has all but
   crossed the wire (``ahead`` characters early, to keep the line busy, plus however late
   its own timers have been firing lately, so that a late wake-up does not leave the line
   idle). A wake-up that comes later still writes more at once: it tops what is in flight
   up to ``burst`` + ``ahead`` characters, never beyond (but for a drip-feed's closing
   ``%``, which goes out with the last block). What is in flight is its own count,
   never a buffer in the OS, the adapter or the server: after it hears a DC3, only the last
   burst or two it wrote are still to arrive.
2. **It knows the control's buffer.** For a drip-feed it runs the control's motion model
   (:mod:`cellctl.kinds.iso_cnc.motion`, the one the emulator and the estimate use) over
   the blocks it sends: a block leaves the control's buffer when it starts to execute, at
   ``max(its arrival, the previous block's end)``. It sends only while the modelled buffer,
   its characters in flight included, stays ``margin`` characters under the control's
   high-water mark (``buffer_size - dc3_tolerance`` unless ``high_water`` is set), and it
   counts a block as arrived ``link_lag_s`` after its line time (a write that a USB adapter
   or a device server holds a moment still has to arrive: its block cannot start). So the
   control never has cause to send DC3, and the adapter's delay does not matter. The model
   is corrected by what the control says: a DC3 means the buffer is fuller than modelled (it
   is taken as at the high-water mark), a DC1 that it is no fuller than the low-water mark.
   The DC3 stays obeyed at once, as the backstop. For read-in to memory the control stores
   as fast as the line brings characters (``store_cps`` = 0) and DC3 comes only at the end.

With ``cs_flow`` the control's RTS (the host's CTS, carried by a serial port or RFC 2217) is
also obeyed before each burst. Bad input (no such file, a program the G-code check refuses,
characters a 7-bit tape cannot carry) is refused before a byte goes out.

A read ends at the control's DC3 after the closing ``%`` (the rest of the trailer is not
sent: the control has left the read). A punch is received whole as it comes; :meth:`pause`
and :meth:`resume` send DC3 and DC1 to hold it (CS cannot: the link layer drives no RTS).
In a cell, :meth:`run` drip-feeds the route's program: the cell's GO output (wired to CYCLE
START, the control in RMT) starts it, and it returns when the control has run it to its end.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable
from pathlib import Path

from cellctl.clock import Clock
from cellctl.drivers.base import StartOutput
from cellctl.drivers.state import StateStore
from cellctl.errors import CellctlError, DeviceError, LinkTimeout, ProtocolError
from cellctl.kinds.families import RunNotStarted, RunProgress
from cellctl.kinds.iso_cnc import tape
from cellctl.kinds.iso_cnc.buffer import BufferModel, modelled_blocks
from cellctl.kinds.iso_cnc.options import ISO_LINE, IsoCncOptions, off_loop, prepare, read_program
from cellctl.kinds.iso_cnc.sender import TapeSender
from cellctl.kinds.iso_cnc.status import IsoCncState, IsoCncStatus
from cellctl.kinds.iso_cnc.transfer import (
    Progress,
    TapeEnd,
    TransferProgress,
    TransferReport,
    with_words,
)
from cellctl.link import LineSettings, Link, TrafficLog


class ControlAlarm(DeviceError):
    """The control raised an alarm (085, 086, 087) and aborted the transfer."""


class ReadNotStarted(LinkTimeout, RunNotStarted):
    """The control sent no DC1 in time: nobody pressed READ or CYCLE START (nothing went
    out; ``options.dc1_timeout`` unless the caller gave its own wait). A cell's run that
    ends so started nothing: its part stays as it was."""


class IsoCncDriver(TapeSender):
    """One ISO-code control on one link (see module docstring); what it hears while it sends
    and how it sends are :class:`~cellctl.kinds.iso_cnc.sender.TapeSender`'s."""

    def __init__(
        self,
        link: Link,
        *,
        name: str | None,
        store: StateStore | None,
        options: IsoCncOptions,
        start_output: StartOutput | None = None,
        clock: Clock | None = None,
    ) -> None:
        saved = self._attach(link, name, store, clock)
        self.options = options
        self.start_output = start_output
        self.state = IsoCncState(int(saved.get("state", IsoCncState.IDLE)))
        if self.state != IsoCncState.ALARM:
            self.state = IsoCncState.IDLE  # a transfer does not survive the host
        self.alarm: int | None = saved.get("alarm")
        self.initialized = True  # a control keeps its memory: nothing to set up
        self._stopped = True  # the host sends nothing before the control's DC1
        self._inbuf = bytearray()
        self._dc3_seen = 0  # DC3s heard (the end of a read is a DC3)
        self._last_dc3_at = 0.0
        self._progress = IsoCncStatus()
        self._model: BufferModel | None = None
        self._sent = 0
        self._stops = 0
        self._seen_at_end = -1  # DC3s heard when the closing % went out
        self._sending = False  # a DC3 now is flow control, not the end of the read
        self._end_asked = False  # end_tape(): cut the tape at the next block's end
        self._cut = False  # this transfer's tape was cut short
        self._lock = asyncio.Lock()
        #: Where the last read's tape stopped going out when it failed part-way (None: it
        #: did not, or nothing went out): what an operator needs before going on.
        self.ended_at: TapeEnd | None = None
        #: Characters of the last punch received after its DC2 (what a failed one had sent).
        self.punched = 0
        self._opened_with(getattr(link, "opened_with", b""))

    @classmethod
    async def connect(
        cls,
        url: str,
        *,
        name: str | None = None,
        settings: LineSettings | None = None,
        store: StateStore | None = None,
        options: IsoCncOptions | None = None,
        start_output: StartOutput | None = None,
        trace: TrafficLog | None = None,
        clock: Clock | None = None,
    ) -> IsoCncDriver:
        """Open ``url`` and return the driver (the machine's owner locks taken)."""
        chosen = options or IsoCncOptions()
        return await cls._connect_owned(
            url,
            settings or LineSettings.parse(ISO_LINE),
            name=name,
            store=store,
            trace=trace,
            build=lambda link: cls(
                link,
                name=name,
                store=store,
                options=chosen,
                start_output=start_output,
                clock=clock,
            ),
            clock=clock,
        )

    # -- the host's state, an alarm, a read's start and end ----------------------------------

    def _set(self, state: IsoCncState) -> None:
        self.state = state
        self._persist({"state": int(state), "alarm": self.alarm})

    def _raise_alarm(self, code: int, raw: bytes) -> None:
        words = tape.ALARMS.get(code, "ALARM")
        self.alarm = code
        self._progress = IsoCncStatus(IsoCncState.ALARM, alarm=code, alarm_text=words)
        self._set(IsoCncState.ALARM)
        meaning = tape.ALARM_MEANINGS.get(code, "the control stopped the transfer")
        raise ControlAlarm(code, words, detail=f"{meaning} (raw: {raw!r})")

    def _opened_with(self, data: bytes) -> None:
        """What the control said while the link opened (a device server's link keeps it
        out of the read buffer): an alarm it reported then is the host's from the start, a
        reset after it clears it; its flow control belonged to a read that is over."""
        said, code, rest = tape.alarm_state(data)
        self._inbuf += rest  # a report cut in two: its rest is still to come
        if said and code is not None:
            self.alarm = code
            self._set(IsoCncState.ALARM)
        elif said:
            self._control_reset()

    def _control_reset(self) -> None:
        # Only an alarm is undone: a read under way is the read's own to end.
        if self.state == IsoCncState.ALARM:
            self.alarm = None
            self._progress = IsoCncStatus()
            self._set(IsoCncState.IDLE)

    def _take_reports(self) -> None:
        """Between transfers: what the control said since (an alarm report, the SYN of a
        reset, a DC1 of READ pressed again), taken as a read would take it. Left alone
        while a transfer runs (it reads its own) or a punch is coming (``receive`` wants
        its DC2 and tape)."""
        if self._lock.locked() or tape.DC2 in self.link.pending():
            return
        data = self.link.reset_input()
        while data or self._inbuf:
            try:
                self._handle(data)
                return
            except ControlAlarm:
                data = b""  # the host holds it now; what came after it is taken too

    async def _wait_dc1(self, timeout: float, what: str) -> None:
        clock = self.clock
        deadline = clock.monotonic() + timeout
        self._handle(self.link.reset_input())
        while self._stopped:
            try:
                await self._listen(
                    deadline,
                    f"no DC1 (tape reader start) from the control in {timeout:g} s: {what}",
                )
            except LinkTimeout as e:
                raise ReadNotStarted(str(e)) from None

    async def _wait_end(self, deadline: float, model: BufferModel, seen_before: int) -> None:
        """Wait for the control's DC3 that ends the read (after the closing ``%``).

        A DC3 heard once every byte is out ends a read-in. A drip-feed's ends the run only
        from shortly before the modelled end of its last block on: a DC3 before that is the
        buffer's (which a control lagging behind the model can still send)."""
        clock = self.clock
        finished = clock.monotonic()
        if model.drip:
            end = model.end_time()
            grace = 0.05 + 0.05 * max(0.0, end - finished)
            while clock.monotonic() < end - grace:
                self._handle(self.link.reset_input())
                await self.clock.sleep(min(0.05, end - grace - clock.monotonic()))
        while True:
            self._handle(self.link.reset_input())
            if self._dc3_seen > seen_before:
                return
            await self._listen(deadline, "the control did not end the read (no DC3 after %)")

    async def read_in(
        self,
        data: bytes,
        *,
        progress: Progress | None = None,
        timeout: float | None = None,
        name: str = "program",
    ) -> TransferReport:
        """Send a program file into the control's memory (EDIT mode, READ pressed): wait for
        DC1, send, stop on DC3, go on at DC1; returns at the control's DC3 after ``%``.
        ``name`` (the file's) begins each problem of the G-code check that refuses it.
        ``timeout``: seconds to wait for the DC1 (``options.dc1_timeout`` by default), then
        :class:`ReadNotStarted`."""
        framed = await off_loop(data, prepare, data, self.options, name)
        return await self._read(framed, drip=False, progress=progress, timeout=timeout)

    async def drip_feed(
        self,
        data: bytes,
        *,
        progress: Progress | None = None,
        timeout: float | None = None,
        name: str = "program",
    ) -> TransferReport:
        """Run a program as it is sent (RMT mode, CYCLE START): never overflow the control's
        buffer, never let it starve where the line can keep up; returns when it has ended.
        ``timeout`` as for :meth:`read_in` (the wait for the DC1)."""
        framed = await off_loop(data, prepare, data, self.options, name, True)
        return await self._read(framed, drip=True, progress=progress, timeout=timeout)

    async def _read(
        self, framed: bytes, *, drip: bool, progress: Progress | None, timeout: float | None
    ) -> TransferReport:
        o = self.options
        clock = self.clock
        async with self._lock:
            state = IsoCncState.DRIP_FEEDING if drip else IsoCncState.READING
            # The model is ready before the state says "waiting": the control's DC1 that
            # comes from now on is answered at once. Its blocks are modelled whole first
            # (see ModelledBlocks: never in the send loop).
            model = BufferModel(drip=drip, store_cps=o.store_cps)
            if drip:
                model.feed(
                    await off_loop(framed, modelled_blocks, framed, o.motion(), o.motion_scale)
                )
            self.alarm = None
            self._set(state)
            self._progress = IsoCncStatus(state, 0, len(framed))
            self._sent, self._end_asked = 0, False  # end_tape() says "waiting" until DC1
            self.ended_at = None
            try:
                if progress is not None:
                    progress(TransferProgress(0, len(framed), 0.0, 0, 0.0, math.inf, "waiting"))
                # _stopped stays as the control left it: a DC1 it sent since the last read
                # (an operator, or the auto-operator, pressed READ again) is its asking.
                if drip and self.start_output is not None:
                    await self.start_output.pulse(o.go_pulse)
                what = "RMT mode and CYCLE START" if drip else "EDIT mode and READ"
                await self._wait_dc1(timeout or o.dc1_timeout, f"is the control in {what}?")
                began = clock.monotonic()
                sent = await self._send(framed, model, "sending", progress)
                # DC3s until the closing % was out were the buffer's
                seen = self._seen_at_end if self._seen_at_end >= 0 else self._dc3_seen
                left = max(0.0, model.end_time() - clock.monotonic())
                allowed = left * o.end_margin + o.end_extra + o.ready_wait
                await self._wait_end(clock.monotonic() + allowed, model, seen)
                sent.elapsed_s = clock.monotonic() - began
                sent.stalls_modelled_s = model.idle_s  # wall seconds, as the user saw them
                if progress is not None:
                    progress(
                        TransferProgress(
                            sent.chars_sent,
                            sent.chars_total,
                            sent.chars_per_s,
                            sent.buffer_stops,
                            sent.elapsed_s,
                            0.0,
                            "done",
                        )
                    )
                self._set(IsoCncState.IDLE)
                self._progress = IsoCncStatus()
                return sent
            except BaseException:
                if self._sent:
                    self.ended_at = TapeEnd.of(framed, self._sent)
                self._stopped = True  # what the control does next is not known: wait for DC1
                if self.state != IsoCncState.ALARM:
                    self._set(IsoCncState.IDLE)
                raise
            finally:
                self._model = None

    async def receive(
        self,
        *,
        progress: Progress | None = None,
        timeout: float = 600.0,
        max_bytes: int = 64 * 1024 * 1024,
        idle: float | None = None,
    ) -> bytes:
        """What the control punches (PUNCH pressed): the bytes between DC2 and DC4.
        ``idle``: seconds the punch may go silent once its DC2 came (a control punches
        without a pause: silence is a punch stopped at the control or a cable pulled), then
        LinkTimeout; else only ``timeout`` ends it."""
        clock = self.clock
        deadline = clock.monotonic() + timeout
        async with self._lock:
            self._set(IsoCncState.PUNCHING)
            self.punched = 0
            try:
                buf = bytearray(self.link.reset_input())
                while (start := buf.find(tape.DC2)) < 0:
                    buf = buf[-1:] if buf[-1:] == tape.NAK else bytearray()
                    buf += await self._read_some(deadline, "no DC2: PUNCH was not pressed")
                got = buf[start + 1 :]
                began = clock.monotonic()
                while (end := got.find(tape.DC4)) < 0:
                    self.punched = len(got)
                    if len(got) > max_bytes:
                        raise ProtocolError(f"{self.name}: punched more than {max_bytes} bytes")
                    if tape.NAK in got:
                        i = got.find(tape.NAK)
                        found = tape.parse_alarm(bytes(got[i:]))
                        if found is not None:
                            self._raise_alarm(found[0], bytes(got[i : i + found[1]]))
                    if progress is not None:  # what came so far, the first piece too
                        elapsed = clock.monotonic() - began
                        rate = len(got) / elapsed if elapsed > 0 else 0.0
                        progress(
                            TransferProgress(len(got), 0, rate, 0, elapsed, math.inf, "receiving")
                        )
                    until, wanted = deadline, "the punch did not end (no DC4)"
                    if idle is not None and clock.monotonic() + idle < deadline:
                        until = clock.monotonic() + idle
                        wanted = (
                            f"the punch stopped: nothing from the control for {idle:g} s and "
                            "no DC4 (its end): was it stopped at the control (RESET, the mode "
                            "switch), or its cable pulled?"
                        )
                    got += await self._read_some(until, wanted)
                self._set(IsoCncState.IDLE)
                return bytes(got[:end])
            except BaseException:
                if self.state != IsoCncState.ALARM:
                    self._set(IsoCncState.IDLE)
                raise

    async def _read_some(self, deadline: float, wanted: str) -> bytes:
        left = deadline - self.clock.monotonic()
        try:
            return await self.link.read(65536, timeout=max(left, 0.0))
        except LinkTimeout:
            raise LinkTimeout(f"{self.name}: {wanted}") from None

    def end_tape(self) -> str:
        """End the tape going out the clean way (:func:`tape.cut_tape`: the rest of the
        block in flight, then ``%``), under the control's DC3/DC1 as ever; the read then
        returns as at any tape's end, its report ``ended_early``. Where it stood, in a word:
        ``"ending"``; ``"waiting"`` (no DC1 yet: nothing went out, cancel the read instead);
        ``"out"`` (all of it is out: the control stores or runs the rest)."""
        if self._sending:
            self._end_asked = True
            return "ending"
        return "out" if self._sent else "waiting"

    async def pause(self) -> None:
        """Stop a punch with DC3 (the control stops within 10 characters)."""
        await self.link.write(tape.DC3)

    async def resume(self) -> None:
        """Let a punch go on (DC1)."""
        await self.link.write(tape.DC1)

    # -- the mill family ----------------------------------------------------------------------

    @property
    def running(self) -> bool:
        return self.state == IsoCncState.DRIP_FEEDING

    @property
    def state_text(self) -> str:
        return self.host_status().shown

    @property
    def manual(self) -> bool:
        return self.state == IsoCncState.IDLE

    @property
    def ready_wait(self) -> float:
        return self.options.ready_wait

    @property
    def setup_timeout(self) -> float:
        return self.options.setup_timeout

    def host_status(self) -> IsoCncStatus:
        """The status from the host's state, no byte sent."""
        if self.state == IsoCncState.IDLE:
            return IsoCncStatus()
        if self.state == IsoCncState.ALARM:
            words = tape.ALARMS.get(self.alarm or 0, "")
            return IsoCncStatus(IsoCncState.ALARM, alarm=self.alarm, alarm_text=words)
        return self._progress

    async def status(self) -> IsoCncStatus:
        """The host's view: a control on RS-232 answers no status request, but one that
        reports its alarms says each, and its reset (SYN), as they happen: taken first."""
        self._take_reports()
        return self.host_status()

    async def setup(self, program: Path, *, force: bool) -> None:
        """Drip-feed the setup program (a warm-up, a probing cycle); forced: clear an alarm
        the host holds first (the operator has reset the control)."""
        framed = read_program(program, self.options)
        if force and self.state == IsoCncState.ALARM:
            self.alarm = None
            self._set(IsoCncState.IDLE)
        await self._read(framed, drip=True, progress=None, timeout=self.options.dc1_timeout)

    async def run(
        self, program: Path, *, progress: Callable[[RunProgress], None] | None = None
    ) -> None:
        """Drip-feed ``program``: the control (RMT) runs it as it comes, to its end."""
        framed = read_program(program, self.options)
        lines = framed.count(b"\n")

        def relay(p: TransferProgress) -> None:
            if progress is None:
                return
            block = framed.count(b"\n", 0, p.chars_sent)
            phase = {"stopped": "sending", "running": "machining"}.get(p.phase, p.phase)
            progress(RunProgress(block, lines, block, lines, p.chars_sent, p.chars_total, phase))

        try:
            await self._read(framed, drip=True, progress=relay, timeout=self.options.dc1_timeout)
        except CellctlError as e:
            if self.ended_at is None:
                raise
            # Where the tape ended, in the cell's alarm as the DNC line says it: the operator
            # goes on from there (or not) at the control.
            raise with_words(e, self.ended_at.words(drip=True)) from e

    async def end(self) -> str:
        """Back to the operator's hands (the host forgets an alarm the operator resets)."""
        self.alarm = None
        self._set(IsoCncState.IDLE)
        return "idle"


__all__ = [
    "ISO_LINE",
    "ControlAlarm",
    "IsoCncDriver",
    "IsoCncOptions",
    "ReadNotStarted",
    "TransferProgress",
    "TransferReport",
    "prepare",
    "read_program",
]
