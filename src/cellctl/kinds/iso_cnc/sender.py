"""The iso-cnc driver's sending under the control's flow control, the base of
:class:`~cellctl.kinds.iso_cnc.driver.IsoCncDriver`: what the control says while the host
sends (DC1, DC3, an alarm report), the control's buffer marks, and a tape sent in bursts paced
to the line and kept under the modelled buffer, the DC3 obeyed as the backstop (the driver's
module docstring says why: "How it stays safe over a USB adapter or a device server"). The
driver's reads wait for the control's DC1, then send through these::

    report = await self._send(framed, model, "sending", progress)   # every byte through
    await self._listen(deadline, "no DC3")     # the control's next bytes, handled
"""

from __future__ import annotations

import math
from collections.abc import Callable

from cellctl.drivers.base import LinkDriver
from cellctl.errors import LinkTimeout
from cellctl.kinds.iso_cnc import tape
from cellctl.kinds.iso_cnc.buffer import BufferModel
from cellctl.kinds.iso_cnc.options import IsoCncOptions
from cellctl.kinds.iso_cnc.status import IsoCncState, IsoCncStatus
from cellctl.kinds.iso_cnc.transfer import Progress, TransferProgress, TransferReport

#: Per wake-up, how much of the host's measured lateness it keeps (about 350 wake-ups to
#: halve: a second or two of sending, so a burst of load is remembered through it).
_LATE_DECAY = 0.998


class TapeSender(LinkDriver):
    """Flow control on one control's line (see module docstring).

    The driver sets the state below in its constructor and provides ``_raise_alarm`` (it
    moves the host's state to ALARM).
    """

    options: IsoCncOptions
    state: IsoCncState
    _stopped: bool
    _inbuf: bytearray
    _dc3_seen: int
    _last_dc3_at: float
    _progress: IsoCncStatus
    _model: BufferModel | None
    _sent: int
    _stops: int
    _seen_at_end: int
    _sending: bool
    _end_asked: bool
    _cut: bool

    def _raise_alarm(self, code: int, raw: bytes) -> None:
        """Raise the control's alarm ``code`` (its report's bytes ``raw``); the driver's."""
        raise NotImplementedError

    def _control_reset(self) -> None:
        """The control was reset (SYN): an alarm the host holds is gone; the driver's."""
        raise NotImplementedError

    # -- what the control says ---------------------------------------------------------------

    @property
    def high_water(self) -> int:
        return self.options.high_water_mark()

    @property
    def low_water(self) -> int:
        o = self.options
        return o.low_water if o.low_water is not None else o.buffer_size // 2

    def _handle(self, data: bytes) -> None:
        """Bytes from the control while the host sends: DC1, DC3, alarm reports and the
        SYN of a reset."""
        self._inbuf += data
        now = self.clock.monotonic()
        while self._inbuf:
            byte = self._inbuf[0]
            if byte == tape.NAK[0]:
                found = tape.parse_alarm(bytes(self._inbuf))
                if found is None:
                    return  # the rest of the report is still to come
                code, used = found
                raw = bytes(self._inbuf[:used])
                del self._inbuf[:used]
                self._raise_alarm(code, raw)
            del self._inbuf[:1]
            if byte == tape.SYN[0]:
                self._control_reset()
            elif byte == tape.Code.DC3:
                self._stopped = True
                self._dc3_seen += 1
                self._last_dc3_at = now
                model = self._model
                if model is not None and model.drip and self._sending:
                    # The control is at its high-water mark: if the model thought it emptier,
                    # it is behind the control; take its word.
                    level = model.level(self._sent, now)
                    model.offset = max(model.offset, self.high_water - (level - model.offset))
            elif byte == tape.Code.DC1:
                self._stopped = False
                model = self._model
                if model is not None and model.drip and model.offset:
                    level = model.level(self._sent, now) - model.offset
                    model.offset = min(model.offset, max(0, self.low_water - level))

    async def _listen(self, deadline: float, wanted: str) -> None:
        """Wait for bytes from the control until ``deadline`` (loop time), and handle them."""
        left = deadline - self.clock.monotonic()
        if left <= 0:
            raise LinkTimeout(f"{self.name}: {wanted}")
        try:
            data = await self.link.read(4096, timeout=left)
        except LinkTimeout:
            raise LinkTimeout(f"{self.name}: {wanted}") from None
        self._handle(data)

    # -- sending --------------------------------------------------------------------------------

    async def _send(
        self, framed: bytes, model: BufferModel, phase: str, progress: Progress | None
    ) -> TransferReport:
        """Send a tape under flow control (module docstring); returns when the last byte is
        through the line. The caller waits for the control's end of the read."""
        clock = self.clock
        total = len(framed)
        began = clock.monotonic()
        self._stops = 0
        self._sent = 0
        self._seen_at_end = -1
        self._model = model
        self._cut = False

        def report(state: str) -> None:
            if progress is None:
                return
            elapsed = clock.monotonic() - began
            rate = self._sent / elapsed if elapsed > 0 else 0.0
            eta = (total - self._sent) / rate if rate > 0 else math.inf
            progress(TransferProgress(self._sent, total, rate, self._stops, elapsed, eta, state))

        report(phase)
        self._sending = True
        try:
            await self._send_all(framed, model, phase, report)
        finally:
            self._sending = False
        elapsed = clock.monotonic() - began
        report("running" if model.drip else "done")
        return TransferReport(
            self._sent,
            total,
            self._sent / elapsed if elapsed > 0 else 0.0,
            self._stops,
            elapsed,
            stalls_modelled_s=model.idle_s,
            ended_early=self._cut,
        )

    async def _send_all(
        self, framed: bytes, model: BufferModel, phase: str, report: Callable[[str], None]
    ) -> None:
        o = self.options
        clock = self.clock
        char_time = self.link.settings.char_time
        total = len(framed)
        # Bursts cover at least pace_s of line time, whatever the baud rate (see pace_s).
        burst, limit = o.sender(char_time)
        ahead = max(o.ahead, burst / 2) * char_time
        # How late this host's timers fire (a decaying maximum, s): it widens `ahead`, so a
        # late wake-up does not leave the line idle. (Not the model's lag: a lag counts every
        # character written within it as still in the buffer, and a burst of load would
        # hold the host back while the control starves; link_lag_s is the link's own.)
        late = 0.0
        # Where a burst and its lead fit in the tolerance, the DC3 stays a backstop for the
        # model (what is in flight when it comes must fit too): the lateness does not widen
        # the lead. Where they do not (a line made faster than this host's timers: a scaled
        # emulated cell or bench), the model alone guards the buffer, and the lead follows
        # the host's lateness so that the line does not idle.
        lead = ahead / char_time  # in characters
        fits = burst + lead <= o.dc3_tolerance
        spare = 0.0 if fits else math.inf
        wire_free = clock.monotonic()
        last_report = 0.0
        # Past the closing % (its trailer is only tape feed) a DC3 is the end of the read.
        end_at = framed.rfind(b"%") + 1 if o.percent else total - o.trailer
        # A drip-feed's last block and its closing % go out in one write: the control may end
        # the run at that block (M30) and send its DC3 before a later write, and a DC3 heard
        # before the % is out would be taken for the buffer's (the host would then wait for a
        # DC1 and feed the % to the control's next read).
        last_lf = framed.rfind(b"\n", 0, end_at) + 1 if model.drip else end_at
        # Looked up once: this loop runs once a burst, for hundreds of lines in one process.
        link, monotonic, sleep, level = self.link, clock.monotonic, clock.sleep, model.level
        lag, small, cs_flow = o.link_lag_s, o.burst, o.cs_flow
        while self._sent < total:
            data = link.reset_input()
            if data:
                self._handle(data)
            if self._end_asked:  # end_tape(): the rest of this block, then the tape's end
                self._end_asked = False
                shorter = tape.cut_tape(framed, self._sent, percent=o.percent)
                if shorter is not None:
                    framed, total, end_at, self._cut = shorter, len(shorter), len(shorter), True
                    last_lf = framed.rfind(b"\n", 0, end_at) + 1 if model.drip else end_at
                    model.cut(total)  # blocks past the cut never go out
                    if model.drip and not o.percent:
                        model.unsent.append((total, 0.0))  # the M30 block
            sent = self._sent
            if sent >= end_at and self._dc3_seen > self._seen_at_end:
                break
            if self._stopped:
                self._stops += 1
                report("stopped")
                deadline = monotonic() + o.stop_timeout
                while self._stopped:
                    await self._listen(
                        deadline, f"the control held the tape with DC3 for {o.stop_timeout:g} s"
                    )
                continue
            now = monotonic()
            wake = pace = wire_free - ahead - min(late, spare)  # when the line wants more
            # A burst tops what is in flight up to `burst` + `ahead` characters: a late
            # wake-up writes more at once (and wakes less often), never more in flight.
            gap = int(lead - max(0.0, wire_free - now) / char_time)
            n = min(burst + gap if gap > 0 else burst, total - sent)
            room = limit - level(sent, now)
            if room < n:
                drain = model.next_drain()
                if drain is not None and room < min(n, small):
                    # One wake-up for both: the room only grows while nothing is written.
                    wake = max(drain, now + char_time, pace)
                else:
                    # What fits now; with nothing to wait for (a block longer than the room),
                    # a small burst: the control's DC3 is the guard.
                    n = max(1, min(n, room)) if drain is not None else min(n, small)
            if wake > now:
                await sleep(wake - now)
                # How late the wake-up was, kept as a maximum that decays (see `late`).
                late = max(monotonic() - wake, late * _LATE_DECAY)
                continue
            if cs_flow and not await link.cts():
                await link.wait_cts(True, timeout=o.stop_timeout)
                continue
            if sent < last_lf <= sent + n < end_at:
                n = end_at - sent  # the closing % with its last block (see last_lf)
            await link.write(framed[sent : sent + n])
            # Dated from when the write returned, not from `now`: a host held up (by its OS,
            # by its load) between deciding and writing puts the burst on an idle line late,
            # and its blocks start late; counting them from `now` would empty the model early.
            wire_free = max(wire_free, monotonic()) + n * char_time
            self._sent = sent = sent + n
            model.wrote(sent, wire_free + lag)
            if sent >= end_at and self._seen_at_end < 0:
                self._seen_at_end = self._dc3_seen
            if now - last_report >= 0.2 or sent >= total:
                last_report = now
                self._progress = IsoCncStatus(self.state, sent, total, stall_s=model.idle_s)
                report(phase)
        if wire_free > clock.monotonic():
            await self.clock.sleep(wire_free - clock.monotonic())
