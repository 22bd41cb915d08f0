"""``cellctl service install`` / ``status``: the systemd unit that runs a cell's controller,
checked by systemd's own ``systemd-analyze verify`` where it is installed, and read back."""

from __future__ import annotations

import os
import pwd
import shutil
import subprocess
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.cell.config import load_cell
from cellctl.emulators.cell import EXAMPLE_CELL
from cellctl.errors import UsageError
from cellctl.ui.systemd_unit import (
    SERIAL_DEVICES,
    SYSTEM_UNIT_DIR,
    ServiceUnit,
    parse_unit,
    unit_target,
)
from tests.conftest import CELLCTL


def cellctl(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CELLCTL, *args], capture_output=True, text=True, timeout=60, cwd=cwd, check=False
    )


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    """A copy of the example cell, owned by a user who is not root (nobody, when we are root)."""
    directory = tmp_path / "lab"
    shutil.copytree(EXAMPLE_CELL, directory)
    if os.geteuid() == 0:
        nobody = pwd.getpwnam("nobody")
        for path in [directory, *directory.rglob("*")]:
            os.chown(path, nobody.pw_uid, nobody.pw_gid)
    return directory


def owner(path: Path) -> str:
    return pwd.getpwuid(path.stat().st_uid).pw_name


def test_install_writes_a_hardened_unit_for_the_cells_user(cell: Path, tmp_path: Path) -> None:
    target = tmp_path / "cellctl-lab.service"
    result = cellctl("service", "install", "--cell", str(cell), "--output", str(target))
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"wrote {target}: cellctl-lab.service runs the cell in {cell}" in result.stdout
    unit = parse_unit(target.read_text())
    service = unit["Service"]
    exe = Path(CELLCTL[0])
    assert service["ExecStart"] == [f"{exe} --cell {cell} run --no-live"]
    assert exe.is_absolute() and exe.is_file()
    assert service["User"] == [owner(cell)] and owner(cell) != "root"
    assert service["WorkingDirectory"] == [str(cell)]
    assert service["Restart"] == ["on-failure"]
    assert service["NoNewPrivileges"] == ["yes"]
    assert service["ProtectSystem"] == ["strict"]
    # The cell, and the machine's lock directory where the link locks are (shared with shells).
    assert service["ReadWritePaths"] == [str(cell), "-/run/lock"]
    assert service["ProtectHome"] == ["yes"]  # neither the cell nor cellctl is under /home
    assert service["PrivateTmp"] == ["yes"]
    # This cell is under /tmp (the test's): bound into the service's private /tmp, not hidden.
    assert str(cell).startswith("/tmp/") and service["BindPaths"] == [str(cell)]
    assert service["DevicePolicy"] == ["closed"]
    assert service["DeviceAllow"] == [f"{d} rw" for d in SERIAL_DEVICES]
    assert "char-ttyUSB rw" in service["DeviceAllow"]
    assert service["SupplementaryGroups"] == ["dialout"]
    assert unit["Install"]["WantedBy"] == ["multi-user.target"]
    name = load_cell(cell).name  # cell.toml's
    assert unit["Unit"]["Description"] == [f"cellctl: the controller of {name} ({cell})"]


@pytest.mark.skipif(
    shutil.which("systemd-analyze") is None,
    reason="systemd-analyze is not installed (make test installs systemd): only the "
    "`systemd-analyze verify` step is skipped; the unit's content is checked by the other tests",
)
def test_systemd_analyze_verifies_the_unit(cell: Path, tmp_path: Path) -> None:
    target = tmp_path / "cellctl-lab.service"
    # root: systemd warns about "nobody" (a special user); a real cell has its own user.
    user = "root" if os.geteuid() == 0 else pwd.getpwuid(os.geteuid()).pw_name
    made = cellctl("service", "install", "--cell", str(cell), "--user", user, "-o", str(target))
    assert made.returncode == 0, made.stdout + made.stderr
    verify = subprocess.run(
        ["systemd-analyze", "verify", "--man=no", str(target)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    # It exits 0 on a key it ignores but says so: every word it says is a finding.
    assert (verify.returncode, verify.stdout + verify.stderr) == (0, ""), target.read_text()


def test_an_existing_unit_stays_without_force(cell: Path, tmp_path: Path) -> None:
    target = tmp_path / "cellctl-lab.service"
    target.write_text("# the operator's own unit\n")
    refused = cellctl("service", "install", "--cell", str(cell), "--output", str(target))
    assert refused.returncode != 0
    assert f"{target} exists: --force replaces it" in refused.stderr
    assert target.read_text() == "# the operator's own unit\n"
    forced = cellctl("service", "install", "--cell", str(cell), "--output", str(target), "--force")
    assert forced.returncode == 0, forced.stderr
    assert "ExecStart=" in target.read_text()


def test_print_writes_the_unit_to_stdout_only(cell: Path, tmp_path: Path) -> None:
    result = cellctl("--cell", str(cell), "service", "install", "--print", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert parse_unit(result.stdout)["Service"]["User"] == [owner(cell)]
    assert list(tmp_path.iterdir()) == [cell]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--user", "no-such-user-h19"], "no user 'no-such-user-h19' on this machine"),
        (["--name", "cellctl lab"], "unit name 'cellctl lab': letters, digits"),
    ],
)
def test_bad_input_is_refused(cell: Path, tmp_path: Path, args: list[str], message: str) -> None:
    target = tmp_path / "unit.service"
    result = cellctl("service", "install", "--cell", str(cell), "-o", str(target), *args)
    assert result.returncode != 0
    assert message in result.stderr
    assert not target.exists()


def test_a_directory_that_is_no_cell_is_refused(tmp_path: Path) -> None:
    result = cellctl("service", "install", "--cell", str(tmp_path), "--print")
    assert result.returncode != 0
    assert result.stdout == ""
    # The file named once, and what to do.
    toml = tmp_path / "cell.toml"
    assert f"error: {toml}: no such file (create it, or run 'cellctl emulate cell')" in (
        result.stderr
    ), result.stderr
    assert result.stderr.count(str(toml)) == 1, result.stderr


def test_a_path_the_unit_would_have_to_quote_is_refused(cell: Path) -> None:
    spaced = cell.parent / "my lab"
    cell.rename(spaced)
    result = cellctl("service", "install", "--cell", str(spaced), "--print")
    assert result.returncode != 0
    assert f"cell directory '{spaced}': a systemd unit here takes absolute paths" in result.stderr


@pytest.mark.skipif(os.geteuid() != 0, reason="needs a cell directory owned by root")
def test_a_root_cell_needs_an_explicit_user(tmp_path: Path) -> None:
    shutil.copytree(EXAMPLE_CELL, tmp_path / "lab")
    result = cellctl("service", "install", "--cell", str(tmp_path / "lab"), "--print")
    assert result.returncode != 0
    assert "belongs to root: give --user NAME" in result.stderr


def test_root_writes_to_the_system_unit_directory_and_others_must_say_where() -> None:
    name = "cellctl-lab.service"
    assert unit_target(name, output=None, euid=0) == SYSTEM_UNIT_DIR / name
    assert unit_target(name, output=Path("u.service"), euid=1000) == Path("u.service")
    with pytest.raises(UsageError, match="give --output FILE or --print"):
        unit_target(name, output=None, euid=1000)


def test_status_reads_the_unit(cell: Path, tmp_path: Path) -> None:
    target = tmp_path / "cellctl-lab.service"
    assert cellctl("service", "install", "--cell", str(cell), "-o", str(target)).returncode == 0
    result = cellctl("--cell", str(cell), "service", "status", "--unit-file", str(target))
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0] == f"unit:    cellctl-lab.service: {target}"
    assert lines[1] == f"runs:    {CELLCTL[0]} --cell {cell} run --no-live  (as {owner(cell)})"
    # Enabled and active come from systemctl; where systemd does not run, the status says so.
    if shutil.which("systemctl") is None:
        assert lines[2].startswith("systemd: not on this machine (no systemctl)")
    elif not Path("/run/systemd/system").is_dir():
        assert lines[2].startswith("systemd: not running here (no /run/systemd/system")
    else:
        assert lines[2].startswith("enabled:") and lines[3].startswith("active:")


def test_status_says_when_the_unit_runs_another_cell(cell: Path, tmp_path: Path) -> None:
    target = tmp_path / "cellctl-lab.service"
    assert cellctl("service", "install", "--cell", str(cell), "-o", str(target)).returncode == 0
    other = tmp_path / "other"
    other.mkdir()
    result = cellctl("service", "status", "--cell", str(other), "--unit-file", str(target))
    assert result.returncode == 0, result.stderr
    assert f"note:    it runs the cell in {cell}, not {other}" in result.stdout


def test_status_of_a_unit_not_installed(tmp_path: Path) -> None:
    missing = tmp_path / "cellctl-lab.service"
    result = cellctl("service", "status", "--cell", str(tmp_path), "--unit-file", str(missing))
    assert result.returncode == 1
    assert f"not installed (no {missing}); `cellctl service install` writes it" in result.stdout


REFERENCE = ServiceUnit(Path("/srv/lab"), "lab", "cell", Path("/usr/bin/cellctl"), "x.service")


@settings(max_examples=150, deadline=None)
@given(
    directory=st.text(min_size=1, max_size=30),
    cell_name=st.text(max_size=40),
    user=st.text(min_size=1, max_size=12),
)
def test_no_input_adds_a_line_or_a_word_to_the_unit(
    directory: str, cell_name: str, user: str
) -> None:
    cell = Path("/srv") / directory
    try:
        unit = ServiceUnit(cell, cell_name, user, Path("/usr/bin/cellctl"), "x.service")
    except UsageError:
        return  # refused before a unit was written
    text = unit.text()
    parsed, reference = parse_unit(text), parse_unit(REFERENCE.text())
    assert {s: list(keys) for s, keys in parsed.items()} == {
        s: list(keys) for s, keys in reference.items()
    }
    assert all(len(parsed[s][k]) == len(reference[s][k]) for s in reference for k in reference[s])
    service = parsed["Service"]
    assert service["ExecStart"][0].split() == [
        "/usr/bin/cellctl",
        "--cell",
        str(cell),
        "run",
        "--no-live",
    ]
    assert service["User"] == [user]
    assert service["ReadWritePaths"] == [str(cell), "-/run/lock"]
    assert service["WorkingDirectory"] == [str(cell)]
    assert len(text.splitlines()) == len(REFERENCE.text().splitlines())
