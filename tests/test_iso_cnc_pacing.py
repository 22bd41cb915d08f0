"""How the iso-cnc driver paces its writes when its own timers fire late (a host feeding
hundreds of lines from one process), on virtual time over mem://: the emulated control at its
real line rate, the host's every sleep ending a set time late. Late or not, what the host has
in flight never passes ``burst`` + ``ahead`` characters (the bound that keeps the control's
DC3 a backstop); a late host writes more at once, so it wakes less often. And a drip-feed
ends at its M30 however its writes fall: its last block goes out with its closing %."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from cellctl.clock import Clock, current_clock, run_virtual
from cellctl.emulators.memserve import serve_mem
from cellctl.kinds.iso_cnc import tape
from cellctl.kinds.iso_cnc.driver import IsoCncDriver, IsoCncOptions
from cellctl.kinds.iso_cnc.emulator import EmulatorOptions, IsoCncEmulator, Mode
from cellctl.kinds.iso_cnc.options import ISO_LINE
from cellctl.link import LineSettings, TrafficLog
from cellctl.link.trace import SENT

from .test_iso_cnc_link import surfacing

LINE = LineSettings.parse(ISO_LINE)


class LateClock:
    """The running loop's clock, but every sleep ends ``late`` s after it was due: what a
    busy host's timers do. Everything else is the loop's own clock."""

    def __init__(self, late: float) -> None:
        self.inner: Clock = current_clock()
        self.late = late

    @property
    def time_scale(self) -> float:
        return self.inner.time_scale

    def now(self) -> float:
        return self.inner.now()

    def monotonic(self) -> float:
        return self.inner.monotonic()

    async def sleep(self, seconds: float) -> None:
        await self.inner.sleep(seconds + self.late)

    def timeout(self, seconds: float | None) -> Any:
        return self.inner.timeout(seconds)

    def call_at(self, when: float, callback: Callable[..., object], *args: Any) -> Any:
        return self.inner.call_at(when, callback, *args)


def feed(
    data: bytes, mode: Mode, late: float, options: IsoCncOptions, trace: TrafficLog | None = None
) -> IsoCncEmulator:
    """``data`` fed to an emulated control in ``mode`` (EDIT: read into memory; RMT: a
    drip-feed) by a host ``late`` s late at every wake-up, on virtual time; the control."""
    control = IsoCncEmulator(EmulatorOptions(auto_operator=True))
    control.mode = mode

    async def main() -> None:
        server = await serve_mem(control, LINE)
        clock = LateClock(late) if late else None
        driver = await IsoCncDriver.connect(
            server.url, settings=LINE, options=options, trace=trace, clock=clock
        )
        send = driver.read_in if mode == Mode.EDIT else driver.drip_feed
        try:
            await send(data, timeout=600)
        finally:
            await driver.close()
            await server.close()

    run_virtual(main())
    return control


def read_in(late: float) -> tuple[list[tuple[float, int]], IsoCncEmulator, bytes, IsoCncOptions]:
    """A program read into the control's memory by a host ``late`` s late at every wake-up:
    the host's writes as (time, characters), the control, the program and the options."""
    data = surfacing(6)
    options = IsoCncOptions(dc1_timeout=10)
    trace = TrafficLog(None)
    control = feed(data, Mode.EDIT, late, options, trace)
    writes = [(t, len(d)) for t, _, direction, d in trace.entries if direction == SENT]
    return writes, control, data, options


def most_in_flight(writes: list[tuple[float, int]]) -> float:
    """The most characters written and not yet across the line, right after any write."""
    char_time, wire_free, most = LINE.char_time, -math.inf, 0.0
    for when, n in writes:
        wire_free = max(wire_free, when) + n * char_time
        most = max(most, (wire_free - when) / char_time)
    return most


#: The trace's times are wall-clock floats, a quarter of a microsecond apart at today's
#: dates: over a few hundred writes their rounding adds up to hundredths of a character.
ROUNDING = 0.05


def test_a_late_host_tops_up_what_is_in_flight_and_never_goes_past_it() -> None:
    on_time, control, data, options = read_in(0.0)
    late, late_control, _, _ = read_in(0.004)  # 3.5 characters of line time late
    for ctl in (control, late_control):
        assert ctl.memory[1234] == tape.unframe(data)  # byte for byte
        assert ctl.alarms == []
    burst, _ = options.sender(LINE.char_time)
    bound = burst + max(options.ahead, burst / 2)
    # On time: the first write fills the empty line up to the bound, then bursts as set.
    assert on_time[0][1] == bound
    assert max(n for _, n in on_time[1:]) == burst
    assert most_in_flight(on_time) <= bound + ROUNDING
    # Late: each wake-up finds the line emptier and tops it up, never past the bound.
    assert max(n for _, n in late) > burst
    assert most_in_flight(late) <= bound + ROUNDING
    assert len(late) < len(on_time)
    print(f"on time: {len(on_time)} writes; 4 ms late: {len(late)} writes")


def starving(pad: int) -> bytes:
    """Short fast moves the line cannot keep up with, so that the control runs each block as
    its LF arrives, M30 too; ``pad`` characters of comment move where the writes fall."""
    lines = ["%", f"O1234 ({'P' * pad})", "G21 G90 G17", "G1 Z0 F3000"]
    lines += [f"G1 X{(i % 2) / 10:.3f}" for i in range(40)]
    lines += ["M30", "%"]
    return ("\n".join(lines) + "\n").encode()


def test_a_drip_feed_ends_at_its_m30_wherever_the_writes_fall() -> None:
    """The control ends the run at M30 the moment its LF arrives and says so with DC3. A host
    8 ms late whose write ended with that LF would hear the DC3 before its closing % was out,
    take it for a full buffer, and feed the % to the next read (the automatic operator's):
    the run's end is then never heard. Every alignment of the writes is tried."""
    ended: list[int] = []
    for pad in range(8):
        control = feed(starving(pad), Mode.RMT, 0.008, IsoCncOptions(dc1_timeout=10))
        run = next(r for r in control.runs if r.blocks)
        assert run.done and run.blocks == 44, (pad, run)
        assert control.alarms == [], pad
        ended.append(pad)
    assert ended == list(range(8))
