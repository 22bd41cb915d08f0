"""Benchmark: 256 emulated controls drip-fed at once from one ``cellctl dnc serve``.

The controls (``bench/_dnc.py``'s surfacing program at 9600 7E2 into a 256-character buffer,
DC3 tolerance 10) run in another process, each on its own TCP port; one ``cellctl dnc serve``
process feeds them all (``SHOP/dnc.toml`` names each). Every drip-feed is started through the
server's control API (``dnc.send`` with ``drip``), the controls press CYCLE START together, and
each control records its own run: from its DC1 to its last block, its stalls, its alarms.

Printed: ``machines= overflows= time_ratio_p95= stall_ratio_max= cpu_us_per_char=`` where a
control's time_ratio is its run's time over the ideal host's (computed from the program, the
line rate and the motion model, bench/_dnc.py), p95 nearest-rank over every machine (one that
failed counts as +inf), stall_ratio its stall time over the ideal's, and cpu_us_per_char the
server process's CPU (user + system) over the characters it fed. Goals: overflows 0,
time_ratio_p95 <= 1.05.

Time may be scaled (``--time-scale``: line, motion together); figures are in the control's
time. ``--machines`` and ``--size`` for quick runs::

    .venv/bin/python bench/dnc_many.py [--machines 256] [--size 6000] [--time-scale 1]
"""

from __future__ import annotations

import argparse
import asyncio
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import ChildEmulators, machine_line, percentile
from _dnc import TimedControl, ideal_drip, surfacing_program
from cellctl.emulators.cell import scaled_line
from cellctl.emulators.serve import serve
from cellctl.kinds.iso_cnc.driver import IsoCncOptions
from cellctl.kinds.iso_cnc.emulator import EmulatorOptions, Mode
from cellctl.kinds.iso_cnc.tape import frame
from cellctl.link import LineSettings
from cellctl.service.client import RemoteCell
from cellctl.service.token import read_token

LINE = LineSettings.parse("9600,7E2")
BUFFER = 256
TOLERANCE = 10
CELLCTL = Path(sys.executable).with_name("cellctl")


async def _controls(conn: Any, count: int, scale: float) -> None:
    """The child: ``count`` controls in RMT mode; ``go`` presses CYCLE START on all,
    ``results`` sends each run's figures, ``stop`` ends."""
    line = scaled_line(LINE, scale)
    options = EmulatorOptions(buffer_size=BUFFER, tolerance=TOLERANCE)
    controls = [TimedControl(options, time_scale=scale) for _ in range(count)]
    servers = []
    for control in controls:
        control.set_mode(Mode.RMT)
        servers.append(await serve(control, "socket://127.0.0.1:0", line, pacing=True))
    conn.send([s.url for s in servers])
    loop = asyncio.get_running_loop()
    while True:
        message = await loop.run_in_executor(None, conn.recv)
        if message == "go":
            for control in controls:
                control.cycle_start()
            conn.send("ok")
        elif message == "results":
            conn.send(
                [
                    {
                        "total_s": (c.ended - c.began) * scale,
                        "stall_s": c.runs[-1].stall_s if c.runs else math.inf,
                        "done": bool(c.runs and c.runs[-1].done),
                        "overflows": sum(1 for a in c.alarms if a.code == 87),
                        "alarms": [a.code for a in c.alarms],
                        "chars": c.chars_read,
                    }
                    for c in controls
                ]
            )
        else:
            break
    for server in servers:
        await server.close()


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _write_shop(shop: Path, urls: list[str], program: str, scale: float, burst: int) -> None:
    line = scaled_line(LINE, scale)
    rows = []
    for i, url in enumerate(urls):
        rows.append(
            f'[machines.m{i:04d}]\nlink = "{url}"\nline = "{line}"\n'
            f"options = {{ buffer_size = {BUFFER}, dc3_tolerance = {TOLERANCE}, "
            f"motion_scale = {scale:g}, burst = {burst} }}\n"
        )
        folder = shop / f"m{i:04d}" / "programs"
        folder.mkdir(parents=True, mode=0o700)
        (folder / "O2000.nc").write_text(program)
    (shop / "dnc.toml").write_text("\n".join(rows))


async def _wait(condition: Any, what: str, timeout: float) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        found = await condition()
        if found:
            return found
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not within {timeout:g} s")
        await asyncio.sleep(0.2)


async def bench(args: argparse.Namespace) -> None:
    scale, count = args.time_scale, args.machines
    rate = LINE.chars_per_second
    program = surfacing_program(args.size)
    opts = IsoCncOptions()
    tape = frame(program, leader=opts.leader, trailer=opts.trailer, percent=opts.percent)
    bound = ideal_drip(
        tape, rate, opts.motion(), high_water=BUFFER - TOLERANCE, low_water=BUFFER // 2
    )
    print(
        f"dnc_many: {count} controls, each {len(tape)} chars ({bound.blocks} blocks, ideal "
        f"{bound.total_s:.1f} s, stall {bound.stall_s:.1f} s) at {LINE} = {rate:.1f} chars/s; "
        f"buffer {BUFFER}, tolerance {TOLERANCE}, burst {args.burst}; time scale {scale:g} "
        "(line and motion); "
        "figures in the control's time"
    )
    child = ChildEmulators(_controls, count, scale)
    urls: list[str] = child.receive(timeout=300)
    with tempfile.TemporaryDirectory() as tmp:
        shop = Path(tmp) / "shop"
        shop.mkdir(mode=0o700)
        _write_shop(shop, urls, program, scale, args.burst)
        serve_proc = subprocess.Popen(  # noqa: ASYNC220 - started once, not awaited
            [str(CELLCTL), "dnc", "serve", "--dir", str(shop)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        try:
            await _run(args, shop, serve_proc, child, tape, bound)
        finally:
            serve_proc.terminate()
            try:
                serve_proc.wait(20)
            except subprocess.TimeoutExpired:
                serve_proc.kill()
            child.close()


async def _run(
    args: argparse.Namespace,
    shop: Path,
    proc: subprocess.Popen[bytes],
    child: ChildEmulators,
    tape: bytes,
    bound: Any,
) -> None:
    count = args.machines

    async def ready() -> bool:
        if proc.poll() is not None:
            why = proc.stderr.read().decode() if proc.stderr else ""
            raise RuntimeError(f"dnc serve ended: {why}")
        return (shop / "api.sock").exists() and (shop / "api-token").exists()

    await _wait(ready, "dnc serve's API", 120)
    api = await RemoteCell.connect(token=read_token(shop), socket_path=shop / "api.sock")
    try:
        calls = [
            asyncio.create_task(
                api.call(
                    "dnc.send",
                    {"machine": f"m{i:04d}", "program": "O2000", "drip": True},
                    timeout=36000.0,
                )
            )
            for i in range(count)
        ]

        async def all_waiting() -> bool:
            status = await api.call("cell.status")
            states = [m["state"] for m in status["machines"].values()]
            return bool(sum(str(s).startswith("drip-feeding") for s in states) == count)

        await _wait(all_waiting, "every machine waiting for its control's read", 300)
        cpu0 = _cpu_seconds(proc.pid)
        child.parent.send("go")
        child.receive()
        outcomes = await asyncio.gather(*calls, return_exceptions=True)
        cpu = _cpu_seconds(proc.pid) - cpu0
    finally:
        await api.close()
    child.parent.send("results")
    results = child.receive()
    failed = sum(1 for o in outcomes if isinstance(o, BaseException))
    ratios = [
        r["total_s"] / bound.total_s if r["done"] and not isinstance(o, BaseException) else math.inf
        for r, o in zip(results, outcomes, strict=True)
    ]
    stalls = [r["stall_s"] / bound.stall_s if bound.stall_s else math.nan for r in results]
    chars = sum(r["chars"] for r in results)
    for o in outcomes:
        if isinstance(o, BaseException):
            print(f"# failed: {o}", file=sys.stderr)
            break
    print(
        machine_line(
            machines=count,
            overflows=sum(r["overflows"] for r in results),
            time_ratio_p95=percentile(ratios, 95),
            stall_ratio_max=max(stalls),
            cpu_us_per_char=cpu * 1e6 / max(1, chars),
            failed=failed,
        )
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--machines", type=int, default=256)
    parser.add_argument("--size", type=int, default=6000, help="each program, chars")
    parser.add_argument("--time-scale", type=float, default=1.0)
    parser.add_argument(
        "--burst", type=int, default=4, help="the driver's burst option (its default: 4)"
    )
    asyncio.run(bench(parser.parse_args()))


if __name__ == "__main__":
    main()
