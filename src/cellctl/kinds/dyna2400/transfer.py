"""How a validated program crosses the line to a Dyna 2400: block by block, or line by line.

The driver's :meth:`~cellctl.kinds.dyna2400.driver.Dyna2400Mill.download` and
:meth:`~cellctl.kinds.dyna2400.driver.Dyna2400Mill.line_execute` check the program and the
host's state, then hand the mill and the program's pieces to these functions::

    await stream_blocks(mill, result.blocks, result.toolpath.block_seconds,
                        wait=True, progress=print)
    await send_lines(mill, lines, print)

They drive the mill through its link helpers (``_send``, ``_send_block``, ``_wait_ready``,
its readiness: :class:`~cellctl.kinds.dyna2400.line.MillLine`) and move its host-kept state
as the blocks are taken and finish.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from cellctl.errors import DeviceError, LinkTimeout
from cellctl.kinds.dyna2400.dynalan import Block, BlockLine, Kind
from cellctl.kinds.dyna2400.dynalan.table import LINE_END
from cellctl.kinds.dyna2400.status import BlockTiming, Progress, ProgressCallback

if TYPE_CHECKING:
    from cellctl.kinds.dyna2400.driver import Dyna2400Mill


async def stream_blocks(
    mill: Dyna2400Mill,
    blocks: Sequence[Block],
    estimates: Sequence[float],
    *,
    wait: bool,
    progress: ProgressCallback | None,
) -> None:
    """Send ``blocks`` one by one as the controller asks (DOWNLOAD), each block's machining
    estimate in ``estimates``; the last leaves the mill in state 3 unless ``wait`` (state 2).
    Keeps each block's :class:`BlockTiming` in ``mill.last_download``."""
    bytes_total = sum(len(b.wire()) + 1 for b in blocks)
    lines_total = sum(len(b.lines) for b in blocks)
    done_bytes = done_lines = 0
    mill.last_download = []
    report = progress or (lambda p: None)
    # The run's estimate: each block's line time, then its cut (the toolpath's, in the
    # machine's time); ``before[i]`` is where block i+1 starts.
    wire_s = [mill._wire_time(len(b.wire()) + 1) for b in blocks]
    cut_s = [estimates[i] / mill.config.time_scale for i in range(len(blocks))]
    before = [sum(wire_s[:i]) + sum(cut_s[:i]) for i in range(len(blocks) + 1)]

    def machining(k: int) -> Progress:
        """Block k was taken: the machine cuts it (the estimate runs to its end)."""
        return Progress(
            k,
            len(blocks),
            done_lines,
            lines_total,
            done_bytes,
            bytes_total,
            "machining",
            before[-1],
            before[k - 1] + wire_s[k - 1],
            before[k],
            mill.clock.now(),
            True,
        )

    for block in blocks:
        k = block.index
        if k > 1:
            report(machining(k - 1))
            await wait_block_done(mill, blocks[k - 2], estimates[k - 2])
            mill._set_state(2)
        wire = len(block.wire()) + 1
        timing = BlockTiming(k, wire, len(block.lines), mill.clock.monotonic())
        mill.last_download.append(timing)
        base_bytes, base_lines = done_bytes, done_lines

        def on_line(
            n: int, sent: int, k: int = k, b: int = base_bytes, l0: int = base_lines
        ) -> None:
            start = before[k - 1]
            report(
                Progress(
                    k,
                    len(blocks),
                    l0 + n,
                    lines_total,
                    b + sent,
                    bytes_total,
                    "sending",
                    before[-1],
                    start + mill._wire_time(sent),
                    start + wire_s[k - 1],
                    mill.clock.now(),
                    True,
                )
            )

        await mill._send_block(block, timing, on_line, run_s=block_budget(mill, estimates[k - 1]))
        mill._set_state(3)
        done_bytes += wire
        done_lines += len(block.lines)
    if wait:
        report(machining(len(blocks)))
        await wait_block_done(mill, blocks[-1], estimates[-1])
        mill._set_state(2)
    report(
        Progress(
            len(blocks),
            len(blocks),
            lines_total,
            lines_total,
            bytes_total,
            bytes_total,
            "done",
            before[-1],
            before[-1],
            before[-1],
            mill.clock.now(),
        )
    )


def block_budget(mill: Dyna2400Mill, estimate: float) -> float:
    """How long a block of ``estimate`` seconds may run: times ``block_margin``, plus
    ``block_extra``."""
    return estimate * mill.config.block_margin + mill.config.block_extra


async def wait_block_done(mill: Dyna2400Mill, block: Block, estimate: float) -> None:
    """Wait for ``block`` to finish (within :func:`block_budget`)."""
    timeout = block_budget(mill, estimate)
    if not await mill._wait_ready(timeout):
        raise DeviceError(
            2,
            "Machine executing program",
            detail=f"block {block.index} of {block.count} still running after "
            f"{timeout:.0f} s (CTS low)",
        )
    if mill.last_download and mill.last_download[-1].block == block.index:
        mill.last_download[-1].done = mill.clock.monotonic()


async def send_lines(
    mill: Dyna2400Mill, lines: Sequence[BlockLine], progress: ProgressCallback | None
) -> None:
    """Send ``lines`` one at a time, each once CTS is high (LINE EXECUTE)."""
    total_bytes = sum(len(line.render()) + 2 for line in lines)
    sent = 0
    for n, line in enumerate(lines, start=1):
        if not await mill._wait_ready(
            mill.config.ready_wait if n == 1 else mill.config.block_extra
        ):
            raise DeviceError(4, "Machine not ready", detail=f"before line {n}")
        data = line.render().encode("ascii") + LINE_END
        lows = mill._ready.lows
        await mill._send(data)
        sent += len(data)
        if line.statement is not None and line.statement.kind not in (
            Kind.COMMENT,
            Kind.BLANK,
        ):
            try:
                await mill._ready.wait(
                    False,
                    mill.config.accept_timeout + mill._wire_time(len(data)),
                    lows_before=lows,
                )
            except LinkTimeout:
                raise LinkTimeout(f"{mill.name}: the controller did not take line {n}") from None
        if progress:
            progress(Progress(1, 1, n, len(lines), sent, total_bytes, "sending"))
    await mill._wait_ready(mill.config.block_extra)
