"""50 subscribers on the control API while the emulated cell runs a batch: how fast does a
change in the controller reach every subscriber, and does anyone wait for them?

The emulated example cell (``cellctl emulate cell``) and the controller (``cellctl run``, which
serves the API on the cell's Unix socket) run as separate processes, as a user runs them. The
batch runs twice: once with no subscriber, once with ``--subscribers`` clients subscribed
(``cell.subscribe``) from this process. Every controller event carries the time it happened;
a subscriber notes when the update carrying it arrived.

Every (event, subscriber) pair counts. The events pushed are those any subscriber saw (the
controller keeps no other record of them); each subscriber should see every one of them that
happened after it subscribed and was not already in its first snapshot. A pair it never saw
is a miss: in the count and +inf in the percentiles (nearest rank); a subscriber that saw
nothing at all is printed by itself. Printed: the latency percentiles, the misses, the
controller process's CPU share (its CPU time over the run's wall time, from ``wait4``), both
makespans, and finally

    subscribers=50 deliveries= missed= silent= p50_ms= p99_ms= max_ms= cpu_share= makespan_s=
    makespan_alone_s= ratio=

with ratio = p99 / 100 ms (goal <= 1, missed = 0) and the makespans for "dispatch no slower
with subscribers". About 2 minutes at the defaults.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from _common import machine_line, percentile
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
    # per subscriber: when it subscribed, the events of its first snapshot, what it saw
    since: list[float] = []
    known: list[set[tuple[float, str]]] = []
    seen: list[dict[tuple[float, str], float]] = []
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

            def noter(index: int) -> Callable[[dict[str, Any]], None]:
                def note(update: dict[str, Any]) -> None:
                    now = time.time()
                    for event in update.get("events", []):
                        key = (event["time"], event["text"])
                        seen[index].setdefault(key, (now - event["time"]) * 1000)

                return note

            for i, client in enumerate(clients):
                since.append(time.time())
                seen.append({})
                snapshot = await client.subscribe(noter(i))
                known.append({(e["time"], e["text"]) for e in snapshot.get("events", [])})
        loop = asyncio.get_running_loop()
        _, status, usage = await loop.run_in_executor(None, os.wait4, run.pid, 0)
        wall = time.monotonic() - started
        run.returncode = os.waitstatus_to_exitcode(status)
        if run.returncode != 0:
            raise RuntimeError(f"cellctl run exited {run.returncode}")
        with open_journal(directory) as journal:
            makespan = journal.makespan() or float("nan")
        # Events from before a subscription, or in its first snapshot, were not pushed to it.
        pushed = set().union(*seen) if seen else set()
        latencies: list[float] = []
        missed = 0
        for i in range(len(clients)):
            for key in pushed:
                if key[0] < since[i] or key in known[i]:
                    continue
                if key in seen[i]:
                    latencies.append(seen[i][key])
                else:
                    latencies.append(math.inf)
                    missed += 1
        return {
            "latencies": latencies,
            "missed": missed,
            "silent": sum(not s for s in seen),
            "events": len(pushed),
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
    lat = watched["latencies"]
    if not lat:
        # Not one event reached any subscriber: every subscriber missed the whole batch.
        lat = [math.inf]
    p50, p99, worst = percentile(lat, 50), percentile(lat, 99), max(lat)
    print(
        f"with {args.subscribers} subscribers: {watched['events']} events pushed, "
        f"{len(lat) - watched['missed']} deliveries, {watched['missed']} missed, "
        f"{watched['silent']} subscribers saw nothing; p50 {p50:.1f} ms, p99 {p99:.1f} ms, "
        f"max {worst:.1f} ms; makespan {watched['makespan']:.1f} s, "
        f"controller CPU {watched['cpu_share']:.1%}"
    )
    print(
        machine_line(
            subscribers=args.subscribers,
            deliveries=len(lat) - watched["missed"],
            missed=watched["missed"],
            silent=watched["silent"],
            p50_ms=p50,
            p99_ms=p99,
            max_ms=worst,
            cpu_share=watched["cpu_share"],
            makespan_s=watched["makespan"],
            makespan_alone_s=alone["makespan"],
            ratio=p99 / LIMIT_MS,
        )
    )


if __name__ == "__main__":
    asyncio.run(main())
