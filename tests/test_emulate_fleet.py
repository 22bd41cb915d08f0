"""``cellctl emulate robot --count N --workers K``: many robots over several processes, each
its own machine on its own TCP port, driven by the real driver."""

from __future__ import annotations

import asyncio
import subprocess
import time
from pathlib import Path

import pytest
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st

from cellctl.drivers.robot import Ibm7545Robot
from cellctl.emulators.fleet import _share, check_fleet, listen_for
from cellctl.errors import DeviceError, UsageError
from cellctl.ui.cli import main

from .conftest import CELLCTL


def children(pid: int) -> list[int]:
    text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    return [int(p) for p in text.split()]


def alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


async def drive(urls: list[str]) -> None:
    robots = [await Ibm7545Robot.connect(u, name=f"r{i}") for i, u in enumerate(urls)]
    try:
        for robot in robots:
            assert not (await robot.machine_status()).flags
        # Each is its own machine: the first is initialized; the last (in the other worker)
        # has not returned home, so its controller refuses auto mode (48).
        await robots[0].initialize()
        with pytest.raises(DeviceError) as refused:
            await robots[3].auto_mode()
        assert refused.value.code == 48
        await robots[0].auto_mode()
    finally:
        for robot in robots:
            await robot.close()


def test_four_robots_in_two_worker_processes() -> None:
    args = ["--count", "4", "--workers", "2", "--listen", "socket://127.0.0.1:0"]
    proc = subprocess.Popen(
        [*CELLCTL, "emulate", "robot", *args, "--time-scale", "500", "--no-pacing"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        header = proc.stdout.readline()
        assert header.startswith("4 x IBM 7545 emulator in 2 processes"), header
        urls = [proc.stdout.readline().split("--link", 1)[1].strip() for _ in range(4)]
        assert len(set(urls)) == 4 and all(u.startswith("socket://127.0.0.1:") for u in urls)
        workers = children(proc.pid)
        assert len(workers) == 2
        asyncio.run(drive(urls))
    finally:
        proc.terminate()
        proc.wait(timeout=20)
    assert proc.returncode == 0
    deadline = time.monotonic() + 10
    while any(alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(alive(w) for w in workers), "a worker outlived the emulate command"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--count", "0"], "at least 1"),
        (["--count", "2", "--workers", "3"], "workers must be between 1 and the count (2)"),
        (["--count", "2", "--workers", "0"], "workers must be between"),
        (["--count", "2", "--listen", "pty:/tmp/robot"], "names one pty"),
        (["--count", "3", "--listen", "socket://127.0.0.1:65534"], "go past 65535"),
    ],
)
def test_bad_fleet_is_refused_before_anything_starts(args: list[str], message: str) -> None:
    result = CliRunner().invoke(main, ["emulate", "robot", *args])
    assert result.exit_code == 2, result.output
    assert message in result.output


def test_fixed_port_counts_up_per_machine() -> None:
    assert [listen_for("socket://127.0.0.1:7000", i, 3) for i in range(3)] == [
        "socket://127.0.0.1:7000",
        "socket://127.0.0.1:7001",
        "socket://127.0.0.1:7002",
    ]
    assert listen_for("rfc2217://127.0.0.1:0", 5, 9) == "rfc2217://127.0.0.1:0"


@given(st.integers(-3, 300), st.integers(-3, 40))
def test_any_count_and_workers_is_refused_or_split_exactly(count: int, workers: int) -> None:
    try:
        check_fleet("pty", count, workers)
    except UsageError:
        assert count < 1 or not 1 <= workers <= count
        return
    shares = [_share(count, workers, w) for w in range(workers)]
    assert [i for share in shares for i in share] == list(range(count))
    assert all(len(share) >= 1 for share in shares)
