"""IBM 7545 / 7547 SCARA robot controller driver.

One :class:`Ibm7545Robot` per controller; it owns its link and its host-kept state (robot
state 0/1/2 and which partition holds which program), saved in the cell directory::

    robot = await Ibm7545Robot.connect("rfc2217://cellhost:7001", name="robot1",
                                       store=StateStore("cell"))
    await robot.initialize()                   # return home (11), then auto mode (20)
    await robot.download(3, "loadcnc1.rec")    # N record, D records, end record, Ack each
    await robot.go(3)                          # select application 33, start cycle 22
    print(await robot.status())
    await robot.close()

The transactions on the line (X, R, N), their deadlines, the reads of a reject and the
retries of a garbled handshake or D record are the base class's:
:class:`~cellctl.kinds.ibm7545.transactions.RobotTransactions` (its module docstring says how).

The host's state guards every function: :mod:`cellctl.kinds.ibm7545.states` says which function
the source's library answered itself in which state (GO after HALT: "partition empty", code
3; DOWNLOAD outside state 1: "improper startup sequence", code 48), and such a refusal raises
:class:`DeviceError` before any byte goes out. A reject from the controller changes neither
the host's robot state nor its partitions, but for the partition a download was writing:
once its N record went out, its content is unknown until the last Ack (Empty meanwhile).

A ``.rec`` file is decoded whole before a byte goes out, every instruction included
(:meth:`ProgramFile.parse`): a record the controller would refuse is a UsageError naming the
file and the line.

A download the controller refused for a transmission error (reject 16 "record format error",
96, 112, an EOT that was a garbled Ack, a stray byte where an Ack belongs, or no Ack after the
controller had already acknowledged part of this download) is sent again from its N record,
up to ``download_retries`` times; any other reject (48, 80, 83, ...) is raised at once, and
so is a 16 for the same record as the try before (the record's content, not the line: a
retry cannot fix it). Before a retry the host sends a record the controller cannot take
(``E`` CR LF), so whatever it was receiving ends in a reject, and discards what comes back
until the line is quiet. A download cancelled half-way (Ctrl-C) resyncs the same way (see
:mod:`~cellctl.kinds.ibm7545.transactions`).
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable
from pathlib import Path

from cellctl.clock import Clock
from cellctl.drivers.state import StateStore
from cellctl.errors import CellctlError, DeviceError, LinkTimeout, SignalTimeout, UsageError
from cellctl.kinds.families import HostStatus, RecordsProgress
from cellctl.kinds.ibm7545.options import ROBOT_CONDITIONS as ROBOT_CONDITIONS
from cellctl.kinds.ibm7545.options import ROBOT_STATES as ROBOT_STATES
from cellctl.kinds.ibm7545.options import RobotConfig as RobotConfig
from cellctl.kinds.ibm7545.options import RobotState as RobotState
from cellctl.kinds.ibm7545.options import robot_condition as robot_condition
from cellctl.kinds.ibm7545.records import (
    HALTING_FLAGS,
    PARTITIONS,
    UNDEFINED_RECORD,
    DiDo,
    ExecuteOperand,
    MachineStatus,
    ProgramFile,
    ReadOperand,
    emulator_input_operand,
    encode_record,
    reject_message,
    select_application_operand,
)
from cellctl.kinds.ibm7545.states import RobotFunction, robot_refusal
from cellctl.kinds.ibm7545.status import RobotCounters as RobotCounters
from cellctl.kinds.ibm7545.status import RobotHalted as RobotHalted
from cellctl.kinds.ibm7545.status import RobotStatus as RobotStatus
from cellctl.kinds.ibm7545.status import _digest, _waits
from cellctl.kinds.ibm7545.transactions import (
    RECORD_FORMAT_ERROR,
    RobotTransactions,
    _AckLost,
    _garbled,
)
from cellctl.kinds.ibm7545.transactions import TRANSMISSION_REJECTS as TRANSMISSION_REJECTS
from cellctl.link import ROBOT_LINE, LineSettings, Link, TrafficLog

# RobotState, RobotConfig and robot_condition live in options.py (the registry reads them
# without importing this driver), RobotStatus, RobotCounters and RobotHalted in status.py,
# TRANSMISSION_REJECTS in transactions.py: all are named here as before.

#: Rejects after which a start needs an initialize first: improper startup sequence (48),
#: manipulator power off (128).
_NEEDS_INITIALIZE = frozenset({48, 128})
#: Reject code the controller gives for selecting an empty partition.
_EMPTY_PARTITION = 83

RetryCallback = Callable[[int, int, CellctlError], None]
"""``on_retry(attempt, limit, error)``, called before a download is sent again."""

ProgressCallback = Callable[[int, int, int], None]
"""``progress(records_done, records_total, bytes_sent)``, called after every Ack."""


class Ibm7545Robot(RobotTransactions):
    """Driver for one IBM 7545/7547 controller over any :class:`Link`."""

    def __init__(
        self,
        link: Link,
        *,
        name: str | None = None,
        store: StateStore | None = None,
        config: RobotConfig | None = None,
        clock: Clock | None = None,
    ) -> None:
        saved = self._attach(link, name, store, clock)
        self.config = config or RobotConfig()
        self.counters = RobotCounters()
        self.state = RobotState(int(saved.get("state", 0)))
        self.partitions: dict[int, str | None] = {p: None for p in PARTITIONS}
        for p, prog in saved.get("partitions", {}).items():
            if int(p) in PARTITIONS:
                self.partitions[int(p)] = prog
        self.digests: dict[int, str] = {int(p): d for p, d in saved.get("digests", {}).items()}
        # Each partition's WAITIs (input, value), and the partition started last: what an
        # executing program may wait for (status names them).
        self.waits: dict[int, list[tuple[int, bool]]] = {
            int(p): [(int(n), bool(v)) for n, v in w] for p, w in saved.get("waits", {}).items()
        }
        self.started: int | None = saved.get("started")
        self._in_reject_read = False
        # A transaction was cut short (saved): resync before the next one (transactions.py).
        self._out_of_step = bool(saved.get("out_of_step", False))
        # The last program downloaded, as sent: (program given, partition, program retargeted,
        # wire pieces, digest). A DNC server sends one program over and over; encoding,
        # retargeting and hashing it again each time was a quarter of the work per record.
        self._last_wire: tuple[ProgramFile, int, ProgramFile, list[bytes], str] | None = None
        self._used: dict[int, float] = {}  # partition -> when its program last ran (LRU)
        # One transaction at a time on the line: a monitor polling status and a scheduler
        # starting programs may share one driver.
        self._lock = asyncio.Lock()

    @classmethod
    async def connect(
        cls,
        url: str,
        *,
        name: str | None = None,
        settings: LineSettings = ROBOT_LINE,
        store: StateStore | None = None,
        config: RobotConfig | None = None,
        trace: TrafficLog | str | Path | None = None,
        clock: Clock | None = None,
    ) -> Ibm7545Robot:
        """Open ``url`` and return a driver on it (the robot's name keys its saved state).

        Raises MachineInUse, before opening anything, when another owner holds the robot.
        """
        return await cls._connect_owned(
            url,
            settings,
            name=name,
            store=store,
            trace=trace,
            build=lambda link: cls(link, name=name or url, store=store, config=config, clock=clock),
            clock=clock,
        )

    # -- host-kept state --------------------------------------------------------------------------

    def _save(self) -> None:
        self._persist(
            {
                "state": self.state,
                "partitions": {str(p): prog for p, prog in self.partitions.items() if prog},
                "digests": {str(p): d for p, d in self.digests.items()},
                "waits": {str(p): w for p, w in self.waits.items() if self.partitions.get(p)},
                "started": self.started,
                "out_of_step": self._out_of_step,
            }
        )

    def _set_state(self, state: RobotState, *, flush: bool = False) -> None:
        self.state = state
        if flush:
            self.partitions = {p: None for p in PARTITIONS}
            self.digests = {}
        self._save()

    def _guard(self, function: RobotFunction, partition: int | None = None) -> None:
        """Refuse ``function`` before any byte goes out if the host's state says so."""
        full = None if partition is None else self.partitions.get(partition) is not None
        refusal = robot_refusal(function, self.state, full)
        if refusal is not None:
            where = f" {partition}" if partition is not None else ""
            raise DeviceError(
                refusal.code,
                refusal.message,
                detail=f"{self.name}: {function.value}{where} refused by the host's state "
                f"(robot state {self.state}): {refusal.why}",
            )

    def holds(self, partition: int, program: ProgramFile) -> bool:
        """True if the host's view says ``partition`` holds exactly ``program``."""
        return self.digests.get(partition) == _digest(program.with_partition(partition))

    # -- the robot family (cellctl.kinds.families.Robot) -------------------------------------------

    @property
    def running(self) -> bool:
        return self.state == RobotState.EXECUTING

    @property
    def ready(self) -> bool:
        return self.state == RobotState.INITIALIZED

    @property
    def cold(self) -> bool:
        return self.state == RobotState.UNINITIALIZED

    def host_status(self) -> HostStatus:
        """The host state in words and its condition (no byte sent)."""
        return HostStatus(RobotState.words(self.state), robot_condition(self.state))

    def needs_initialize(self, error: DeviceError) -> bool:
        return not self.ready or error.code in _NEEDS_INITIALIZE

    async def ensure_program(
        self, name: str, program: ProgramFile, progress: RecordsProgress | None = None
    ) -> int:
        """The partition holding ``program``: downloaded into an empty one, or else into the
        least recently used, only when no partition holds it already."""
        for p in PARTITIONS:
            if self.holds(p, program):
                self._used[p] = self.clock.monotonic()
                return p
        empty = [p for p in PARTITIONS if self.partitions.get(p) is None]
        target = empty[0] if empty else min(PARTITIONS, key=lambda p: self._used.get(p, 0.0))
        await self.download(target, program, progress=progress)
        self._used[target] = self.clock.monotonic()
        return target

    async def start(self, slot: int) -> None:
        """Run the program in partition ``slot`` (GO): the cell's way, with its PLC behind
        the inputs, so STATUS does not look for what the program's WAITIs wait for (no
        transaction more beside the cell's own)."""
        await self.go(slot)
        self.started = None

    async def wait_end(
        self,
        done_output: int,
        *,
        timeout: float,
        poll: float = 0.1,
        watch_every: float = 0.0,
        expected: float = 0.0,
    ) -> None:
        """Wait for the program's "cycle done" output (see :meth:`wait_cycle_end`)."""
        await self.wait_cycle_end(
            done_output, timeout=timeout, poll=poll, watch_every=watch_every, quiet=expected
        )

    # -- what a user wants done -------------------------------------------------------------------

    async def return_home(self) -> None:
        """Move the arm home (X 11): Xoff at once, Xoff while moving, Xon when home."""
        await self._execute(ExecuteOperand.RETURN_HOME, "return home")

    async def auto_mode(self) -> None:
        """Auto-execution mode (X 20); the robot is then initialized (state 1)."""
        await self._execute(ExecuteOperand.AUTO, "auto mode")
        self._set_state(RobotState.INITIALIZED)

    async def initialize(self) -> None:
        """Return home, then auto mode: state 1, ready for downloads."""
        await self.return_home()
        await self.auto_mode()

    async def download(
        self,
        partition: int,
        program: ProgramFile | str | Path,
        *,
        progress: ProgressCallback | None = None,
        on_retry: RetryCallback | None = None,
    ) -> None:
        """Download a compiled program (``.rec`` file or ProgramFile) into ``partition`` 1..5.

        The file is read and decoded (every instruction), the partition checked, and the
        host's state consulted (state 1 only: initialized, no cycle running) before any byte
        is sent. A transmission error sends it again from the N record (up to
        ``download_retries`` times, ``on_retry`` told first); any other reject stops it. A
        download that failed after its N record leaves the partition Empty; one refused
        before leaves it as it was (Empty after a cold start or HALT); DeviceError says why.
        """
        if partition not in PARTITIONS:
            raise UsageError(f"partition must be 1 to 5, not {partition} (partition error)")
        given = program if isinstance(program, ProgramFile) else ProgramFile.load(program)
        prog, pieces, digest = self._wire(given, partition)
        total = len(prog.records)
        try:
            self._guard(RobotFunction.DOWNLOAD)
        except DeviceError:
            if self.state == RobotState.UNINITIALIZED:
                # Cold or halted, every partition was flushed: a program here is a stale view.
                self._forget(partition)
            raise
        what = f"download to partition {partition}"
        async with self._transaction():
            kept = (self.partitions[partition], self.digests.get(partition))
            # Until the last Ack the partition's content is unknown: never trust a half
            # download. Until the line is known in step again, the next transaction (here or
            # after a restart) resyncs first. One save for both.
            self._out_of_step = True
            self._forget(partition)
            reached = [0]  # the farthest piece any try sent (0: the N identifier alone)
            try:
                await self._send_with_retries(pieces, total, what, progress, on_retry, reached)
            except DeviceError:
                self._mark_out_of_step(False)  # the reject was read: the controller is idle
                if reached[0] == 0:  # refused at the N identifier: no record reached it
                    self.partitions[partition] = kept[0]
                    if kept[1] is not None:
                        self.digests[partition] = kept[1]
                    self._save()
                raise
            self._out_of_step = False  # saved below
        self.partitions[partition] = prog.name
        self.digests[partition] = digest
        self.waits[partition] = _waits(prog)
        self._save()

    def _forget(self, partition: int) -> None:
        """The host no longer knows what ``partition`` holds: Empty (saved)."""
        self.partitions[partition] = None
        self.digests.pop(partition, None)
        self._save()

    async def _send_with_retries(
        self,
        pieces: list[bytes],
        total: int,
        what: str,
        progress: ProgressCallback | None,
        on_retry: RetryCallback | None,
        reached: list[int],
    ) -> None:
        """Send the program, again from its N record after a transmission error (see the
        module docstring); ``reached[0]``: the farthest piece any try sent."""
        attempt = 0
        refused_at: int | None = None  # the piece the last record format error answered
        while True:
            at = [0]
            try:
                await self._send_program(pieces, total, what, progress, at)
                return
            except CellctlError as e:
                reached[0] = max(reached[0], at[0])
                if not _garbled(e) or attempt >= self.config.download_retries:
                    raise
                if isinstance(e, DeviceError) and e.code == RECORD_FORMAT_ERROR:
                    if refused_at == at[0]:
                        record = _record_text(pieces, at[0])
                        raise DeviceError(
                            e.code,
                            e.message,
                            detail=f"{e.detail}: record {max(at[0], 1)} ({record}) refused "
                            "twice in a row: its content, not the line (not sent again)",
                        ) from e
                    refused_at = at[0]
                attempt += 1
                self.counters.download_retries += 1
                if on_retry is not None:
                    on_retry(attempt, self.config.download_retries, e)
                await self._resync()

    def _wire(self, given: ProgramFile, partition: int) -> tuple[ProgramFile, list[bytes], str]:
        """``given`` aimed at ``partition``, its wire pieces and digest (the last one kept)."""
        last = self._last_wire
        if last is not None and last[0] is given and last[1] == partition:
            return last[2], last[3], last[4]
        prog = given.with_partition(partition)
        wire = [encode_record(r) for r in prog.records]
        # The identifier goes alone and is acknowledged, then the rest of the N record.
        pieces = [wire[0][:1], wire[0][1:], *wire[1:]]
        digest = _digest(prog)
        self._last_wire = (given, partition, prog, pieces, digest)
        return prog, pieces, digest

    async def _send_program(
        self,
        pieces: list[bytes],
        total: int,
        what: str,
        progress: ProgressCallback | None,
        at: list[int],
    ) -> None:
        """One try: each piece, an Ack for each; ``at[0]``: the piece in flight."""
        self.link.reset_input()
        sent = 0
        for i, piece in enumerate(pieces):
            at[0] = i
            await self.link.write(piece)
            sent += len(piece)
            try:
                await self._expect_ack(piece, what)
            except LinkTimeout as e:
                if i == 0:  # no answer at all: a silent controller, not a garbled line
                    raise LinkTimeout(f"{e}: {self._no_answer()}") from e
                raise _AckLost(str(e)) from e
            if i >= 1:
                self.counters.records_downloaded += 1
                if progress is not None:
                    progress(i, total, sent)

    async def select_application(self, partition: int) -> None:
        """Select the program in ``partition`` (X 3n); reject 83 means the partition is empty."""
        operand = select_application_operand(partition)
        self._guard(RobotFunction.APPLICATION, partition)
        try:
            await self._execute(operand, f"select application {partition}")
        except DeviceError as e:
            if e.code == _EMPTY_PARTITION:
                self.partitions[partition] = None
                self.digests.pop(partition, None)
                self._save()
                raise DeviceError(e.code, "partition empty", detail=e.detail) from e
            raise

    async def start_cycle(self) -> None:
        """Run the selected application (X 22): state 2."""
        self._guard(RobotFunction.START_CYCLE)
        await self._execute(ExecuteOperand.START_CYCLE, "start cycle")
        self._set_state(RobotState.EXECUTING)

    async def go(self, partition: int) -> None:
        """Run the program in ``partition``: select application, then start cycle."""
        if partition not in PARTITIONS:
            raise UsageError(f"partition must be 1 to 5, not {partition} (starting function error)")
        self._guard(RobotFunction.GO, partition)
        await self.select_application(partition)
        await self.start_cycle()
        self.started = partition
        self._save()

    async def stop(self) -> None:
        """Stop the cycle (X 23): state 1. Accepts Ack or Xoff ... Xon as completion."""
        await self._execute(ExecuteOperand.STOP_CYCLE, "stop cycle")
        self._set_state(RobotState.INITIALIZED)

    async def halt(self) -> None:
        """Stop the cycle and treat the robot as uninitialized: state 0, partitions flushed."""
        await self._execute(ExecuteOperand.STOP_CYCLE, "halt")
        self._set_state(RobotState.UNINITIALIZED, flush=True)

    async def reset_errors(self) -> None:
        """ERRESET: clear machine-status and reject-status errors (operand configurable)."""
        await self._execute(self.config.erreset_operand, "error reset")

    async def machine_status(self) -> MachineStatus:
        """The controller's 2 status bytes (R 01), decoded."""
        return MachineStatus.from_bytes(
            await self._read(ReadOperand.MACHINE_STATUS, "machine status", 2)
        )

    async def status(self, *, waits: bool = False) -> RobotStatus:
        """Host state, decoded controller status and which partitions are full. ``waits``
        (the operator's STATUS): while executing, also the inputs its program's WAITIs wait
        for that are not so now (one DI/DO read more: a monitor's poll leaves it out)."""
        machine = await self.machine_status()
        waiting: list[tuple[int, bool]] = []
        pending = self.waits.get(self.started or 0, []) if waits else []
        if self.state == RobotState.EXECUTING and pending:
            dido = await self.io()
            waiting = [(n, v) for n, v in pending if dido.input(n) != v]
        return RobotStatus(self.state, machine, dict(self.partitions), waiting)

    async def set_input(self, port: int, value: bool) -> None:
        """Drive input ``port`` (1..16) on an emulator with no PLC behind it (an emulator-only
        operand: a real controller's inputs come from its wiring, and it refuses)."""
        operand = emulator_input_operand(port, value)  # refused before a byte goes out
        try:
            await self._execute(operand, f"set input {port}")
        except DeviceError as e:
            if e.code != UNDEFINED_RECORD:
                raise
            raise DeviceError(
                e.code,
                e.message,
                detail=f"{self.name}: a real IBM 7545 takes its inputs from its wiring, not "
                "from the host: drive the PLC output wired to it (`cellctl plc set NAME 1`)",
            ) from e

    async def reject_status(self) -> tuple[int, str]:
        """The reject status (R 02): code and the source's message."""
        code = (await self._read(ReadOperand.REJECT_STATUS, "reject status", 1))[0]
        return code, reject_message(code)

    async def io(self) -> DiDo:
        """Digital inputs and outputs (R 10): 16 each."""
        return DiDo.from_bytes(await self._read(ReadOperand.DIDO, "DI/DO status", 4))

    async def wait_output(
        self,
        line: int,
        value: bool,
        *,
        timeout: float,
        poll: float = 0.1,
        watch: bool = False,
        watch_every: float = 0.0,
        quiet: float = 0.0,
    ) -> DiDo:
        """Poll DI/DO until output ``line`` (1-16) is ``value``; SignalTimeout after ``timeout``.

        The controller tells nothing unasked, so a program signals progress on an output
        (the cell's programs raise a "cycle done" output before END) and the host polls.
        With ``watch`` the machine status is read too, on the first look and then at most
        every ``watch_every`` s (every poll if 0): a servo error or a power failure that
        aborted the cycle raises :class:`RobotHalted` then instead of the timeout.

        ``quiet``: seconds from now the output cannot change yet (a cycle's known least
        time): DI/DO is first read then, the status still watched meanwhile. Each read is
        tens of milliseconds of a slow line; polling a cycle of seconds from its start
        filled the line for nothing.
        """
        clock = self.clock
        now = clock.monotonic()
        deadline = now + timeout
        asked_from = now + min(max(quiet, 0.0), timeout)
        watched = -math.inf
        while True:
            if clock.monotonic() >= asked_from:
                dido = await self.io()
                if dido.output(line) == value:
                    return dido
            if watch and clock.monotonic() - watched >= watch_every:
                watched = clock.monotonic()
                status = await self.machine_status()
                if status.flags & HALTING_FLAGS:
                    self._set_state(
                        RobotState.UNINITIALIZED
                    )  # the cycle was aborted; the controller needs INIT
                    raise RobotHalted(status, f"{self.name}: cycle aborted")
            now = clock.monotonic()
            if now >= deadline:
                raise SignalTimeout(
                    f"{self.name}: output {line} did not go {int(value)} within {timeout:g} s"
                )
            wake = now + poll
            if now < asked_from:
                # Quiet: up to the first DI/DO read, or the next status look before it.
                wake = asked_from
                if watch:
                    wake = min(wake, watched + max(watch_every, poll))
            await clock.sleep(max(0.0, min(wake, deadline) - now))

    async def wait_cycle_end(
        self,
        done_output: int,
        *,
        timeout: float,
        poll: float = 0.1,
        watch_every: float = 0.0,
        quiet: float = 0.0,
    ) -> None:
        """Wait for the running program's "cycle done" output (watching the machine status
        every ``watch_every`` s, the output from ``quiet`` s on, see :meth:`wait_output`);
        the robot is then state 1."""
        await self.wait_output(
            done_output,
            True,
            timeout=timeout,
            poll=poll,
            watch=True,
            watch_every=watch_every,
            quiet=quiet,
        )
        self._set_state(RobotState.INITIALIZED)


def _record_text(pieces: list[bytes], index: int) -> str:
    """The record piece ``index`` of a download belongs to, as a .rec file writes it."""
    if index <= 1:
        return (pieces[0] + pieces[1]).decode("ascii").strip()
    return pieces[index].decode("ascii").strip()
