"""One name, one kind: a plug-in cannot take over a built-in kind's name, and two plug-ins
declaring one name are both refused, each said in `cellctl kinds` and on stderr.

The plug-ins here are distributions made in the test's directory (a ``.dist-info`` with its
``entry_points.txt``, found on ``PYTHONPATH`` as pip would leave one in site-packages)."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

from .conftest import CELLCTL


def distribution(site: Path, name: str, kinds: list[str]) -> None:
    """An installed distribution ``name`` declaring each of ``kinds``: the saw under that
    name (a good declaration, but for its name)."""
    module = name.replace("-", "_")
    info = site / f"{module}-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    (site / f"{module}.py").write_text(
        "import dataclasses\nfrom cellctl_saw.kind import KERF100\n"
        + "".join(
            f"K{i} = dataclasses.replace(KERF100, name={kind!r})\n" for i, kind in enumerate(kinds)
        )
    )
    lines = "".join(f"{kind} = {module}:K{i}\n" for i, kind in enumerate(kinds))
    (info / "entry_points.txt").write_text(f"[cellctl.machine_kinds]\n{lines}")


def kinds(site: Path) -> tuple[dict[str, dict[str, str]], str]:
    """`cellctl kinds --json` with ``site`` on the path: the rows by kind, and stderr."""
    path = [str(site), *filter(None, [os.environ.get("PYTHONPATH")])]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(path)}
    done = subprocess.run(
        [*CELLCTL, "kinds", "--json"], capture_output=True, text=True, timeout=60, env=env
    )
    assert done.returncode == 0, done.stderr
    rows: dict[str, dict[str, str]] = {}
    for row in json.loads(done.stdout):
        rows.setdefault(row["kind"], {}).update(row)
    return rows, done.stderr


def test_a_plug_in_cannot_replace_a_built_in_kind(tmp_path: Path) -> None:
    # The saw's declaration under the Dyna 2400's name: never imported, never used.
    distribution(tmp_path, "cellctl-usurper", ["dyna2400"])
    rows, stderr = kinds(tmp_path)
    dyna = rows["dyna2400"]
    assert dyna["distribution"] == "cellctl" and dyna["maker"] == "Dyna", dyna
    assert dyna["broken"] == "dyna2400 is a built-in kind: cellctl-usurper cannot replace it"
    assert stderr.count("cellctl-usurper cannot replace it") == 1, stderr
    assert len(stderr.strip().splitlines()) == 1, stderr


def test_two_plug_ins_declaring_one_name_are_both_refused(tmp_path: Path) -> None:
    distribution(tmp_path, "cellctl-saw-a", ["kerf100x"])
    distribution(tmp_path, "cellctl-saw-b", ["kerf100x"])
    rows, stderr = kinds(tmp_path)
    row = rows["kerf100x"]
    assert "family" not in row, row  # neither is used
    assert row["broken"] == (
        "declared by cellctl-saw-a and cellctl-saw-b: neither is used "
        "(uninstall one, or rename its kind)"
    )
    assert "neither is used" in stderr
    # The saw itself, declared once, is untouched.
    assert rows["kerf100"]["distribution"] == "cellctl-saw"


def test_a_kind_whose_options_take_unknown_keys_is_broken_saying_why(tmp_path: Path) -> None:
    """A mistyped option in a cell.toml must be refused by its name (docs/kinds.md): a
    kind whose options model lets unknown keys through would drop it unsaid."""
    module = "cellctl_lax"
    info = tmp_path / f"{module}-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: cellctl-lax\nVersion: 0.1\n")
    (tmp_path / f"{module}.py").write_text(
        "import dataclasses\nfrom pydantic import BaseModel, ConfigDict\n"
        "from cellctl_saw.kind import KERF100\n"
        "class LaxOptions(BaseModel):\n"
        "    model_config = ConfigDict(extra='ignore')\n"
        "K = dataclasses.replace(KERF100, name='lax1', options=LaxOptions)\n"
    )
    (info / "entry_points.txt").write_text(f"[cellctl.machine_kinds]\nlax1 = {module}:K\n")
    rows, stderr = kinds(tmp_path)
    assert "family" not in rows["lax1"], rows["lax1"]
    assert rows["lax1"]["broken"] == (
        "ValueError: its options model LaxOptions must refuse unknown keys "
        '(model_config = ConfigDict(extra="forbid"))'
    ), rows["lax1"]
    assert "lax1" in stderr
