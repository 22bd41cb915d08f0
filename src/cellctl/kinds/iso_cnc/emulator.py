"""An ISO-code CNC control (Fanuc style), emulated: program memory, its RS-232 reader and
punch with DC1-DC4, drip-feed execution timed by the motion model::

    control = IsoCncEmulator(EmulatorOptions(buffer_size=256, tolerance=10), time_scale=10)
    server = await serve(control, "rfc2217://127.0.0.1:0", LineSettings.parse("9600,7E2"))
    control.set_mode(Mode.EDIT); control.read()      # READ: DC1, the tape goes into memory
    control.memory[1234]                             # "O1234 (PART)\\nG0 X0\\n...M30\\n"
    control.set_mode(Mode.RMT); control.cycle_start()  # drip-feed: blocks run as they come
    control.stalls                                   # [Stall(start_s, seconds), ...]
    control.punch(1234)                              # DC2, leader, %, O1234..., %, trailer, DC4

Flow control as the spec has it: DC1 when it wants data; DC3 once its buffer holds
``high_water`` characters; DC1 again at ``low_water``. It counts what arrives after each DC3
and raises alarm 087 past ``tolerance``. With ``cs_flow`` it also drops RTS (the host's CTS)
at the high-water mark. ``adapter_latency_ms`` holds each DC1/DC3 (and RTS change) back that
long before the host sees it, as a USB serial adapter does; the characters after the DC3 are
counted from the moment the control sent it. ``line_lag_ms`` holds each piece of the host's
data a random 0 to MS before it crosses (in order), as a device server's packet timer does.

An alarm stops the transfer and is reported the way a remote-buffer interface does: NAK,
then the alarm number (three digits) and LF (``\\x15087\\n``); the control stays in ALARM until
``reset()`` (RESET on its panel), which the interface says with SYN. A fault switched off
leaves an alarm as it was, as on the real control: the operator's RESET
(:meth:`~IsoCncEmulator.operator_after`, :meth:`~IsoCncEmulator.operator_clear`) clears it.
The alarms are in :data:`ALARMS`. Machine times (motion, the adapter's delay) are divided by
``time_scale``.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
from collections import deque
from collections.abc import Callable, Coroutine

from cellctl.clock import Clock, emulator_clock
from cellctl.emulators.serve import DeviceLine, LineNoise
from cellctl.emulators.switches import check_switch
from cellctl.errors import LinkClosed, LinkError, UsageError
from cellctl.kinds.iso_cnc import tape
from cellctl.kinds.iso_cnc.execution import ControlExecution
from cellctl.kinds.iso_cnc.gcode import PROGRAM_ENDS, Block, parse_block
from cellctl.kinds.iso_cnc.motion import Machine
from cellctl.kinds.iso_cnc.panel import (
    FAULTS,
    Activity,
    Alarm,
    DripRun,
    EmulatorOptions,
    Mode,
    Stall,
)
from cellctl.kinds.iso_cnc.tape import ALARMS, DC1, DC2, DC3, DC4, SYN, alarm_report
from cellctl.tasks import cancel_and_wait

#: Its panel and records (:mod:`cellctl.kinds.iso_cnc.panel`) are imported from here too.
__all__ = [
    "FAULTS",
    "Activity",
    "Alarm",
    "DripRun",
    "EmulatorOptions",
    "IsoCncEmulator",
    "Mode",
    "Stall",
    "block_of",
]

#: Seconds between the automatic operator's looks at a control waiting for its tape: nothing
#: came in that long, it presses READ again.
_OPERATOR_PATIENCE_S = 1.0
#: What a tape has before its program (leader and trailer NULs, DEL, the %, EOBs): a control
#: that has had only these still waits for its tape (Fanuc shows LSK, label skip), and the
#: trailer of the last tape often comes after the next READ.
_BEFORE_PROGRAM = frozenset(b"\x00\x7f\r\n%")
_BEFORE_PROGRAM_BYTES = bytes(sorted(_BEFORE_PROGRAM))


class IsoCncEmulator(ControlExecution):
    """One emulated control (see module docstring); its runs and their blocks are
    :class:`~cellctl.kinds.iso_cnc.execution.ControlExecution`'s."""

    def __init__(
        self,
        options: EmulatorOptions | None = None,
        *,
        time_scale: float | None = None,
        clock: Clock | None = None,
    ) -> None:
        self._clock = emulator_clock(clock, time_scale)
        self.options = options or EmulatorOptions()
        self.memory: dict[int, str] = {}
        self.mode = Mode.EDIT
        self.activity = Activity.IDLE
        self.selected = 0
        self.alarms: list[Alarm] = []
        self.runs: list[DripRun] = []
        self.run_hooks: list[Callable[[DripRun], None]] = []
        self.overflow_chars = 0  # the most characters received after one DC3
        self.dc3_sent = 0
        self.punched = 0  # characters punched, all punches
        self.punch_overrun = 0  # the most it punched after a host's DC3
        self.punch_held = False  # a punch waits for the host's DC1
        self._paused_at = 0
        self._read_serial = 0  # which READ press the automatic operator is waiting on
        self._program_came = False  # this read has had a character of a program
        self.peak_buffer = 0  # the most characters its reader buffer held
        self.chars_read = 0
        self.faults: set[str] = set()
        self._latency_ms = self.options.adapter_latency_ms
        self._lag_ms = self.options.line_lag_ms
        self._lag_rng = random.Random(self.options.seed)
        self._held_until = 0.0  # when the last held character crossed (loop time)
        self._tolerance = self.options.tolerance
        self._rng = random.Random(self.options.seed)
        self._parity_rate = self.options.parity_noise
        self._line: DeviceLine | None = None
        self._buffer = bytearray()
        self._lf_at: deque[float] = deque()  # when each LF in the buffer came through the line
        self._stopped = False  # a DC3 is out: counting what comes after it
        self._after_dc3 = 0
        self._dc3_at = 0.0
        self._tape = bytearray()  # what a read-in has taken so far
        self._run: DripRun | None = None
        self._machine: Machine | None = None
        self._block_ready = asyncio.Event()
        self._free_at = 0.0  # when the block running now ends (loop time)
        self._read_began = 0.0
        self._tape_done = False
        self._exec_task: asyncio.Task[None] | None = None
        self._punch_task: asyncio.Task[None] | None = None
        self._punch_go = asyncio.Event()
        self._punch_go.set()
        self._tasks: set[asyncio.Task[None]] = set()
        self._started_tape = False
        self._percents = 0
        self._line_start = 0
        if self.options.dr_off:
            self.faults.add("dr-off")
        if self.options.never_dc1:
            self.faults.add("never-dc1")

    # -- options and faults --------------------------------------------------------------------

    @property
    def high_water(self) -> int:
        return self.options.high_water or self.options.buffer_size - self._tolerance

    @property
    def low_water(self) -> int:
        if self.options.low_water is not None:
            return self.options.low_water
        return self.options.buffer_size // 2

    @property
    def tolerance(self) -> int:
        return self._tolerance

    def set_fault(self, name: str, arg: str | None = None) -> None:
        """Switch a fault on (names in :data:`FAULTS`)."""
        check_switch(FAULTS, name, arg)
        try:
            if name == "adapter-latency":
                self._latency_ms = float(arg or "16")
            elif name == "line-lag":
                self._lag_ms = float(arg or "16")
            elif name == "parity-noise":
                self._parity_rate = float(arg or "0.01")
            elif name == "noise":
                self.noise = LineNoise.parse(arg)
            elif name == "tolerance-2":
                self._tolerance = 2
        except ValueError:
            raise UsageError(f"fault {name}: {arg!r} is not a number") from None
        self.faults.add(name)
        if name == "dr-off" and self.activity in (Activity.READING, Activity.PUNCHING):
            self._alarm(86)

    def clear_fault(self, name: str) -> None:
        self.faults.discard(name)
        if name == "adapter-latency":
            self._latency_ms = self.options.adapter_latency_ms
        elif name == "line-lag":
            self._lag_ms = self.options.line_lag_ms
        elif name == "parity-noise":
            self._parity_rate = self.options.parity_noise
        elif name == "noise":
            self.noise = None
        elif name == "tolerance-2":
            self._tolerance = self.options.tolerance

    async def operator_after(self, fault: str) -> None:
        """The operator at the control once fault ``fault`` went: RESET for the alarm it
        left (its cause, a lost DR or a noisy line, is gone now; the control keeps the alarm
        until RESET all the same); a control that sent no DC1 has its READ or CYCLE START
        pressed again (it asks for the tape now)."""
        if self.activity == Activity.ALARM:
            self.reset()
        elif (
            fault == "never-dc1"
            and self.activity == Activity.READING
            and not self._program_came
            and not self._stopped
        ):
            self._signal(DC1, rts=True)

    async def operator_clear(self) -> None:
        """RESET at the control, once its alarm was looked into: the alarm cleared (SYN to
        the host), the reader ready again. An alarm whose cause is still there (DR still
        off) comes back as the next read begins. Nothing when no alarm shows."""
        if self.activity == Activity.ALARM:
            self.reset()

    @property
    def alarmed(self) -> bool:
        """The control shows an alarm: only RESET clears it."""
        return self.activity == Activity.ALARM

    @property
    def display(self) -> str:
        """What its screen shows: ``ALARM 086 DR OFF``, else its mode and what it does
        (``RMT reading``)."""
        if self.activity == Activity.ALARM and self.alarms:
            alarm = self.alarms[-1]
            return f"ALARM {alarm.code:03d} {alarm.text}"
        return f"{self.mode} {self.activity}"

    # -- the panel -----------------------------------------------------------------------------

    def start(self) -> None:
        """Power on: the automatic operator (``auto_operator``) presses READ (EDIT) or CYCLE
        START (RMT) now if a host is connected, else as one connects; without, it waits."""
        self._auto()

    async def stop(self) -> None:
        """Shut down: a read, punch or cycle under way and the automatic operator end."""
        await cancel_and_wait(self._tasks)

    def set_mode(self, mode: Mode | str) -> None:
        """The mode switch: it ends a read or punch under way (an alarm stays)."""
        self.mode = Mode(mode)
        if self.activity != Activity.ALARM:
            self._end_transfer()
            self.activity = Activity.IDLE
            self._auto()

    def reset(self) -> None:
        """RESET: clears an alarm and stops whatever runs; the remote-buffer interface says
        so with SYN (spec, "Alarms the host must understand"), so a host holding the alarm
        knows it is gone."""
        self._end_transfer()
        self.activity = Activity.IDLE
        line = self._line
        if line is not None:
            line.set_rts(True)
            if not line.closed:
                self._spawn(line.write(SYN))
        self._auto()

    def read(self) -> None:
        """READ (EDIT mode): ask for a tape into memory."""
        if self.mode != Mode.EDIT:
            raise UsageError(f"READ reads into memory in EDIT mode, not {self.mode}")
        self._begin_read()

    def cycle_start(self) -> None:
        """CYCLE START: RMT runs the tape as it comes; MEM runs the selected program."""
        if self.activity == Activity.ALARM or self.activity != Activity.IDLE:
            return
        if self.mode == Mode.RMT:
            self._begin_read()
        elif self.mode == Mode.MEM and self.selected in self.memory:
            run = self._new_run(self.selected)
            self.activity = Activity.RUNNING
            self._exec_task = asyncio.ensure_future(self._run_memory(run))

    def punch(self, number: int | None = None) -> None:
        """PUNCH (EDIT mode): send program ``number`` (all of memory: None) to the host."""
        if self.activity != Activity.IDLE:
            raise UsageError(f"the control is {self.activity}: PUNCH waits")
        chosen = sorted(self.memory) if number is None else [number]
        missing = [n for n in chosen if n not in self.memory]
        if missing or not chosen:
            raise UsageError(f"no program O{missing[0] if missing else ''} in memory")
        text = "".join(self.memory[n] for n in chosen)
        lead = self.options.punch_leader
        data = DC2 + tape.frame(text, leader=lead, trailer=lead, percent=True) + DC4
        self.activity = Activity.PUNCHING
        self._punch_go.set()
        self._punch_task = asyncio.ensure_future(self._punch(data))

    def _auto(self) -> None:
        if not self.options.auto_operator or self.activity != Activity.IDLE:
            return
        if self._line is None or self._line.closed:
            return
        if self.mode == Mode.EDIT:
            self._begin_read()
        elif self.mode == Mode.RMT:
            self.cycle_start()

    # -- reading -------------------------------------------------------------------------------

    def _begin_read(self) -> None:
        if self.activity != Activity.IDLE:
            return
        self.activity = Activity.READING
        self._buffer.clear()
        self._lf_at.clear()
        self._tape.clear()
        self._stopped = False
        self._after_dc3 = 0
        self._started_tape = False
        self._program_came = False
        self._percents = self._line_start = 0
        if "dr-off" in self.faults:
            self._alarm(86)
            return
        if self.mode == Mode.RMT:
            run = self._new_run(0)
            self._machine = Machine(self.options.motion(), trace=False)
            self._free_at = self._read_began = self.clock.monotonic()
            self._tape_done = False
            self._exec_task = asyncio.ensure_future(self._execute(run))
        if "never-dc1" not in self.faults:
            self._signal(DC1, rts=True)
            if self.options.auto_operator:
                self._read_serial += 1
                serial, seen = self._read_serial, self.chars_read
                self._later(_OPERATOR_PATIENCE_S, self._press_again, serial, seen)

    def _press_again(self, serial: int, seen: int) -> None:
        """The automatic operator looks again: while the control still waits for its program
        (only leader, trailer or nothing came) and nothing came since it last looked
        (``seen``), it presses READ again. Its DC1 may have gone to a host not listening yet,
        or been lost on the line; stray characters (the last tape's trailer) do not make it
        stop looking, a program under way does."""
        if serial != self._read_serial or self.activity != Activity.READING:
            return
        if self._program_came:
            return
        if self.chars_read == seen and not self._stopped and "never-dc1" not in self.faults:
            self._signal(DC1, rts=True)
        self._later(_OPERATOR_PATIENCE_S, self._press_again, serial, self.chars_read)

    def _signal(self, code: bytes, *, rts: bool | None = None, at: float = 0.0) -> None:
        """Send DC1/DC3 (and RTS with CS flow) through the adapter's delay, from ``at`` (loop
        time; a character that crossed the line late is answered when it crossed)."""
        line = self._line
        if line is None or line.closed:
            return
        # Only a held character can cross after now (line-lag); otherwise send at once, as
        # before: the host's backstop counts on the DC3 leaving as soon as it is due.
        wait = max(0.0, at - self.clock.monotonic()) if self._lag_ms else 0.0
        delay = wait + self._latency_ms / 1000.0 / self.time_scale

        def send() -> None:
            if line.closed:
                return
            if rts is not None and self.options.cs_flow:
                line.set_rts(rts)
            self._spawn(line.write(code))

        if delay > 0:
            self._later(delay, send)
        else:
            send()

    def _take(self, data: bytes, line: DeviceLine) -> None:
        """Characters through the line while reading, each at the time it crossed."""
        char_time = line.settings.char_time if line.pacing else 0.0
        last = line.last_ready
        if self._lag_ms:
            lag = self._lag_rng.uniform(0.0, self._lag_ms) / 1000.0 / self.time_scale
            last = max(last + lag, self._held_until + len(data) * char_time)
            self._held_until = last
        n = len(data)
        high_water = self.high_water  # read once a chunk: it is asked at every character
        buffer = self._buffer
        if (
            not self._stopped
            and not self._parity_rate
            and self.mode != Mode.EDIT
            and len(buffer) + n < high_water
            and data.isascii()
        ):
            # The usual chunk, taken whole: what _take_each does character by character
            # when none of them stops, fills or garbles anything.
            self.chars_read += n
            if not self._program_came and data.translate(None, _BEFORE_PROGRAM_BYTES):
                self._program_came = True
            buffer += data
            i = data.find(b"\n")
            while i >= 0:
                self._lf_at.append(last - (n - 1 - i) * char_time)
                i = data.find(b"\n", i + 1)
            self.peak_buffer = max(self.peak_buffer, len(buffer))
        elif not self._take_each(data, last, char_time, high_water):
            return  # the read ended (an alarm, or the tape stored)
        if self.mode != Mode.EDIT and (0x0A in data or 0x25 in data):
            # The execution waits for a block's LF (or the closing %): nothing else wakes it,
            # which spares a wake-up a burst with hundreds of controls in one process.
            self._block_ready.set()

    def _take_each(self, data: bytes, last: float, char_time: float, high_water: int) -> bool:
        """:meth:`_take`, character by character; False once the read has ended."""
        n, buffer = len(data), self._buffer
        for j, byte in enumerate(data):
            if self._stopped and last - (n - 1 - j) * char_time > self._dc3_at:
                self._after_dc3 += 1
                self.overflow_chars = max(self.overflow_chars, self._after_dc3)
                if self._after_dc3 > self._tolerance:
                    self._alarm(87, f"{self._after_dc3} characters after DC3")
                    return False
            if self._parity_rate and self._rng.random() < self._parity_rate:
                self._alarm(85, f"parity error on 0x{byte:02X}")
                return False
            if byte & 0x80:
                self._alarm(85, f"0x{byte:02X} is not a 7-bit ISO character")
                return False
            self.chars_read += 1
            if byte not in _BEFORE_PROGRAM:
                self._program_came = True
            if self.mode == Mode.EDIT:
                self._tape.append(byte)
                if self._tape_ends(byte):
                    self._store()
                    return False
                continue
            at = last - (n - 1 - j) * char_time
            buffer.append(byte)
            if byte == 0x0A:
                self._lf_at.append(at)
            if len(buffer) >= high_water:
                # The blocks the machine has started by now have left the buffer, even when
                # this process got to them late: the control runs in real time.
                self._advance(at)
            if len(buffer) > self.peak_buffer:
                self.peak_buffer = len(buffer)
            if not self._stopped and len(buffer) >= high_water:
                # Counted from the character that filled it, as a control does in real time
                # (even when this process got to it late).
                self._send_dc3(at)
        return True

    def _send_dc3(self, at: float) -> None:
        self._dc3_at = at
        self._stopped = True
        self._after_dc3 = 0
        self.dc3_sent += 1
        self._signal(DC3, rts=False, at=at)

    def _tape_ends(self, byte: int) -> bool:
        """Whether ``byte`` (just appended to the tape) ends it: the closing %, or without %
        framing the end of a block that ends the program (M02, M30, M99)."""
        if byte == 0x25:
            self._percents += 1
            return self._percents == 2
        if byte != 0x0A:
            return False
        start = self._line_start
        self._line_start = len(self._tape)
        if self._percents:
            return False
        text = self._tape[start:].decode("latin-1").rstrip("\r\n\x00")
        return bool(PROGRAM_ENDS & set(parse_block(0, text, []).m_codes))

    def _store(self) -> None:
        """The tape is in: its programs into memory by O-number; DC3 and out of the read."""
        text = tape.unframe(bytes(self._tape))
        for program in tape.split_programs(text):
            self.memory[program.number] = program.text
            self.selected = program.number
        self._finish_read()

    def _finish_read(self) -> None:
        self._send_dc3(self.clock.monotonic())
        self._stopped = False
        self.activity = Activity.IDLE
        self._later(0.05, self._auto)

    # -- punching ------------------------------------------------------------------------------

    async def _punch(self, data: bytes) -> None:
        line = self._line
        try:
            if line is None or "dr-off" in self.faults:
                self._alarm(86)
                return
            step = 4  # it stops within a few characters of a DC3 (the spec allows 10)
            for i in range(0, len(data), step):
                if not self._punch_go.is_set():
                    self.punch_overrun = max(self.punch_overrun, self.punched - self._paused_at)
                    self.punch_held = True
                await self._punch_go.wait()
                self.punch_held = False
                if self.activity != Activity.PUNCHING:
                    return
                await line.write(data[i : i + step])
                await line.drain()
                self.punched += len(data[i : i + step])
            self.activity = Activity.IDLE
        except (LinkClosed, LinkError):
            self.activity = Activity.IDLE

    # -- alarms and the line -------------------------------------------------------------------

    def _alarm(self, code: int, detail: str = "") -> None:
        self.alarms.append(Alarm(code, ALARMS[code], detail))
        self._end_transfer()
        self.activity = Activity.ALARM
        line = self._line
        if line is not None and not line.closed:
            self._spawn(line.write(alarm_report(code)))

    def _later(self, seconds: float, callback: Callable[..., object], *args: object) -> None:
        clock = self.clock
        clock.call_at(clock.monotonic() + seconds, callback, *args)

    def _spawn(self, coro: Coroutine[object, object, None]) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _end_transfer(self) -> None:
        for task in (self._exec_task, self._punch_task):
            if task is not None and task is not asyncio.current_task():
                task.cancel()
        self._exec_task = self._punch_task = None
        self._stopped = False
        self._buffer.clear()
        self._lf_at.clear()

    async def session(self, line: DeviceLine) -> None:
        """Serve one host: read what it sends and act by what the control is doing."""
        self._line = line
        line.set_rts(True)
        if self.activity == Activity.READING and not self._stopped and not self.chars_read:
            # It asked before a host was there (no cable, no device server): ask again.
            self._signal(DC1, rts=True)
        self._auto()
        with contextlib.suppress(LinkClosed, LinkError):
            while True:
                data = await line.read()
                if not data:
                    continue
                if self.activity == Activity.READING:
                    self._take(data, line)
                elif self.activity == Activity.PUNCHING:
                    for byte in data:
                        if byte == tape.Code.DC3 and self._punch_go.is_set():
                            self._punch_go.clear()
                            self._paused_at = self.punched
                        elif byte == tape.Code.DC1:
                            self._punch_go.set()
        if self._line is line:
            self._line = None
            if self.activity in (Activity.READING, Activity.PUNCHING):
                self._end_transfer()
                self.activity = Activity.IDLE

    def line_changed(self, line: DeviceLine) -> None:
        """New line settings from the host (RFC 2217): nothing to do, pacing follows."""


def block_of(raw: bytes, number: int = 0) -> Block:
    """One received block, parsed (for the execution and for tests)."""
    return parse_block(number, raw.decode("latin-1").rstrip("\r\n"), [])
