"""The machine kinds: found through the entry points, listed by `cellctl kinds`, and named
nowhere in src/ outside their own packages."""

from __future__ import annotations

import subprocess
from dataclasses import replace
from pathlib import Path

from pydantic import BaseModel, Field

from cellctl.kinds import registry
from cellctl.kinds.families import Mill, Robot
from cellctl.kinds.kind import attribute_docs

from .conftest import CELLCTL

ROOT = Path(__file__).resolve().parent.parent
#: Each kind's own package (where its name belongs), by the names that mean it.
KIND_PACKAGES = {
    "ibm7545": "src/cellctl/kinds/ibm7545/",
    "ibm7547": "src/cellctl/kinds/ibm7545/",
    "dyna2400": "src/cellctl/kinds/dyna2400/",
    "iso-cnc": "src/cellctl/kinds/iso_cnc/",
}
#: Kinds from outside cellctl (installed into the test environment as plug-ins, see
#: tests/plugins/): src/ names none of them anywhere.
PLUGIN_KINDS = ("kerf100",)
NAMES = [*KIND_PACKAGES, *PLUGIN_KINDS]


def test_the_1988_kinds_register_through_the_entry_points() -> None:
    found = {k.name: k for k in registry.kinds()}
    assert {"ibm7545", "ibm7547", "dyna2400"} <= set(found)
    assert found["ibm7547"].family == "robot" and found["dyna2400"].family == "mill"
    assert found["ibm7545"].origin is not None
    assert found["ibm7545"].origin.module == "cellctl.kinds.ibm7545.kind"
    assert registry.broken() == {}


def test_cellctl_kinds_lists_each_with_where_it_comes_from() -> None:
    out = subprocess.run(
        [*CELLCTL, "kinds"], capture_output=True, text=True, timeout=60, check=True
    ).stdout
    for name, maker in (("ibm7545", "IBM"), ("ibm7547", "IBM"), ("dyna2400", "Dyna")):
        line = next(line for line in out.splitlines() if line.startswith(name))
        assert maker in line and "cellctl" in line


def test_a_kind_s_options_are_refused_by_field_name() -> None:
    mill = registry.kind("dyna2400")
    try:
        mill.checked_options({"ready_wait": "soon"})
    except Exception as e:
        assert "ready_wait" in str(e)
    else:
        raise AssertionError("a bad option was accepted")


#: What a driver sets in __init__ (not on its class).
OWN = ("name", "link", "initialized")


def test_the_drivers_speak_their_family_protocol() -> None:
    robot_driver = registry.kind("ibm7545").open_driver
    mill_driver = registry.kind("dyna2400").open_driver
    assert robot_driver is not None and mill_driver is not None
    # The classes are what open_driver returns; the protocols are runtime-checkable.
    from cellctl.kinds.dyna2400.driver import Dyna2400Mill
    from cellctl.kinds.ibm7545.driver import Ibm7545Robot

    for cls, family in ((Ibm7545Robot, Robot), (Dyna2400Mill, Mill)):
        missing = [
            name
            for name in dir(family)
            if not name.startswith("_") and not hasattr(cls, name) and name not in OWN
        ]
        assert missing == [], (cls.__name__, missing)


def test_no_kind_is_named_in_src_outside_its_own_package() -> None:
    found = subprocess.run(
        # a kind named with a dash is also found spelt as its package (iso-cnc, iso_cnc)
        ["git", "grep", "-l", "-i", "-E", "|".join(NAMES).replace("-", "[-_]"), "--", "src"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    ).stdout.split()
    naming = {
        path
        for path in found
        if not path.startswith("src/cellctl/examples/")
        and not any(path.startswith(pkg) for pkg in KIND_PACKAGES.values())
    }
    assert naming == set(), "a kind is named outside its own package"


def test_the_pickers_faults_and_checks_come_from_the_kinds() -> None:
    """What the console and `emulate cell` once named by kind, each kind declares."""
    for kind in registry.kinds():
        assert kind.picked_files, kind.name
        assert kind.check_text is not None and kind.faults, kind.name
    robot = registry.kind("ibm7545")
    assert robot.picked_files == (".rec",) and "power-off" in robot.faults
    mill = registry.kind("dyna2400")
    assert mill.picked_files == (".dyn",) and "stall" in mill.faults
    problems = mill.check_text("download", "p.dyn", "NOT DYNALAN\n", mill.checked_options({}))
    assert problems and all(p.startswith("p.dyn") for p in problems)


def test_docs_kinds_md_holds_each_shipped_kind_s_options() -> None:
    docs = (ROOT / "docs" / "kinds.md").read_text(encoding="utf-8")
    for name in KIND_PACKAGES:
        assert registry.kind(name).options_table() in docs, name


class _Base(BaseModel):
    first: int = 1
    """What the base says of ``first``:
    two lines."""


class _Options(_Base):
    second: str = Field(default="x", description="given to the field")
    """the docstring the description outranks"""
    third: float = 0.5
    """Seconds, from the subclass."""
    fourth: bool = False


def test_attribute_docs_are_read_from_the_source_with_the_bases() -> None:
    docs = attribute_docs(_Options)
    assert docs["first"] == "What the base says of ``first``:\ntwo lines."
    assert docs["third"] == "Seconds, from the subclass." and "fourth" not in docs
    # The table prefers a field's own description.
    kind = registry.kind("dyna2400")
    table = replace(kind, options=_Options).options_table()
    assert "| `second` | 'x' | given to the field |" in table
    assert "| `first` | 1 | What the base says of ``first``: two lines. |" in table
    assert "| `fourth` | False |  |" in table
