"""Many emulated machines at once, spread over worker processes.

A DNC server drives thousands of machines; one process cannot pace thousands of emulated
lines on one core, so a fleet forks ``workers`` processes and each serves its share::

    fleet = Fleet.start(lambda i: Ibm7545Emulator(time_scale=20.0), "socket://127.0.0.1:0",
                        ROBOT_LINE, count=4096, workers=2)
    fleet.urls            # one per machine, in machine order: what drivers open
    fleet.cpu_seconds()   # CPU (user + system) the workers have used so far
    fleet.close()         # stop every worker (also when this process dies: pipes close)

``cellctl emulate robot --count N --workers K`` is this from the command line. With
``workers=1`` nothing is forked (:func:`serve_many` in this process).

``listen`` is as for :func:`cellctl.emulators.serve.serve`, for every machine: ``pty`` gives
each its own pty; ``socket://HOST:0`` (or ``rfc2217://``) a free port each;
``socket://HOST:PORT`` the ports PORT, PORT+1, ... in machine order. ``pty:PATH`` names one
machine and is refused for more. Each machine is its own emulator (``make(index)``) with its
own state; they share nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import multiprocessing as mp
import os
import signal
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from urllib.parse import urlsplit

from cellctl.emulators.serve import EmulatedDevice, Server, serve
from cellctl.errors import LinkError, UsageError
from cellctl.link import LineSettings, parse_host_port
from cellctl.link.serialport import raise_fd_limit

DeviceFactory = Callable[[int], EmulatedDevice]
"""``make(index)``: the emulator of machine ``index`` (0-based)."""

#: How long a worker may take to open its share of the machines (thousands of ptys or ports).
START_TIMEOUT_S = 300.0


def listen_for(listen: str, index: int, count: int) -> str:
    """Where machine ``index`` of ``count`` listens, given one ``listen`` for all of them."""
    if listen == "pty":
        return listen
    if listen.startswith("pty:"):
        if count > 1:
            raise UsageError(f"{listen} names one pty: use --listen pty for {count} machines")
        return listen
    scheme = urlsplit(listen).scheme
    if scheme in ("socket", "tcp", "rfc2217"):
        host, port = parse_host_port(listen)
        if port == 0:
            return listen
        if port + count - 1 > 65535:
            raise UsageError(f"{listen}: {count} ports from {port} go past 65535")
        return f"{scheme}://{host}:{port + index}"
    return listen  # serve() refuses it with its own message


def check_fleet(listen: str, count: int, workers: int) -> None:
    """Refuse a bad ``count``/``workers``/``listen`` before anything is started."""
    if count < 1:
        raise UsageError(f"the count of machines must be at least 1, not {count}")
    if not 1 <= workers <= count:
        raise UsageError(f"workers must be between 1 and the count ({count}), not {workers}")
    listen_for(listen, count - 1, count)


async def serve_many(
    make: DeviceFactory,
    listen: str,
    settings: LineSettings,
    *,
    pacing: bool = True,
    indices: range,
    count: int,
) -> list[Server]:
    """Serve machines ``indices`` (of ``count``) in this process; close them all on a failure."""
    servers: list[Server] = []
    try:
        for i in indices:
            servers.append(
                await serve(make(i), listen_for(listen, i, count), settings, pacing=pacing)
            )
    except BaseException:
        for s in servers:
            await s.close()
        raise
    return servers


def _share(count: int, workers: int, worker: int) -> range:
    return range(worker * count // workers, (worker + 1) * count // workers)


async def _worker_main(
    conn: Connection,
    make: DeviceFactory,
    listen: str,
    settings: LineSettings,
    pacing: bool,
    indices: range,
    count: int,
) -> None:
    raise_fd_limit()
    try:
        servers = await serve_many(
            make, listen, settings, pacing=pacing, indices=indices, count=count
        )
    except Exception as e:  # told to the parent, which raises it there
        conn.send(("error", f"{type(e).__name__}: {e}"))
        return
    # Thousands of long-lived emulator objects: keep the collector from walking them again
    # and again (it would stall every paced line in this process for a moment each time).
    gc.freeze()
    conn.send(("urls", [s.url for s in servers]))
    loop = asyncio.get_running_loop()
    with contextlib.suppress(EOFError, OSError):
        await loop.run_in_executor(None, conn.recv)  # "stop", or EOF when the parent died
    for s in servers:
        await s.close()


def _worker(conn: Connection, *args: object) -> None:
    # Ctrl-C reaches the whole process group: the parent stops the workers itself.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    asyncio.run(_worker_main(conn, *args))  # type: ignore[arg-type]


@dataclass
class Fleet:
    """Machines served by worker processes (see the module docstring); ``close()`` stops them."""

    urls: list[str]
    processes: list[mp.process.BaseProcess] = field(default_factory=list)
    _conns: list[Connection] = field(default_factory=list)

    @classmethod
    def start(
        cls,
        make: DeviceFactory,
        listen: str,
        settings: LineSettings,
        *,
        count: int,
        workers: int,
        pacing: bool = True,
        timeout: float = START_TIMEOUT_S,
    ) -> Fleet:
        """Fork ``workers`` processes serving ``count`` machines; return once all listen.

        Blocks until then (at most ``timeout`` s). Raises UsageError for a bad count, worker
        count or ``listen``, and LinkError when a worker could not open its machines.
        """
        check_fleet(listen, count, workers)
        ctx = mp.get_context("fork")  # the factory may be a closure: no pickling
        fleet = cls(urls=[])
        try:
            for w in range(workers):
                parent, child = ctx.Pipe()
                args = (child, make, listen, settings, pacing, _share(count, workers, w), count)
                proc = ctx.Process(target=_worker, args=args, daemon=True)
                proc.start()
                child.close()
                fleet.processes.append(proc)
                fleet._conns.append(parent)
            for w, conn in enumerate(fleet._conns):
                if not conn.poll(timeout):
                    raise LinkError(f"emulator worker {w} did not start in {timeout:g} s")
                try:
                    kind, payload = conn.recv()
                except EOFError:
                    raise LinkError(f"emulator worker {w} exited while starting") from None
                if kind == "error":
                    raise LinkError(f"emulator worker {w}: {payload}")
                fleet.urls.extend(payload)
        except BaseException:
            fleet.close()
            raise
        return fleet

    def cpu_seconds(self) -> float:
        """CPU time (user + system) the workers have used so far (nan where unreadable)."""
        total = 0.0
        for proc in self.processes:
            total += process_cpu_seconds(proc.pid or 0)
        return total

    def close(self, timeout: float = 10.0) -> None:
        """Stop every worker: ask, wait up to ``timeout`` s, then kill what is left."""
        for conn in self._conns:
            with contextlib.suppress(OSError, ValueError):
                conn.send("stop")
        for proc in self.processes:
            proc.join(timeout)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout)
        for conn in self._conns:
            conn.close()
        self._conns = []

    def __enter__(self) -> Fleet:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def process_cpu_seconds(pid: int) -> float:
    """CPU time (user + system) process ``pid`` has used, from /proc (nan where unreadable)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
