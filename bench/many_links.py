"""Many robot links from one controller process, under a DNC server's load.

N emulated robots run in other processes (``--workers``, as ``cellctl emulate robot --count N
--workers K`` runs them), each on its own pty or TCP port, paced at 4800 7E2. This process
opens N links and, for DURATION seconds:

- every link polls its robot's status (R 01) once a second, at a random phase;
- a quarter of the links download a 200-record program over and over; a serial line carries
  one transaction at a time, so these poll once between two downloads.

Every poll is timed from the moment it was due: its place in the once-a-second schedule (for
a downloading link, the end of the download before it), so a poll this process started late
is late. A poll that failed (a 5 s timeout included) is a late poll: it stays in the count
and is +inf in the percentiles. A download is timed from the end of the transaction before
it; a failed one counts its time and delivers nothing.

Printed per size: the fraction of polls answered within 1.5x their limit (paced wire time of
the poll's 24 characters plus 3 emulator turnarounds measured unpaced), the poll percentiles
(nearest rank), the downloads' ratio to their paced limit (as in robot_download.py: limit
time x downloads completed / time spent downloading), errors, and this process's CPU
microseconds per transaction (a poll, or one downloaded record and its Ack). Goal at 1,024 and
4,096 links: >= 99 % of polls in time, downloads >= 0.95 of the limit, errors = 0.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import math
import random
import resource
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from _common import line_settings, machine_line, percentile, robot_program
from cellctl.drivers.robot import Ibm7545Robot, RobotConfig
from cellctl.emulators.fleet import Fleet
from cellctl.emulators.robot import Ibm7545Emulator
from cellctl.link.serialport import raise_fd_limit
from cellctl.protocol.robot import encode_record

POLL_CHARS = 24  # R, Xoff Xon, "01" CR LF, D02xxxxcs CR LF, Ack, EG CR LF, Ack
POLL_TURNAROUNDS = 3  # R -> Xoff, operand -> D record, Ack -> EG
RECORDS = 200
# ptys left for everyone else on the box (other programs, other benches) when choosing one
PTY_MARGIN = 256


def make_robot(index: int) -> Ibm7545Emulator:
    return Ibm7545Emulator(time_scale=20.0)


def free_ptys() -> int:
    try:
        top = int(Path("/proc/sys/kernel/pty/max").read_text())
        used = int(Path("/proc/sys/kernel/pty/nr").read_text())
    except (OSError, ValueError):
        return 0
    return top - used - PTY_MARGIN


def listen_url(transport: str) -> str:
    return "pty" if transport == "pty" else f"{transport}://127.0.0.1:0"


@dataclass
class Stats:
    poll_latencies: list[float] = field(default_factory=list)  # from due; inf if it failed
    start_lags: list[float] = field(default_factory=list)  # due to the poll's first byte
    downloads_done: int = 0
    download_time: float = 0.0  # time spent on downloads, failed ones included
    records: int = 0
    errors: list[str] = field(default_factory=list)
    # this process's CPU (user, system) and the emulators' CPU over the window, wall length
    cpu_user: float = 0.0
    cpu_system: float = 0.0
    emulator_cpu: float = 0.0
    wall: float = 0.0


async def run_links(
    urls: list[str],
    duration: float,
    downloaders: int,
    stats: Stats,
    emulator_cpu: Callable[[], float],
) -> None:
    """Connect, initialize, then run the load for ``duration`` s; CPU is counted from then
    until the last transaction ended (connecting thousands of links is not a transaction)."""
    settings = line_settings()
    program = robot_program(RECORDS)
    config = RobotConfig(reply_timeout=5.0)
    robots = [
        await Ibm7545Robot.connect(u, name=f"r{i}", settings=settings, config=config)
        for i, u in enumerate(urls)
    ]
    await asyncio.gather(*(r.initialize() for r in robots))
    gc.freeze()
    download_s = settings.wire_time(sum(len(encode_record(r)) + 1 for r in program.records))
    loop = asyncio.get_running_loop()
    usage0 = resource.getrusage(resource.RUSAGE_SELF)
    emulator0 = emulator_cpu()
    t0 = loop.time()
    end = t0 + duration

    async def poll(i: int, due: float) -> float:
        """One poll due at ``due``; returns when it ended (counted either way)."""
        stats.start_lags.append(loop.time() - due)
        try:
            await robots[i].machine_status()
            done = loop.time()
            stats.poll_latencies.append(done - due)
        except Exception as e:  # counted, not fatal: a failed poll is a late poll
            done = loop.time()
            stats.poll_latencies.append(math.inf)
            stats.errors.append(f"poll r{i}: {e}")
        return done

    async def poller(i: int) -> None:
        due = t0 + random.random()
        while due < end:
            delay = due - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            await poll(i, due)
            due += 1.0

    async def downloader(i: int) -> None:
        # Downloads start at random moments over one download's length, as a DNC server's
        # do; started together they would also finish together, every time.
        due = t0 + random.random() * download_s
        await asyncio.sleep(due - loop.time())
        while due < end:
            before = robots[i].counters.records_downloaded
            try:
                await robots[i].download(1, program)
                stats.downloads_done += 1
            except Exception as e:  # its time counts, with nothing delivered
                stats.errors.append(f"download r{i}: {e}")
            finished = loop.time()
            stats.download_time += finished - due
            stats.records += robots[i].counters.records_downloaded - before
            due = await poll(i, finished)

    tasks = [downloader(i) for i in range(downloaders)]
    tasks += [poller(i) for i in range(downloaders, len(robots))]
    await asyncio.gather(*tasks)
    usage = resource.getrusage(resource.RUSAGE_SELF)
    stats.wall = loop.time() - t0
    stats.emulator_cpu = emulator_cpu() - emulator0
    stats.cpu_user = usage.ru_utime - usage0.ru_utime
    stats.cpu_system = usage.ru_stime - usage0.ru_stime
    for r in robots:
        await r.close()


async def measure_latency(transport: str) -> float:
    fleet = Fleet.start(
        make_robot, listen_url(transport), line_settings(), count=1, workers=1, pacing=False
    )
    try:
        (url,) = fleet.urls
        async with await Ibm7545Robot.connect(url, settings=line_settings()) as robot:
            times = []
            for _ in range(50):
                start = time.perf_counter()
                await robot.machine_status()
                times.append(time.perf_counter() - start)
    finally:
        fleet.close()
    return min(times) / POLL_TURNAROUNDS


async def one_size(
    count: int, duration: float, transport: str, workers: int, latency: float
) -> dict[str, Any]:
    settings = line_settings()
    fleet = Fleet.start(
        make_robot, listen_url(transport), settings, count=count, workers=min(workers, count)
    )
    stats = Stats()
    try:
        await run_links(fleet.urls, duration, max(1, count // 4), stats, fleet.cpu_seconds)
    finally:
        fleet.close()
    poll_limit = 1.5 * (settings.wire_time(POLL_CHARS) + POLL_TURNAROUNDS * latency)
    polls = stats.poll_latencies
    in_time = sum(t <= poll_limit for t in polls) / max(1, len(polls))
    program = robot_program(RECORDS)
    chars = sum(len(encode_record(r)) for r in program.records) + len(program.records) + 1
    dl_limit = settings.wire_time(chars) + (len(program.records) + 1) * latency
    dl_ratio = stats.downloads_done * dl_limit / stats.download_time if stats.download_time else 0.0
    transactions = len(polls) + stats.records
    # What the load asks of the controller when every line runs at its rate: a poll a second
    # per polling link; per downloading link a download and a poll, back to back.
    downloaders = max(1, count // 4)
    demand = (count - downloaders) + downloaders * (RECORDS + 1) / (dl_limit + poll_limit / 1.5)
    cpu_per_txn = (stats.cpu_user + stats.cpu_system) / max(1, transactions)
    return {
        "links": count,
        "transport": transport,
        "workers": min(workers, count),
        "polls": len(polls),
        "polls_in_time": in_time,
        "poll_limit_ms": poll_limit * 1e3,
        "poll_p50_ms": percentile(polls, 50) * 1e3,
        "poll_p90_ms": percentile(polls, 90) * 1e3,
        "poll_p99_ms": percentile(polls, 99) * 1e3,
        "start_lag_p99_ms": percentile(stats.start_lags, 99) * 1e3,
        "downloads": stats.downloads_done,
        "download_ratio": dl_ratio,
        "errors": len(stats.errors),
        "cpu_us_per_txn": cpu_per_txn * 1e6,
        "demand_txn_per_s": demand,
        "cores_needed": cpu_per_txn * demand,
        "system_us_per_txn": stats.cpu_system / max(1, transactions) * 1e6,
        "controller_load": (stats.cpu_user + stats.cpu_system) / stats.wall,
        "emulator_load": stats.emulator_cpu / stats.wall,
        "first_error": stats.errors[0] if stats.errors else "",
    }


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--links", type=int, nargs="+", default=[64, 256, 1024])
    parser.add_argument("--duration", type=float, default=30.0)
    parser.add_argument(
        "--transport",
        choices=["auto", "pty", "socket"],
        default="auto",
        help="auto: ptys while the kernel has enough free ones, TCP beyond",
    )
    parser.add_argument(
        "--workers", type=int, default=2, help="processes the emulators are spread over"
    )
    args = parser.parse_args()
    raise_fd_limit()
    last: dict[str, Any] = {}
    latencies: dict[str, float] = {}
    for count in args.links:
        transport = args.transport
        if transport == "auto":
            transport = "pty" if count <= free_ptys() else "socket"
        if transport not in latencies:
            latencies[transport] = await measure_latency(transport)
            print(
                f"emulator turnaround (unpaced) over {transport}: "
                f"{latencies[transport] * 1e3:.3f} ms"
            )
        r = await one_size(count, args.duration, transport, args.workers, latencies[transport])
        print(
            f"links={r['links']:5d} ({transport}, emulators in {r['workers']} processes) "
            f"polls={r['polls']:6d} in time {r['polls_in_time']:.4f}  "
            f"downloads={r['downloads']:4d} ratio {r['download_ratio']:.4f}  "
            f"errors {r['errors']}  cpu {r['cpu_us_per_txn']:.0f} us/txn "
            f"({r['system_us_per_txn']:.0f} in the kernel)  "
            f"(controller process {r['controller_load']:.0%} of a core, "
            f"emulators {r['emulator_load']:.0%})"
        )
        print(
            f"  poll times from due: p50 {r['poll_p50_ms']:.1f} ms, p90 {r['poll_p90_ms']:.1f} "
            f"ms, p99 {r['poll_p99_ms']:.1f} ms; in time means <= {r['poll_limit_ms']:.1f} ms; "
            f"started p99 {r['start_lag_p99_ms']:.1f} ms after due"
        )
        print(
            f"  the load asks {r['demand_txn_per_s']:.0f} transactions/s at the line rate: at "
            f"{r['cpu_us_per_txn']:.0f} us each, {r['cores_needed']:.2f} of a core for this process"
        )
        if r["first_error"]:
            print(f"  first error: {r['first_error']}")
        last = r
    ratio = min(last["download_ratio"], last["polls_in_time"] / 0.99)
    print(
        machine_line(
            links=last["links"],
            transport=last["transport"],
            polls=last["polls"],
            polls_in_time=last["polls_in_time"],
            poll_p99_ms=last["poll_p99_ms"],
            downloads=last["downloads"],
            download_ratio=last["download_ratio"],
            errors=last["errors"],
            ratio=ratio,
            cpu_us_per_txn=last["cpu_us_per_txn"],
            controller_cores_needed=last["cores_needed"],
            controller_load=last["controller_load"],
            emulator_load=last["emulator_load"],
        )
    )


if __name__ == "__main__":
    asyncio.run(main())
