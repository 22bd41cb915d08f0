"""Download a 200-record program to the robot emulator paced at 4800 7E2.

Prints records/s achieved and the ratio to the limit

    limit time = sum over records (wire time of the record + wire time of its Ack)
                 + records x emulator reply latency

where the emulator's reply latency is measured first, on the same link with pacing off (the
time from the host's last byte of a record to the Ack, less nothing: no wire time then).
The emulator runs in its own process, over a real pty. The paced download is repeated
``--rounds`` times; the figure is the median run (min and max beside it), never the best. A
download that failed counts as a run of ratio 0 and is printed in ``errors=``.
Goal: ratio >= 0.95.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import time
from typing import Any

from _common import (
    ChildEmulators,
    line_settings,
    machine_line,
    median_run,
    robot_program,
    wait_for_stop,
)
from cellctl.drivers.robot import Ibm7545Robot
from cellctl.emulators.robot import Ibm7545Emulator
from cellctl.emulators.serve import serve
from cellctl.protocol.robot import encode_record


async def emulators(conn: Any, transport: str) -> None:
    settings = line_settings()
    servers = []
    for pacing in (False, True):
        listen = "pty" if transport == "pty" else f"{transport}://127.0.0.1:0"
        servers.append(
            await serve(Ibm7545Emulator(time_scale=20.0), listen, settings, pacing=pacing)
        )
    conn.send([s.url for s in servers])
    await wait_for_stop(conn)
    for s in servers:
        await s.close()


async def download_time(url: str, records: int, rounds: int, errors: list[str]) -> list[float]:
    """Each round's download time; a failed round is ``inf`` (and its error in ``errors``)."""
    settings = line_settings()
    program = robot_program(records)
    times = []
    async with await Ibm7545Robot.connect(url, settings=settings) as robot:
        await robot.initialize()
        for _ in range(rounds):
            start = time.perf_counter()
            try:
                await robot.download(1, program)
                times.append(time.perf_counter() - start)
            except Exception as e:  # counted: a failed download is a run that delivered nothing
                errors.append(str(e))
                times.append(math.inf)
    return times


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--records", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--transport", choices=["pty", "socket", "rfc2217"], default="pty")
    args = parser.parse_args()
    settings = line_settings()
    child = ChildEmulators(emulators, args.transport)
    try:
        fast_url, paced_url = child.receive()
        calibration: list[str] = []
        unpaced = await download_time(fast_url, args.records, 5, calibration)
        if calibration:
            raise SystemExit(f"the unpaced calibration download failed: {calibration[0]}")
        # Per record exchange with no wire time: the emulator's (and driver's) turnaround.
        latency = min(unpaced) / (args.records + 1)
        errors: list[str] = []
        paced = await download_time(paced_url, args.records, args.rounds, errors)
    finally:
        child.close()
    program = robot_program(args.records)
    wire = [encode_record(r) for r in program.records]
    chars = sum(len(w) for w in wire) + len(wire) + 1  # records, one Ack each, N alone + Ack
    exchanges = len(wire) + 1
    limit_s = settings.wire_time(chars) + exchanges * latency
    ratios = [limit_s / t for t in paced]  # a failed run: limit / inf = 0
    ratio, ratio_min, ratio_max = median_run(ratios)
    median_time = limit_s / ratio if ratio else math.inf
    rate = args.records / median_time
    limit_rate = args.records / limit_s
    print(f"program: {args.records} records, {chars} characters on the wire incl. Acks")
    print(f"line: {settings} = {settings.chars_per_second:.2f} chars/s; transport {args.transport}")
    print(f"emulator reply latency (unpaced, per exchange): {latency * 1e3:.3f} ms")
    print(f"paced downloads: {', '.join(f'{t:.3f} s' for t in paced)}")
    for e in errors:
        print(f"  failed: {e}")
    print(
        f"median run: {rate:.2f} records/s; limit: {limit_rate:.2f} records/s; "
        f"ratio median {ratio:.4f} (min {ratio_min:.4f}, max {ratio_max:.4f}) of {len(paced)} runs"
    )
    print(
        machine_line(
            records=args.records,
            runs=len(paced),
            errors=len(errors),
            records_per_s=rate,
            limit_records_per_s=limit_rate,
            latency_ms=latency * 1e3,
            ratio=ratio,
            ratio_min=ratio_min,
            ratio_max=ratio_max,
        )
    )


if __name__ == "__main__":
    asyncio.run(main())
