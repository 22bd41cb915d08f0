"""The cobot tending cell's batch (examples/cell-tending): makespan against physics, and the
robot's state seen through RTDE at 125 Hz while it runs.

The tending cell (a UR5e, an iso-cnc mill, a Dyna 2400, the PLC) is emulated in a second
process at one time factor (``--time-scale``, default 100: every machine time and every
character's time on the mills' lines is divided by it). The real controller runs a batch of
``--parts`` brackets. Meanwhile an RTDE client of its own (the kind's codec over asyncio, as
the driver's) subscribes to the robot's state at 125 Hz and counts what arrives.

Limits, none taken from the run:

- ``bound_s``: the physical bound (:mod:`cellctl.cell.physics`) from the machines' own
  models at this time scale: the mills' cut times from their programs, the UR's transfers
  on the motion model its emulator runs (movej/movel by distance, speed, acceleration; the
  sleeps; the doors and vises from the PLC's timing), the line time of every block.
  ``ratio_physical`` = makespan / bound_s (goal <= 1.05).
- ``rtde_hz``: packages received per second of this process's clock, from the stream's
  start (the controller's reply to START) to the watch's end, over the batch; the goal is
  the 125 Hz subscribed (>= 124). A package late or missing lowers it (the window is the
  clock, not the count).
  ``rtde_gaps``: packages missing by their ``timestamp`` (the controller's cycle it was
  sampled in: each step of n periods between two packages is n - 1 missing); goal 0.
  Jitter of arrival is not a gap: a late package still carries its cycle's timestamp.

Timing figures on a loaded machine are noisy: run it alone. Last line machine-readable.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import os
import shutil
import signal
import tempfile
import time
import tomllib
from pathlib import Path
from typing import Any

from _common import machine_line, within
from cellctl.cell.config import load_cell
from cellctl.cell.controller import CellController, ControllerOptions
from cellctl.cell.journal import open_journal
from cellctl.cell.physics import physical_durations
from cellctl.cell.report import summarize
from cellctl.emulators.cell import EmulatedCell
from cellctl.kinds.ur import rtde
from cellctl.mailbox import open_mailbox

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "cell-tending"
PHYSICAL_GOAL = 1.05
RTDE_HZ = 125.0
RTDE_GOAL = 124.0


def _cell_child(conn: Any, directory: str, time_scale: float) -> None:
    """In the child: serve the emulated cell until told to stop, then send its cut log."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    async def serve() -> None:
        cell = EmulatedCell(time_scale=time_scale, template=EXAMPLE)
        try:
            await cell.start(Path(directory))
            conn.send("ready")
            await asyncio.get_running_loop().run_in_executor(None, conn.recv)
            conn.send(cell.runs_per_part())
        finally:
            await cell.close()

    asyncio.run(serve())


class RtdeWatch:
    """An RTDE client counting the robot's packages: their controller timestamps."""

    FIELDS = ("timestamp", "actual_q", "robot_mode", "safety_mode", "runtime_state")

    def __init__(self) -> None:
        self.stamps: list[float] = []
        self.started = self.stopped = 0.0  # this process's monotonic clock
        self.task: asyncio.Task[None] | None = None

    async def start(self, host: str, port: int) -> None:
        reader, writer = await asyncio.open_connection(host, port)
        t = rtde.PacketType

        async def ask(packet_type: int, payload: bytes) -> bytes:
            writer.write(rtde.encode(packet_type, payload))
            while True:
                got, body = await self._packet(reader)
                if got == packet_type:
                    return body

        assert rtde.parse_protocol_version_reply(
            await ask(t.REQUEST_PROTOCOL_VERSION, rtde.request_protocol_version(2))
        )
        reply = await ask(t.SETUP_OUTPUTS, rtde.setup_outputs_payload(RTDE_HZ, self.FIELDS))
        recipe = rtde.parse_setup_reply(reply, self.FIELDS)
        assert recipe.ok, recipe.refused()
        assert rtde.parse_start_reply(await ask(t.START, b""))
        self.started = time.monotonic()
        self.task = asyncio.ensure_future(self._read(reader, writer, recipe))

    @staticmethod
    async def _packet(reader: asyncio.StreamReader) -> tuple[int, bytes]:
        async with asyncio.timeout(10):
            header = await reader.readexactly(rtde.HEADER.size)
            size, packet_type = rtde.HEADER.unpack(header)
            return packet_type, await reader.readexactly(size - rtde.HEADER.size)

    async def _read(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, recipe: rtde.Recipe
    ) -> None:
        try:
            while True:
                packet_type, body = await self._packet(reader)
                if packet_type == rtde.PacketType.DATA_PACKAGE:
                    self.stamps.append(rtde.unpack_data(recipe, body)["timestamp"])
        finally:
            writer.close()

    async def stop(self) -> None:
        self.stopped = time.monotonic()
        if self.task is not None:
            self.task.cancel()
            await asyncio.gather(self.task, return_exceptions=True)

    def figures(self) -> tuple[float, int]:
        """(packages per second received, packages missing by timestamp) over the watch."""
        if len(self.stamps) < 2:
            return 0.0, 0
        period = 1.0 / RTDE_HZ
        window = self.stopped - self.started
        missing = 0
        for a, b in zip(self.stamps, self.stamps[1:], strict=False):
            missing += max(0, round((b - a) / period) - 1)
        return len(self.stamps) / window if window > 0 else 0.0, missing


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--parts", type=int, default=6)
    parser.add_argument("--time-scale", type=float, default=100.0)
    parser.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "cellctl-ur-cell")
    args = parser.parse_args()
    directory = args.out / "cell"
    shutil.rmtree(directory, ignore_errors=True)
    ctx = mp.get_context("fork")
    conn, child = ctx.Pipe()
    proc = ctx.Process(
        target=_cell_child, args=(child, str(directory), args.time_scale), daemon=True
    )
    proc.start()
    runs: dict[str, dict[str, int]] = {}
    watch = RtdeWatch()
    try:
        if not conn.poll(120) or conn.recv() != "ready":
            raise SystemExit("the emulated cell did not start")
        raw = tomllib.loads((directory / "cell.toml").read_text(encoding="utf-8"))
        robot = raw["machines"]["robot"]
        host = robot["link"].split("://", 1)[1].rsplit(":", 1)[0]
        await watch.start(host, int(robot["options"]["rtde_port"]))
        with open_mailbox(directory) as mailbox:
            mailbox.post_order("bracket", args.parts, order_id="B1")
        config = load_cell(directory)
        options = ControllerOptions.from_config(config)
        controller = CellController(
            config, open_journal(directory), open_mailbox(directory), options=options
        )
        started = time.time()
        # A part takes about 900 s of machine time (9 s of wall time at the default scale).
        # Three times that, and a minute more: a wait that does not end is shown where it
        # waits (one run once did not end).
        limit = 60 + args.parts * 2700 / args.time_scale
        try:
            await within(limit, "the batch", controller.connect())
            await within(limit, "the batch", controller.run(asyncio.Event(), until_idle=True))
        finally:
            await within(60, "closing the cell's links", controller.close())
            await watch.stop()
    finally:
        conn.send("stop")
        runs = conn.recv() if conn.poll(30) else {}
        proc.join(10)
        if proc.is_alive():
            os.kill(proc.pid or 0, signal.SIGKILL)

    machines = [config.robot.name, *(m.name for m in config.mills)]
    summary = summarize(controller.journal, machines, since=started)
    physics = physical_durations(
        config, time_scale=args.time_scale, done_output=options.done_output
    )
    parts = ["bracket"] * args.parts
    bound = physics.bound(parts, config.parts)
    ratio = summary.makespan_s / bound if bound > 0 else float("inf")
    hz, gaps = watch.figures()
    twice = sum(1 for r in runs.values() if any(n != 1 for n in r.values()))
    made = len(runs)
    print(f"tending cell, {args.parts} brackets at time scale {args.time_scale:g}")
    print(
        "physical transfers (s at this scale): "
        + ", ".join(f"{k} {v:.3f}" for k, v in physics.transfer_s.items())
    )
    print(f"makespan {summary.makespan_s:.2f} s, physical bound {bound:.2f} s: "
          f"ratio_physical {ratio:.4f} (goal <= {PHYSICAL_GOAL})")  # fmt: skip
    print(f"RTDE: {len(watch.stamps)} packages, {hz:.2f} Hz received "
          f"(goal >= {RTDE_GOAL:g}), {gaps} missing (goal 0)")  # fmt: skip
    print(f"parts cut on both mills: {made}; cut other than once: {twice}")
    print(
        machine_line(
            makespan_s=summary.makespan_s,
            bound_s=bound,
            ratio_physical=ratio,
            rtde_hz=hz,
            rtde_gaps=gaps,
            parts_wrong=twice + (args.parts - made),
        )
    )


if __name__ == "__main__":
    asyncio.run(main())
