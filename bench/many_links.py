"""Many robot links from one controller process, under a DNC server's load.

N emulated robots run in a second process, each on its own pty (or TCP port), paced at
4800 7E2. This process opens N links and, for DURATION seconds:

- every link polls its robot's status (R 01) once a second, at a random phase;
- a quarter of the links download a 200-record program over and over (between downloads
  they take their poll, since a serial line carries one transaction at a time).

Printed: the fraction of polls answered within 1.5x their limit (paced wire time of the
poll's 24 characters plus 3 emulator turnarounds measured unpaced), the downloads' ratio to
their paced limit (as in robot_download.py), and this process's CPU microseconds per
transaction (a poll, or one downloaded record and its Ack). Goal at 1,024 links: >= 99 % of
polls in time and downloads >= 0.95 of the limit.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import random
import time
from dataclasses import dataclass, field
from typing import Any

from _common import ChildEmulators, line_settings, machine_line, robot_program, wait_for_stop
from cellctl.emulators.serve import serve
from cellctl.kinds.ibm7545.driver import Ibm7545Robot, RobotConfig
from cellctl.kinds.ibm7545.emulator import Ibm7545Emulator
from cellctl.kinds.ibm7545.records import encode_record
from cellctl.link.serialport import raise_fd_limit

POLL_CHARS = 24  # R, Xoff Xon, "01" CR LF, D02xxxxcs CR LF, Ack, EG CR LF, Ack
POLL_TURNAROUNDS = 3  # R -> Xoff, operand -> D record, Ack -> EG


async def emulators(conn: Any, count: int, transport: str, pacing: bool) -> None:
    raise_fd_limit()
    settings = line_settings()
    listen = "pty" if transport == "pty" else f"{transport}://127.0.0.1:0"
    servers = [
        await serve(Ibm7545Emulator(time_scale=20.0), listen, settings, pacing=pacing)
        for _ in range(count)
    ]
    gc.freeze()
    conn.send([s.url for s in servers])
    await wait_for_stop(conn)
    for s in servers:
        await s.close()


@dataclass
class Stats:
    poll_times: list[float] = field(default_factory=list)
    download_times: list[float] = field(default_factory=list)
    records: int = 0
    errors: list[str] = field(default_factory=list)


async def run_links(urls: list[str], duration: float, downloaders: int, stats: Stats) -> None:
    settings = line_settings()
    program = robot_program(200)
    config = RobotConfig(reply_timeout=5.0)
    robots = [
        await Ibm7545Robot.connect(u, name=f"r{i}", settings=settings, config=config)
        for i, u in enumerate(urls)
    ]
    await asyncio.gather(*(r.initialize() for r in robots))
    gc.freeze()
    locks = [asyncio.Lock() for _ in robots]
    download_s = settings.wire_time(sum(len(encode_record(r)) + 1 for r in program.records))
    loop = asyncio.get_running_loop()
    end = loop.time() + duration

    async def poller(i: int) -> None:
        await asyncio.sleep(random.random())
        next_at = loop.time()
        while loop.time() < end:
            async with locks[i]:
                start = loop.time()
                try:
                    await robots[i].machine_status()
                    stats.poll_times.append(loop.time() - start)
                except Exception as e:  # counted, not fatal: the figure is the fraction in time
                    stats.errors.append(f"poll r{i}: {e}")
            next_at += 1.0
            await asyncio.sleep(max(0.0, next_at - loop.time()))

    async def downloader(i: int) -> None:
        # Downloads start at random moments over one download's length, as a DNC server's
        # do; started together they would also finish together, every time.
        await asyncio.sleep(random.random() * download_s)
        while loop.time() < end:
            async with locks[i]:
                start = loop.time()
                try:
                    await robots[i].download(1, program)
                    stats.download_times.append(loop.time() - start)
                    stats.records += len(program.records)
                except Exception as e:
                    stats.errors.append(f"download r{i}: {e}")
            await asyncio.sleep(0)

    tasks = [poller(i) for i in range(len(robots))]
    tasks += [downloader(i) for i in range(downloaders)]
    await asyncio.gather(*tasks)
    for r in robots:
        await r.close()


async def measure_latency(transport: str) -> float:
    child = ChildEmulators(emulators, 1, transport, False)
    try:
        (url,) = child.receive()
        async with await Ibm7545Robot.connect(url, settings=line_settings()) as robot:
            times = []
            for _ in range(50):
                start = time.perf_counter()
                await robot.machine_status()
                times.append(time.perf_counter() - start)
    finally:
        child.close()
    return min(times) / POLL_TURNAROUNDS


async def one_size(count: int, duration: float, transport: str, latency: float) -> dict[str, Any]:
    settings = line_settings()
    child = ChildEmulators(emulators, count, transport, True)
    stats = Stats()
    try:
        urls = child.receive(timeout=300)
        cpu0 = time.process_time()
        child_cpu0 = child.cpu_seconds()
        wall0 = time.monotonic()
        await run_links(urls, duration, max(1, count // 4), stats)
        cpu = time.process_time() - cpu0
        wall = time.monotonic() - wall0
        child_cpu = child.cpu_seconds() - child_cpu0
    finally:
        child.close()
    poll_limit = settings.wire_time(POLL_CHARS) + POLL_TURNAROUNDS * latency
    in_time = sum(t <= 1.5 * poll_limit for t in stats.poll_times) / max(1, len(stats.poll_times))
    program = robot_program(200)
    chars = sum(len(encode_record(r)) for r in program.records) + len(program.records) + 1
    dl_limit = settings.wire_time(chars) + (len(program.records) + 1) * latency
    dl_ratio = (
        dl_limit / (sum(stats.download_times) / len(stats.download_times))
        if stats.download_times
        else 0.0
    )
    transactions = len(stats.poll_times) + stats.records
    times = sorted(stats.poll_times) or [0.0]
    pct = {q: times[min(len(times) - 1, int(q / 100 * len(times)))] for q in (50, 90, 99)}
    return {
        "poll_limit_ms": 1.5 * poll_limit * 1e3,
        "poll_p50_ms": pct[50] * 1e3,
        "poll_p90_ms": pct[90] * 1e3,
        "poll_p99_ms": pct[99] * 1e3,
        "links": count,
        "polls": len(stats.poll_times),
        "polls_in_time": in_time,
        "downloads": len(stats.download_times),
        "download_ratio": dl_ratio,
        "cpu_us_per_txn": cpu / max(1, transactions) * 1e6,
        "errors": len(stats.errors),
        "controller_load": cpu / wall,
        "emulator_load": child_cpu / wall,
        "first_error": stats.errors[0] if stats.errors else "",
    }


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--links", type=int, nargs="+", default=[64, 256, 1024])
    parser.add_argument("--duration", type=float, default=30.0)
    parser.add_argument("--transport", choices=["pty", "socket"], default="pty")
    args = parser.parse_args()
    raise_fd_limit()
    latency = await measure_latency(args.transport)
    print(f"emulator turnaround (unpaced): {latency * 1e3:.3f} ms; transport {args.transport}")
    last: dict[str, Any] = {}
    for count in args.links:
        r = await one_size(count, args.duration, args.transport, latency)
        print(
            f"links={r['links']:5d} polls={r['polls']:6d} in time {r['polls_in_time']:.4f}  "
            f"downloads={r['downloads']:4d} ratio {r['download_ratio']:.4f}  "
            f"cpu {r['cpu_us_per_txn']:.0f} us/txn  errors {r['errors']}  "
            f"(controller process {r['controller_load']:.0%} of a core, "
            f"emulators {r['emulator_load']:.0%})"
        )
        print(
            f"  poll times p50 {r['poll_p50_ms']:.1f} ms, p90 {r['poll_p90_ms']:.1f} ms, "
            f"p99 {r['poll_p99_ms']:.1f} ms; in time means <= {r['poll_limit_ms']:.1f} ms"
        )
        if r["first_error"]:
            print(f"  first error: {r['first_error']}")
        last = r
    ratio = min(last["download_ratio"], last["polls_in_time"] / 0.99)
    print(
        machine_line(
            links=last["links"],
            polls_in_time=last["polls_in_time"],
            download_ratio=last["download_ratio"],
            ratio=ratio,
            cpu_us_per_txn=last["cpu_us_per_txn"],
        )
    )


if __name__ == "__main__":
    asyncio.run(main())
