"""Benchmark: the 2,000-line sample program to the mill emulator over RFC 2217, line paced at
4800 7E2, machining time scaled down.

Reports the characters per second achieved while blocks were on the line and the ratio to the
line rate (4800 / 11 = 436.36 chars/s). Transfer time of a block runs from its first byte
written to the controller taking it (CTS low); the emulator's machining between blocks (CTS
low until READY) is excluded and printed separately. Goal: ratio >= 0.98.

    .venv/bin/python bench/mill_download.py [--time-scale 1000]

The last line is machine-readable.
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import time
from pathlib import Path

from cellctl.drivers.state import StateStore
from cellctl.emulators.serve import serve
from cellctl.kinds.dyna2400.driver import Dyna2400Mill, MillConfig
from cellctl.kinds.dyna2400.emulator import Dyna2400Emulator, OperatorDelays
from cellctl.link import MILL_LINE

ROOT = Path(__file__).resolve().parent.parent
PROGRAM = ROOT / "examples" / "programs" / "toy_mill_table_finish_cnc2.dyn"
SETUP = ROOT / "examples" / "programs" / "cnc2_setup.dyn"


async def bench(time_scale: float) -> None:
    emulator = Dyna2400Emulator(
        time_scale=time_scale, delays=OperatorDelays(power_on=1.0, keys=1.0, setup=200.0)
    )
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
                await mill.download(PROGRAM)
                wall = time.monotonic() - started
                timings = mill.last_download
    finally:
        await server.close()
    lines = len(PROGRAM.read_text().splitlines())
    chars = sum(t.bytes for t in timings)
    transfer = sum(t.transfer_s for t in timings)
    machining = sum(t.machining_s for t in timings)
    line_rate = MILL_LINE.chars_per_second
    rate = chars / transfer
    for t in timings:
        print(
            f"block {t.block}: {t.lines} lines {t.bytes} chars  transfer {t.transfer_s:.2f} s "
            f"({t.bytes / t.transfer_s:.1f} chars/s)  machining {t.machining_s:.2f} s"
        )
    print(
        f"line {MILL_LINE}: {line_rate:.2f} chars/s; time scale {time_scale:g}; wall {wall:.1f} s"
    )
    print(f"chars/s (transfer time only): {rate:.2f}  ratio {rate / line_rate:.4f} (goal 0.98)")
    print(
        f"program_lines={lines} blocks={len(timings)} chars={chars} chars_per_s={rate:.2f} "
        f"transfer_s={transfer:.2f} machining_s={machining:.2f} ratio={rate / line_rate:.4f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--time-scale", type=float, default=1000.0)
    args = parser.parse_args()
    asyncio.run(bench(args.time_scale))


if __name__ == "__main__":
    main()
