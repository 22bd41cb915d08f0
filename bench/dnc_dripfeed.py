"""Benchmark: drip-feed a 3-D surfacing program (about 1 MB, 1 mm segments) at 9600 7E2 into
an emulated control (256-character buffer, DC3 tolerance 10) through an adapter of 0, 2, 8
and 16 ms latency, then read a program into memory at each latency.

For each latency it prints ``latency_ms= overflows= total_s= bound_s= time_ratio= stall_s=
stall_bound_s= stall_ratio=``: total_s (from the control's DC1 to the end of its last block)
and stall_s (the control's own record of the time its axes waited for data) against an ideal
host's, computed from the program, the line rate and the control's motion model
(bench/_dnc.py: it sends at the line rate from DC1 to DC3 and hears both at once). The fifth
line: read-in to memory, the control's characters/s over the line rate (from its DC1 to its
storing the closing ``%``), with overflows. Goals: overflows 0, time_ratio <= 1.03,
stall_ratio <= 1.02, read-in >= 0.97.

Time is scaled (``--time-scale``): the line's baud rate, the adapter's latency and the motion
all run that many times faster, so every figure is in the control's time. The host (the
iso-cnc driver, as ``cellctl dnc drip`` uses it) and the control run in one process over a
real TCP socket (``--transport``: socket, pty or rfc2217).

    .venv/bin/python bench/dnc_dripfeed.py [--size 1000000] [--time-scale 20]
    .venv/bin/python bench/dnc_dripfeed.py --size 60000 --readin-size 20000   # a quick run

The last line is machine-readable.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine_line
from _dnc import TimedControl, ideal_drip, surfacing_program
from cellctl.drivers.state import StateStore
from cellctl.emulators.cell import scaled_line
from cellctl.emulators.serve import serve
from cellctl.errors import CellctlError
from cellctl.kinds.iso_cnc.driver import IsoCncDriver, IsoCncOptions
from cellctl.kinds.iso_cnc.emulator import EmulatorOptions, Mode
from cellctl.kinds.iso_cnc.tape import frame
from cellctl.link import LineSettings

LINE = LineSettings.parse("9600,7E2")
BUFFER = 256
TOLERANCE = 10
LATENCIES = (0.0, 2.0, 8.0, 16.0)


def _listen(transport: str) -> str:
    return "pty" if transport == "pty" else f"{transport}://127.0.0.1:0"


async def _transfer(
    text: str, latency_ms: float, scale: float, transport: str, drip: bool, state: Path
) -> tuple[TimedControl, str]:
    """One transfer into a fresh control; the control and the driver's error ('' if none)."""
    options = EmulatorOptions(
        buffer_size=BUFFER, tolerance=TOLERANCE, adapter_latency_ms=latency_ms
    )
    control = TimedControl(options, time_scale=scale)
    control.set_mode(Mode.RMT if drip else Mode.EDIT)
    line = scaled_line(LINE, scale)
    server = await serve(control, _listen(transport), line, pacing=True)
    # The control's parameters; the deadlines short, so a stuck transfer fails (and counts)
    # rather than holding the bench.
    driver_options = IsoCncOptions(
        buffer_size=BUFFER,
        dc3_tolerance=TOLERANCE,
        motion_scale=scale,
        dc1_timeout=30,
        stop_timeout=60,
        end_extra=30,
    )
    error = ""
    driver = await IsoCncDriver.connect(
        server.url,
        name=f"bench-{latency_ms:g}",
        settings=line,
        options=driver_options,
        store=StateStore(state),
    )
    try:
        data = text.encode("ascii")
        start = asyncio.get_running_loop().call_later(
            0.05, control.cycle_start if drip else control.read
        )
        try:
            if drip:
                await driver.drip_feed(data, timeout=36000.0)
            else:
                await driver.read_in(data, timeout=36000.0)
        except CellctlError as e:
            error = str(e)
        finally:
            start.cancel()
    finally:
        await driver.close()
        await server.close()
    return control, error


async def bench(args: argparse.Namespace) -> None:
    scale = args.time_scale
    rate = LINE.chars_per_second
    program = surfacing_program(args.size)
    opts = IsoCncOptions()
    tape = frame(program, leader=opts.leader, trailer=opts.trailer, percent=opts.percent)
    model = opts.motion()
    high, low = BUFFER - TOLERANCE, BUFFER // 2
    bound = ideal_drip(tape, rate, model, high_water=high, low_water=low)
    print(
        f"dnc_dripfeed: {len(tape)} chars ({bound.blocks} blocks, {bound.machine_s:.0f} s of "
        f"motion) at {LINE} = {rate:.1f} chars/s; buffer {BUFFER}, tolerance {TOLERANCE}; "
        f"time scale {scale:g} (line, latency and motion); figures in the control's time; "
        f"transport {args.transport}"
    )
    readin_text = surfacing_program(args.readin_size, number=3000)
    readin: list[tuple[float, float, int, str]] = []
    with tempfile.TemporaryDirectory() as state:
        for latency in args.latencies:
            control, error = await _transfer(
                program, latency, scale, args.transport, True, Path(state)
            )
            overflows = sum(1 for a in control.alarms if a.code == 87)
            total = (control.ended - control.began) * scale if not error else math.inf
            stall = control.runs[-1].stall_s if control.runs else math.inf
            print(
                machine_line(
                    latency_ms=latency,
                    overflows=overflows,
                    total_s=total,
                    bound_s=bound.total_s,
                    time_ratio=total / bound.total_s,
                    stall_s=stall,
                    stall_bound_s=bound.stall_s,
                    stall_ratio=stall / bound.stall_s if bound.stall_s else math.nan,
                )
                + (f"  # error: {error}" if error else ""),
                flush=True,
            )
        for latency in args.latencies:
            control, error = await _transfer(
                readin_text, latency, scale, args.transport, False, Path(state)
            )
            seconds = (control.ended - control.began) * scale
            cps = control.chars_read / seconds if seconds > 0 and not error else 0.0
            overflows = sum(1 for a in control.alarms if a.code == 87)
            readin.append((latency, cps / rate, overflows, error))
    worst = min(r for _, r, _, _ in readin)
    per = ",".join(f"{lat:g}:{r:.4f}" for lat, r, _, _ in readin)
    errors = [f"{lat:g} ms: {e}" for lat, _, _, e in readin if e]
    print(
        machine_line(
            readin_chars=len(readin_text),
            readin_ratio_min=worst,
            readin_ratios=per,
            overflows=sum(o for _, _, o, _ in readin),
            errors=len(errors),
        )
    )
    for e in errors:
        print(f"# read-in error at {e}", file=sys.stderr)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=1_000_000, help="drip-fed program, chars")
    parser.add_argument("--readin-size", type=int, default=128_000, help="read-in, chars")
    parser.add_argument("--time-scale", type=float, default=20.0)
    parser.add_argument(
        "--latencies",
        type=lambda s: [float(x) for x in s.split(",")],
        default=list(LATENCIES),
        help="adapter latencies, ms (comma-separated)",
    )
    parser.add_argument("--transport", choices=["socket", "pty", "rfc2217"], default="socket")
    asyncio.run(bench(parser.parse_args()))


if __name__ == "__main__":
    main()
