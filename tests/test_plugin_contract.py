"""A badly written plug-in kind, as its author first tries it: each mistake is refused in
words that name the kind and its package and say what to fix, never a traceback, and only
that kind is affected (the shipped kinds and the Kerf 100 saw keep working).

The kinds are tests/plugins/cellctl_flawed's (the saw with one mistake each), declared by a
distribution made in the test's directory (a ``.dist-info`` with its ``entry_points.txt``,
as tests/test_kind_registry.py makes them) and run through the real ``cellctl``."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from .conftest import CELLCTL

PLUGINS = Path(__file__).resolve().parent / "plugins"
FLAWED = PLUGINS / "cellctl_flawed"
TEMPLATE = PLUGINS / "kerf_cell"
DIST = "cellctl-flawed"
#: Seconds a command may take: one that serves (an emulated cell not refused) is cut off.
DEADLINE_S = 60


def install(site: Path, kinds: dict[str, str]) -> Path:
    """Distribution cellctl-flawed in ``site``, declaring ``kinds`` (name -> its entry
    point's ``module:ATTRIBUTE``), as pip leaves one in site-packages."""
    info = site / "cellctl_flawed-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {DIST}\nVersion: 0.1\n")
    lines = "".join(f"{name} = {target}\n" for name, target in kinds.items())
    (info / "entry_points.txt").write_text(f"[cellctl.machine_kinds]\n{lines}")
    return site


def cellctl(site: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``cellctl ARGS`` with ``site``'s distribution installed (and the flawed kinds' code)."""
    path = [str(site), str(FLAWED), *filter(None, [os.environ.get("PYTHONPATH")])]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(path)}
    try:
        return subprocess.run(
            [*CELLCTL, *args], capture_output=True, text=True, timeout=DEADLINE_S, env=env
        )
    except subprocess.TimeoutExpired as e:
        out = (e.stdout or b"").decode() if isinstance(e.stdout, bytes) else e.stdout or ""
        pytest.fail(f"cellctl {' '.join(args)} ran on past {DEADLINE_S} s, never refused: {out}")


def said(done: subprocess.CompletedProcess[str]) -> str:
    """What a command printed, its lines joined and its spaces single (help text wraps)."""
    return " ".join((done.stdout + done.stderr).split())


def refused(done: subprocess.CompletedProcess[str]) -> str:
    """The one error line a refused command printed (its status failure, no traceback)."""
    assert done.returncode != 0, said(done)
    assert "Traceback" not in done.stderr, done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1, done.stderr
    return errors[0]


def saw_template(directory: Path, kind: str) -> Path:
    """The mill-and-saw cell (tests/plugins/kerf_cell), its saw of kind ``kind``."""
    shutil.copytree(TEMPLATE, directory)
    toml = directory / "cell.toml"
    toml.write_text(toml.read_text().replace('kind = "kerf100"', f'kind = "{kind}"'))
    return directory


def emulate_cell(
    site: Path, tmp_path: Path, kind: str, *more: str
) -> subprocess.CompletedProcess[str]:
    """``cellctl emulate cell --template`` of the mill-and-saw cell, its saw of ``kind``."""
    template = saw_template(tmp_path / "template", kind)
    cell = str(tmp_path / "cell")
    return cellctl(site, "--cell", cell, "emulate", "cell", "--template", str(template), *more)


# -- 1. an emulator that does not keep the mill family's emulator protocol ------------------


def test_an_emulator_whose_start_raises_is_refused_naming_its_kind(tmp_path: Path) -> None:
    site = install(tmp_path / "site", {"flawed-start": "cellctl_flawed.kinds:START_RAISES"})
    error = refused(emulate_cell(site, tmp_path, "flawed-start"))
    assert error == (
        "error: kind flawed-start (from cellctl-flawed): its emulator's start() raised "
        "RuntimeError: motor controller not found"
    )


def test_an_emulator_without_run_hooks_is_refused_naming_what_it_lacks(tmp_path: Path) -> None:
    site = install(tmp_path / "site", {"flawed-hooks": "cellctl_flawed.kinds:NO_RUN_HOOKS"})
    error = refused(emulate_cell(site, tmp_path, "flawed-hooks"))
    assert error.startswith(
        "error: kind flawed-hooks (from cellctl-flawed): its emulator (NoRunHooks) has no "
        "cycle_start(), run_hooks"
    ), error
    assert "docs/kinds.md" in error
    # Refused before anything was served or written.
    assert not (tmp_path / "cell" / "cell.toml").exists()


def test_an_emulator_whose_start_is_a_coroutine_is_refused(tmp_path: Path) -> None:
    site = install(tmp_path / "site", {"flawed-async": "cellctl_flawed.kinds:ASYNC_START"})
    error = refused(emulate_cell(site, tmp_path, "flawed-async"))
    assert "kind flawed-async (from cellctl-flawed): its emulator's start() is async" in error


# -- 2. a fault table its LazyTable cannot read --------------------------------------------------


@pytest.mark.parametrize(
    ("kind", "target", "why"),
    [
        ("flawed-nomodule", "NO_MODULE", "ModuleNotFoundError: No module named"),
        ("flawed-notable", "NO_TABLE", "AttributeError: module 'cellctl_saw.emulator' has no"),
    ],
)
def test_a_fault_table_that_cannot_be_read_breaks_only_its_kind(
    tmp_path: Path, kind: str, target: str, why: str
) -> None:
    site = install(tmp_path / "site", {kind: f"cellctl_flawed.kinds:{target}"})
    # The help lists every other kind's switches, and says which kind it left out and why.
    shown = cellctl(site, "emulate", "cell", "--help")
    assert shown.returncode == 0, said(shown)
    assert "Traceback" not in shown.stderr
    assert "kerf100: jam, no-home, noise" in said(shown)
    assert f"machine kind '{kind}' (package {DIST}) is installed but broken" in shown.stderr
    assert why in shown.stderr
    # The other kinds' commands work: the saw's cell is checked as before.
    saw_cell = saw_template(tmp_path / "saw", "kerf100")
    checked = cellctl(site, "--cell", str(saw_cell), "cell", "check")
    assert checked.returncode == 0, said(checked)
    # The broken kind, used, is refused in words before anything is served.
    error = refused(emulate_cell(site, tmp_path, kind))
    broken = f"error: kind '{kind}' (package {DIST}) is installed but broken: its faults table"
    assert error.startswith(broken + " LazyTable("), error
    assert why in error and "fix" in error
    assert not (tmp_path / "cell" / "cell.toml").exists()
    # `cellctl kinds` lists it broken, with why; the saw beside it is fine.
    listed = cellctl(site, "kinds", "--json")
    assert listed.returncode == 0, said(listed)
    rows = {row["kind"]: row for row in json.loads(listed.stdout)}
    assert why in rows[kind]["broken"] and "its faults table" in rows[kind]["broken"], rows
    assert rows["kerf100"]["family"] == "mill" and "broken" not in rows["kerf100"], rows


# -- 3. a kind that is installed but broken ------------------------------------------------------


@pytest.mark.parametrize(
    ("target", "why"),
    [
        # Its package raises on import.
        ("cellctl_flawed.import_fails:KIND", "ImportError: cannot import name 'Blade' from"),
        # Its entry point names a module that is not there, or nothing in its module.
        ("cellctl_flawed.nowhere:KIND", "No module named 'cellctl_flawed.nowhere'"),
        ("cellctl_flawed.kinds:MISSING", "has no attribute 'MISSING'"),
    ],
)
def test_a_broken_kind_is_said_installed_but_broken_with_why(
    tmp_path: Path, target: str, why: str
) -> None:
    site = install(tmp_path / "site", {"saw2": target})
    expected = f"kind 'saw2' (package {DIST}) is installed but broken: "
    # A cell that names it.
    cell = saw_template(tmp_path / "cell", "saw2")
    checked = cellctl(site, "--cell", str(cell), "cell", "check")
    assert checked.returncode != 0
    assert expected in said(checked) and why in said(checked), said(checked)
    assert "not one of" not in said(checked)
    # A machine at a link driven as it: refused before the link is opened.
    at_link = ("mill", "--kind", "saw2", "--link", "socket://127.0.0.1:9", "status")
    error = refused(cellctl(site, *at_link))
    assert expected in error and why in error, error
    assert "entry point saw2 = " + target in error or "ImportError" in error, error
    # An emulated cell from a template that names it: refused before anything is written.
    emulated = refused(emulate_cell(site, tmp_path / "emulated", "saw2"))
    assert expected in emulated and why in emulated, emulated
    assert not (tmp_path / "emulated" / "cell").exists()


# -- 5. emulated options the kind's own options model refuses ------------------------------------


@pytest.mark.parametrize(
    ("kind", "target", "why"),
    [
        ("flawed-optname", "UNKNOWN_OPTION", "cut_margn: unknown option"),
        ("flawed-optvalue", "BAD_OPTION", "home_timeout: Input should be greater than 0"),
    ],
)
def test_emulated_options_its_options_model_refuses_make_the_kind_broken(
    tmp_path: Path, kind: str, target: str, why: str
) -> None:
    site = install(tmp_path / "site", {kind: f"cellctl_flawed.kinds:{target}"})
    error = refused(emulate_cell(site, tmp_path, kind))
    assert error.startswith(
        f"error: kind '{kind}' (package {DIST}) is installed but broken: its "
        "emulated_options(50) gave options its options model SawOptions refuses: "
    ), error
    assert why in error


# -- 4. a fault switch given without the argument it needs, or with a bad one -----------------


def test_a_switch_given_without_the_argument_it_needs_is_refused(tmp_path: Path) -> None:
    site = install(tmp_path / "site", {"flawed-switch": "cellctl_flawed.kinds:LAX_SWITCHES"})
    error = refused(emulate_cell(site, tmp_path, "flawed-switch", "--fault", "saw:slow"))
    assert error == "error: fault slow needs its argument: slow=MS", error


def test_a_bad_switch_argument_its_emulator_does_not_refuse_in_words_is_said(
    tmp_path: Path,
) -> None:
    site = install(tmp_path / "site", {"flawed-switch": "cellctl_flawed.kinds:LAX_SWITCHES"})
    error = refused(emulate_cell(site, tmp_path, "flawed-switch", "--fault", "saw:slow=soon"))
    assert error == (
        "error: fault slow=soon: kind flawed-switch (from cellctl-flawed) refused it with "
        "ValueError: could not convert string to float: 'soon' (its set_fault should raise "
        "UsageError in words: docs/kinds.md, step 5)"
    ), error
