"""``cellctl emulate iso-cnc --panel`` as a user runs it: its keys in ``--help``, and Ctrl-C
ends it even while the panel waits for a key on a terminal's stdin (no Enter needed)."""

from __future__ import annotations

import signal
import subprocess

from tests.conftest import CELLCTL


def test_help_lists_the_panel_keys() -> None:
    said = subprocess.run(
        [*CELLCTL, "emulate", "iso-cnc", "--help"], capture_output=True, text=True, timeout=60
    )
    assert said.returncode == 0, said.stderr
    text = " ".join(said.stdout.split())
    for key in ("edit", "mem", "rmt", "read", "start (CYCLE START)", "punch [N]", "reset", "list"):
        assert key in text, key


def test_ctrl_c_ends_the_emulator_while_its_panel_waits_for_a_key() -> None:
    proc = subprocess.Popen(
        [*CELLCTL, "emulate", "iso-cnc", "--panel", "--listen", "socket://127.0.0.1:0"],
        stdin=subprocess.PIPE,  # kept open: the panel waits for a line that never comes
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert proc.stdout is not None
        for row in proc.stdout:  # served once it says where
            if "link = " in row:
                break
        assert proc.stdin is not None
        proc.stdin.write("list\n")
        proc.stdin.flush()
        for row in proc.stdout:  # the panel answers a key
            if "memory:" in row:
                break
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=20)  # a hang here is the bug
        assert "emulator stopped" in out, out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
