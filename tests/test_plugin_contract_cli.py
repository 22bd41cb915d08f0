"""A family group's command the machine's kind does not have (``cellctl mill --kind kerf100
--link URL home``: the saw homes from its menu, not from a command of the ``mill`` group) is
refused naming the kind and the commands it has, before any link is opened: never Click's
bare "No such command" or "Missing command"."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

from .conftest import CELLCTL

TEMPLATE = Path(__file__).resolve().parent / "plugins" / "kerf_cell"
#: Nothing listens here: a command that opened the link would fail on it, not be refused.
LINK = "socket://127.0.0.1:9"
#: What the command line has for a Kerf 100 (its menu: status, home, cut).
SAW_HAS = "its commands: status; its functions home, cut: in the console or the control API"


def cellctl(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CELLCTL, *args], capture_output=True, text=True, timeout=60)


def refused(done: subprocess.CompletedProcess[str]) -> str:
    """The one error line of a command refused as a usage error (status 2)."""
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    return done.stderr.strip()


def test_a_command_the_kind_at_a_link_has_not_is_refused_naming_what_it_has() -> None:
    done = cellctl("--cell", "nowhere", "mill", "--kind", "kerf100", "--link", LINK, "home")
    assert refused(done) == f"error: no mill command 'home' for {LINK}, a kerf100 ({SAW_HAS})"


def test_a_word_no_kind_has_is_refused_naming_what_the_kind_has() -> None:
    done = cellctl("--cell", "nowhere", "mill", "--kind", "kerf100", "--link", LINK, "frob")
    assert refused(done) == f"error: no mill command 'frob' for {LINK}, a kerf100 ({SAW_HAS})"
    # Given a command after it, the word is the machine's name at the link, as before.
    done = cellctl("--cell", "nowhere", "mill", "--kind", "kerf100", "--link", LINK, "frob", "go")
    assert refused(done) == f"error: no mill command 'go' for frob, a kerf100 ({SAW_HAS})"


def test_a_command_a_cells_machine_has_not_is_refused_naming_what_it_has(tmp_path: Path) -> None:
    cell = tmp_path / "cell"
    shutil.copytree(TEMPLATE, cell)
    done = cellctl("--cell", str(cell), "mill", "saw", "home")
    assert refused(done) == f"error: no mill command 'home' for saw, a kerf100 ({SAW_HAS})"
    # A Dyna 2400 of the same cell has no `cut`: its commands are the mill group's.
    done = cellctl("--cell", str(cell), "mill", "cnc1", "cut")
    dyna = "error: no mill command 'cut' for cnc1, a dyna2400 (its commands: "
    assert refused(done).startswith(dyna), done.stderr
    # A machine named with no command: which ones it has, not Click's "Missing command".
    done = cellctl("--cell", str(cell), "mill", "saw")
    assert refused(done) == f"error: no mill command given for saw, a kerf100 ({SAW_HAS})"
