"""Per-machine state the host keeps between runs: one small JSON file per machine.

The source's controllers could not tell the host which partitions hold programs or whether
a mill's reference zero was set: the host keeps that itself. ``StateStore`` keeps it on disk
in the cell directory so a CLI call, a restart or a second process sees the same view::

    store = StateStore(Path("cell"))
    state = store.load("robot1")          # {} the first time
    state["partitions"] = {"3": "LOADCNC1"}
    store.save("robot1", state)

Writes are atomic (write a temporary file, then rename), so a crash never leaves half a file.
The files are private: the directory is 0700, each file 0600 (mkstemp's mode, kept by rename).
The directory also holds each machine's owner lock (``machine-<key>.lock``, see
:func:`cellctl.drivers.base.take_link_locks`).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
from pathlib import Path
from typing import Any

from cellctl.errors import UsageError

_SAFE = re.compile(r"[^A-Za-z0-9_.-]+")


def machine_key(name_or_url: str) -> str:
    """A file-safe key for a machine name or URL: ``rfc2217://h:7001`` → ``rfc2217_h_7001``."""
    key = _SAFE.sub("_", name_or_url).strip("_.")
    if not key:
        raise UsageError(f"cannot make a state key from {name_or_url!r}")
    return key


class StateStore:
    """JSON state files under ``<cell_dir>/state/``.

    ``durable=False`` only for a throwaway copy (a plan's): a save is atomic still, but not
    synced to disk (a plan's cell saves its machines' state hundreds of times an hour).
    """

    def __init__(self, cell_dir: Path | str, *, durable: bool = True) -> None:
        self.dir = Path(cell_dir) / "state"
        self.durable = durable

    def path(self, key: str) -> Path:
        """The file that holds machine ``key``'s state."""
        return self.dir / f"{machine_key(key)}.json"

    def lock_path(self, name: str) -> Path:
        """The owner lock of machine ``name`` (held while a driver has its link open)."""
        return self.dir / f"machine-{machine_key(name)}.lock"

    def ensure_dir(self) -> Path:
        """Create the directory (0700) if missing; tighten one that is looser."""
        self.dir.mkdir(mode=0o700, parents=True, exist_ok=True)
        if self.dir.stat().st_mode & 0o077:
            with contextlib.suppress(PermissionError):
                os.chmod(self.dir, 0o700)
        return self.dir

    def load(self, key: str) -> dict[str, Any]:
        """The saved state of ``key``, or ``{}`` if none was saved (or the file is unreadable)."""
        try:
            data = json.loads(self.path(key).read_text(encoding="utf-8"))
        except (FileNotFoundError, json.JSONDecodeError):
            return {}
        return data if isinstance(data, dict) else {}

    def save(self, key: str, state: dict[str, Any]) -> None:
        """Replace the saved state of ``key`` atomically."""
        self.ensure_dir()
        target = self.path(key)
        fd, tmp = tempfile.mkstemp(dir=self.dir, prefix=target.name, suffix=".tmp")
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                json.dump(state, f, indent=2, sort_keys=True)
                if self.durable:
                    f.flush()
                    os.fsync(f.fileno())
            os.replace(tmp, target)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
