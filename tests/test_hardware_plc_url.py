"""``cellctl plc --url`` of another PLC is not refused because the cell's PLC is in use.

On a bench beside a running cell, the engineer tries a new PLC before cell.toml names it:
``cellctl plc --url modbus://NEW set door_1 1``. That was refused with "plc is in use by
cellctl run" (the cell's PLC lock), though nobody held the PLC at that address; the cell's
own PLC, however it is spelt, stays refused.
"""

from __future__ import annotations

import os
import re
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from cellctl.drivers.state import StateStore
from cellctl.link.lock import OwnerLock, set_process_label

from .conftest import CELLCTL, refusing_port

#: Seconds one ``cellctl`` command may take, and an emulator to start or stop.
COMMAND_S = 60.0


@contextmanager
def plc_emulator(env: dict[str, str]) -> Iterator[str]:
    """``cellctl emulate plc`` on a free loopback port; yields its URL."""
    proc = subprocess.Popen(
        [*CELLCTL, "emulate", "plc", "--listen", "modbus://127.0.0.1:0"],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert proc.stdout is not None
        url = ""
        for row in proc.stdout:  # ends if the emulator does: no wait without an end
            found = re.search(r"listening on (modbus://\S+)", row)
            if found:
                url = found.group(1)
                break
        assert url, "the PLC emulator did not say where it listens"
        yield url
    finally:
        proc.terminate()
        proc.wait(timeout=COMMAND_S)


def test_another_plcs_url_is_not_the_cells_plc(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir(mode=0o700)
    env = {**os.environ, "CELLCTL_RUNTIME_DIR": str(run)}
    held = refusing_port()
    port = held.getsockname()[1]
    cell = tmp_path / "cell"
    cell.mkdir()
    (cell / "cell.toml").write_text(f'[plc]\nurl = "modbus://127.0.0.1:{port}"\n')
    set_process_label("cellctl run")  # the cell's PLC held as its controller holds it
    try:
        lock = OwnerLock.acquire(StateStore(cell).lock_path("plc"), "plc")
    finally:
        set_process_label(None)

    def plc(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [*CELLCTL, "--cell", str(cell), "plc", *args],
            capture_output=True,
            text=True,
            timeout=COMMAND_S,
            env=env,
        )

    try:
        with plc_emulator(env) as other:
            done = plc("--url", other, "set", "door_1", "1")
            assert done.returncode == 0, done.stderr
            assert "door_1 = 1" in done.stdout
        # The cell's own PLC, spelt otherwise, is still the controller's.
        done = plc("--url", f"modbus://localhost:{port}", "set", "door_1", "1")
        assert done.returncode == 6, done.stderr
        assert "plc is in use by cellctl run" in done.stderr
    finally:
        lock.release()
        held.close()
