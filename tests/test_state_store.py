"""The machines' state files: a save replaces the file whole, private, and reads back the same,
synced to disk or (a plan's throwaway copy) not."""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest

from cellctl.drivers.state import StateStore


@pytest.mark.parametrize("durable", [True, False])
def test_a_save_reads_back_whole_and_private(tmp_path: Path, durable: bool) -> None:
    store = StateStore(tmp_path, durable=durable)
    assert store.load("robot1") == {}
    store.save("robot1", {"partitions": {"3": "LOADCNC1"}, "state": 2})
    store.save("robot1", {"partitions": {"3": "LOADCNC1", "4": "UNLOAD"}, "state": 3})
    assert StateStore(tmp_path).load("robot1") == {
        "partitions": {"3": "LOADCNC1", "4": "UNLOAD"},
        "state": 3,
    }
    assert json.loads(store.path("robot1").read_text())["state"] == 3
    assert [p.name for p in store.dir.iterdir()] == ["robot1.json"]  # no temporary file left
    assert stat.S_IMODE(store.dir.stat().st_mode) == 0o700
    assert stat.S_IMODE(store.path("robot1").stat().st_mode) == 0o600
