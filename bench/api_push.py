"""50 subscribers on the control API while the emulated cell runs a batch: how fast does a
change in the controller reach every subscriber, and does anyone wait for them?

The emulated example cell (``cellctl emulate cell``) and the controller (``cellctl run``, which
serves the API on the cell's Unix socket) run as separate processes, as a user runs them. The
batch runs twice: once with no subscriber, once with ``--subscribers`` clients subscribed
(``cell.subscribe``) from this process. Every controller event carries the time it happened;
a subscriber notes when the update carrying it arrived. Printed: the latency percentiles over
every (event, subscriber) pair, the controller process's CPU share (its CPU time over the
run's wall time, from ``wait4``), both makespans, and finally

    subscribers=50 p50_ms= p99_ms= max_ms= cpu_share= makespan_s= makespan_alone_s= ratio=

with ratio = p99 / 100 ms (goal <= 1) and the makespans for "dispatch no slower with
subscribers". About 2 minutes at the defaults.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from _common import machine_line
from cellctl.cell.journal import open_journal
from cellctl.mailbox import open_mailbox
from cellctl.service.client import RemoteCell, attach

CELLCTL = str(Path(sys.executable).parent / "cellctl")
LIMIT_MS = 100.0


def start_cell(directory: Path, time_scale: float) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        [CELLCTL, "--cell", str(directory), "emulate", "cell", "--time-scale", str(time_scale)],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.strip().startswith("plc"):
            return proc
    raise RuntimeError("the emulated cell did not start")


async def run_batch(
    directory: Path, time_scale: float, parts: int, subscribers: int
) -> dict[str, Any]:
    shutil.rmtree(directory, ignore_errors=True)
    cell = start_cell(directory, time_scale)
    clients: list[RemoteCell] = []
    latencies: list[float] = []
    try:
        with open_mailbox(directory) as mailbox:
            half = parts // 2
            mailbox.post_order("wax-robot-base", half, order_id="A")
            mailbox.post_order("wax-toy-mill-table", parts - half, order_id="B")
        started = time.monotonic()
        run = subprocess.Popen(  # noqa: ASYNC220 - wait4 below needs the pid
            [CELLCTL, "--cell", str(directory), "run", "--no-live", "--until-idle"],
            stdout=subprocess.DEVNULL,
        )
        if subscribers:
            deadline = time.monotonic() + 30
            while True:
                try:
                    first = await attach(directory)
                    break
                except Exception:
                    if time.monotonic() > deadline or run.poll() is not None:
                        raise
                    await asyncio.sleep(0.05)
            clients = [first, *[await attach(directory) for _ in range(subscribers - 1)]]

            def noter(since: float) -> Callable[[dict[str, Any]], None]:
                def note(update: dict[str, Any]) -> None:
                    now = time.time()
                    for event in update.get("events", []):
                        # Events from before the subscription come with its first snapshot:
                        # not a change pushed, so not counted.
                        if event["time"] >= since:
                            latencies.append((now - event["time"]) * 1000)

                return note

            for client in clients:
                await client.subscribe(noter(time.time()))
        loop = asyncio.get_running_loop()
        _, status, usage = await loop.run_in_executor(None, os.wait4, run.pid, 0)
        wall = time.monotonic() - started
        run.returncode = os.waitstatus_to_exitcode(status)
        if run.returncode != 0:
            raise RuntimeError(f"cellctl run exited {run.returncode}")
        with open_journal(directory) as journal:
            makespan = journal.makespan() or float("nan")
        return {
            "latencies": latencies,
            "cpu_share": (usage.ru_utime + usage.ru_stime) / wall,
            "makespan": makespan,
        }
    finally:
        for client in clients:
            await client.close()
        cell.terminate()
        cell.wait(10)


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--subscribers", type=int, default=50)
    parser.add_argument("--parts", type=int, default=6)
    parser.add_argument("--time-scale", type=float, default=200.0)
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix="api-push-"))
    try:
        alone = await run_batch(root / "alone", args.time_scale, args.parts, 0)
        print(f"without subscribers: makespan {alone['makespan']:.1f} s, "
              f"controller CPU {alone['cpu_share']:.1%}")  # fmt: skip
        watched = await run_batch(root / "watched", args.time_scale, args.parts, args.subscribers)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    lat = sorted(watched["latencies"])
    if not lat:
        raise SystemExit("no update reached a subscriber")
    p50 = statistics.median(lat)
    p99 = lat[min(len(lat) - 1, int(0.99 * len(lat)))]
    print(
        f"with {args.subscribers} subscribers: {len(lat)} deliveries, p50 {p50:.1f} ms, "
        f"p99 {p99:.1f} ms, max {lat[-1]:.1f} ms; makespan {watched['makespan']:.1f} s, "
        f"controller CPU {watched['cpu_share']:.1%}"
    )
    print(
        machine_line(
            subscribers=args.subscribers,
            p50_ms=p50,
            p99_ms=p99,
            max_ms=lat[-1],
            cpu_share=watched["cpu_share"],
            makespan_s=watched["makespan"],
            makespan_alone_s=alone["makespan"],
            ratio=p99 / LIMIT_MS,
        )
    )


if __name__ == "__main__":
    asyncio.run(main())
