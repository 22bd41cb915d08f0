"""Benchmark: the 2,000-line sample program to the mill emulator over RFC 2217, line paced at
4800 7E2, machining time scaled down.

Reports the characters per second achieved while blocks were on the line and the ratio to the
line rate (4800 / 11 = 436.36 chars/s). A block's time runs from the moment the controller
asked for it (READY: the emulator raising RTS after machining the block before; for the first
block, the driver starting to send) to the controller taking it (CTS low), so the driver's gap
between READY and the block's first byte -- noticing READY, its own bookkeeping -- counts
against the ratio. The emulator's machining between blocks (CTS low until READY) is excluded
and printed separately, and so is the driver's gap. Goal: ratio >= 0.98.

    .venv/bin/python bench/mill_download.py [--time-scale 1000]

The last line is machine-readable.
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import time
from pathlib import Path

from cellctl.drivers.mill import Dyna2400Mill, MillConfig
from cellctl.drivers.state import StateStore
from cellctl.emulators.mill import Dyna2400Emulator, OperatorDelays
from cellctl.emulators.serve import serve
from cellctl.errors import CellctlError
from cellctl.link import MILL_LINE

ROOT = Path(__file__).resolve().parent.parent
PROGRAM = ROOT / "examples" / "programs" / "toy_mill_table_finish_cnc2.dyn"
SETUP = ROOT / "examples" / "programs" / "cnc2_setup.dyn"


class TimedMill(Dyna2400Emulator):
    """The emulator, noting when it raised READY (RTS): the moment it asked for a block."""

    ready_times: list[float]

    def _set_rts(self, level: bool) -> None:
        if level and not self.rts:
            self.ready_times.append(time.monotonic())
        super()._set_rts(level)


async def bench(time_scale: float) -> None:
    emulator = TimedMill(
        time_scale=time_scale, delays=OperatorDelays(power_on=1.0, keys=1.0, setup=200.0)
    )
    emulator.ready_times = []
    error = ""
    server = await serve(emulator, "rfc2217://127.0.0.1:0", MILL_LINE, pacing=True)
    emulator.start()
    try:
        with tempfile.TemporaryDirectory() as cell:
            mill = await Dyna2400Mill.connect(
                server.url,
                name="bench",
                settings=MILL_LINE,
                store=StateStore(cell),
                config=MillConfig(ready_wait=10.0),
            )
            async with mill:
                await mill.initialize(SETUP)
                await mill.link.wait_cts(True, timeout=30)
                await mill.status()
                started = time.monotonic()
                try:
                    await mill.download(PROGRAM)
                except CellctlError as e:  # the run failed: its line says so, ratio 0
                    error = str(e)
                wall = time.monotonic() - started
                timings = mill.last_download
    finally:
        await server.close()
    lines = len(PROGRAM.read_text().splitlines())
    if error:
        print(f"the download failed: {error}")
        print(f"program_lines={lines} blocks={len(timings)} errors=1 ratio=0")
        return
    chars = sum(t.bytes for t in timings)
    asked: list[float] = []  # when the controller asked for each block
    for i, t in enumerate(timings):
        if i == 0:
            asked.append(t.started)
            continue
        before = timings[i - 1].taken
        ready = [r for r in emulator.ready_times if before < r <= t.started + 1e-3]
        if not ready:
            raise SystemExit(f"block {t.block}: no READY seen between blocks")
        asked.append(min(ready[0], t.started))
    gaps = [t.started - a for t, a in zip(timings, asked, strict=True)]
    counted = [t.taken - a for t, a in zip(timings, asked, strict=True)]
    transfer = sum(counted)
    machining = sum(
        a - prev.taken for prev, a in zip(timings, asked[1:], strict=False)
    )  # CTS low after a block was taken, until READY: the controller's time
    line_rate = MILL_LINE.chars_per_second
    rate = chars / transfer
    for t, gap, c in zip(timings, gaps, counted, strict=True):
        print(
            f"block {t.block}: {t.lines} lines {t.bytes} chars  READY to taken {c:.2f} s "
            f"({t.bytes / c:.1f} chars/s; driver's gap after READY {gap * 1e3:.1f} ms)"
        )
    print(
        f"line {MILL_LINE}: {line_rate:.2f} chars/s; time scale {time_scale:g}; wall {wall:.1f} s"
    )
    print(
        f"chars/s (READY to taken, the driver's gaps included): {rate:.2f}  "
        f"ratio {rate / line_rate:.4f} (goal 0.98); machining {machining:.2f} s, "
        f"driver's gaps {sum(gaps) * 1e3:.1f} ms in all, max {max(gaps) * 1e3:.1f} ms"
    )
    print(
        f"program_lines={lines} blocks={len(timings)} chars={chars} chars_per_s={rate:.2f} "
        f"transfer_s={transfer:.2f} gaps_ms={sum(gaps) * 1e3:.1f} gap_max_ms={max(gaps) * 1e3:.1f} "
        f"machining_s={machining:.2f} errors={int(bool(error))} ratio={rate / line_rate:.4f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--time-scale", type=float, default=1000.0)
    args = parser.parse_args()
    asyncio.run(bench(args.time_scale))


if __name__ == "__main__":
    main()
