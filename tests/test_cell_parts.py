"""The controller's parts see it through narrow interfaces (cell/ports.py), never through copies.

A part that re-declared the controller's attributes under ``if TYPE_CHECKING:`` (so mypy takes
its word for them) drifts from the controller unseen; one that reads another object's private
member depends on its insides. Both are checked here over every module of ``cellctl.cell``, by
reading its syntax tree (the import contracts are import-linter's, in ``make lint``).
"""

from __future__ import annotations

import ast
from pathlib import Path

import cellctl.cell

CELL = Path(cellctl.cell.__file__).parent


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def type_checking_declarations(source: str) -> list[int]:
    """Lines of anything but an import inside an ``if TYPE_CHECKING:`` block (attributes,
    method stubs, assignments): a type's copy that only mypy sees."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for stmt in [*node.body, *node.orelse]:
                if not isinstance(stmt, ast.Import | ast.ImportFrom):
                    found.append(stmt.lineno)
    return found


def private_reaches(source: str) -> list[int]:
    """Lines that read or write ``x._member`` of an ``x`` other than ``self`` or ``cls``."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if (
            isinstance(node, ast.Attribute)
            and node.attr.startswith("_")
            and not node.attr.startswith("__")
            and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))
        ):
            found.append(node.lineno)
    return found


def _modules() -> list[Path]:
    modules = sorted(CELL.glob("*.py"))
    assert CELL / "controller.py" in modules and CELL / "robotsteps.py" in modules
    return modules


def test_no_module_of_the_cell_declares_attributes_under_type_checking() -> None:
    offenders = {
        p.name: lines
        for p in _modules()
        if (lines := type_checking_declarations(p.read_text(encoding="utf-8")))
    }
    assert offenders == {}, (
        "declarations under `if TYPE_CHECKING:` (only imports belong there; a part's needs "
        f"are a Protocol in cell/ports.py): {offenders}"
    )


def test_no_module_of_the_cell_reaches_another_objects_private_members() -> None:
    offenders = {
        p.name: lines for p in _modules() if (lines := private_reaches(p.read_text("utf-8")))
    }
    assert offenders == {}, f"private members of another object read: {offenders}"


def test_the_checks_find_what_they_forbid() -> None:
    """The checks above are not vacuous: a mixin's copied attributes and a reach are found."""
    mixin = (
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n"
        "    from cellctl.cell.journal import Journal\n"
        "class Steps:\n"
        "    if TYPE_CHECKING:\n"
        "        journal: Journal\n"
        "        def log(self, text: str) -> None: ...\n"
        "    def go(self, other: object) -> None:\n"
        "        self._mine = other._theirs\n"
    )
    assert type_checking_declarations(mixin) == [6, 7]
    assert private_reaches(mixin) == [9]
