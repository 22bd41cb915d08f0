"""Robot downloads through a noisy line: how many complete, and does any corruption get through.

The robot emulator runs with the ``noise=RATE,SEED`` fault (every byte, each way, flipped in one
bit or dropped with probability RATE); the driver sends a download refused for a transmission
error again from its N record, up to ``download_retries`` (3) times. Each download is a
different 99-record program into a partition the emulator has just emptied, so a success can
be checked against what the emulator holds.

Prints ``completed`` as the ratio of downloads that reported success (goal >= 0.9 at 3e-4),
``silent``, the downloads that reported success but left something else in the partition
(goal 0), the retries, and the 99th percentile of a download's time. Unpaced, at a high time
scale: it measures the protocol's resilience, not the line's speed (bench/robot_download.py
does that).
"""

from __future__ import annotations

import argparse
import asyncio
import time

from _common import machine_line, percentile
from cellctl.emulators.serve import serve
from cellctl.errors import CellctlError
from cellctl.kinds.ibm7545.aml import compile_source, decode_program
from cellctl.kinds.ibm7545.driver import Ibm7545Robot, RobotConfig
from cellctl.kinds.ibm7545.emulator import Ibm7545Emulator, LoadedProgram
from cellctl.kinds.ibm7545.records import ProgramFile
from cellctl.link import ROBOT_LINE


def program(run: int, records: int) -> ProgramFile:
    lines = [
        "DELAY(0)" if i % 4 == 3 else f"PMOVE(PT({300 + (i + run) % 50}, {i % 40 - 20}, 0, 0))"
        for i in range(records - 3)
    ]
    return compile_source("\n".join([*lines, "END"]), f"RUN{run}", 1)


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rate", type=float, default=3e-4)
    parser.add_argument("--downloads", type=int, default=50)
    parser.add_argument("--records", type=int, default=99)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--retries", type=int, default=3)
    args = parser.parse_args()
    config = RobotConfig(reply_timeout=0.3, retry_settle=0.05, download_retries=args.retries)
    emulator = Ibm7545Emulator(time_scale=1000.0)
    server = await serve(emulator, "socket://127.0.0.1:0", ROBOT_LINE, pacing=False)
    noise = f"{args.rate},{args.seed}"
    completed = silent = 0
    failures: dict[str, int] = {}
    times: list[float] = []
    try:
        async with await Ibm7545Robot.connect(server.url, config=config) as robot:
            await robot.initialize()
            emulator.set_fault("noise", noise)
            for run in range(args.downloads):
                prog = program(run, args.records)
                partition = run % 5 + 1
                emulator.partitions[partition] = None
                started = time.perf_counter()
                try:
                    await robot.download(partition, prog)
                except CellctlError as e:
                    kind = type(e).__name__
                    failures[kind] = failures.get(kind, 0) + 1
                    if robot.state != 1:
                        emulator.clear_fault("noise")
                        await robot.initialize()
                        emulator.set_fault("noise", noise)
                else:
                    completed += 1
                    body = prog.with_partition(partition).records[1:-1]
                    want = LoadedProgram(prog.name, tuple(decode_program(body)))
                    if emulator.partitions[partition] != want:
                        silent += 1
                times.append(time.perf_counter() - started)
            retries = robot.counters.download_retries
    finally:
        await server.close()
    assert emulator.noise is not None
    print(
        f"line noise {args.rate:g} per byte each way (seed {args.seed}): "
        f"{emulator.noise.flipped} bytes flipped, {emulator.noise.dropped} dropped"
    )
    print(f"{args.downloads} downloads of {args.records} records, up to {args.retries} retries")
    print(f"failed: {failures or 'none'}")
    print(
        machine_line(
            rate=args.rate,
            downloads=args.downloads,
            completed=completed / args.downloads,
            errors=sum(failures.values()),
            silent=silent,
            retries=retries,
            p99_s=percentile(times, 99),  # failed downloads count, at their time to fail
        )
    )


if __name__ == "__main__":
    asyncio.run(main())
