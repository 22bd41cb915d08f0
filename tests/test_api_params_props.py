"""Every parameter of every control API method, fed what a hostile peer would send: huge
integers, huge lists, deep nesting, wrong types. The answer is a result or a typed refusal;
a value that fits no field is -32602 naming the field; never -32603, never a hang.

The methods run standalone on a copy of the example cell whose machines point at a closed
port, so a call that passed its checks would fail to connect, never reach a real machine."""

from __future__ import annotations

import asyncio
import shutil
import socket
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cellctl.cell.journal import open_journal
from cellctl.errors import CellctlError
from cellctl.link import MILL_LINE, ROBOT_LINE
from cellctl.service.access import LocalCell
from cellctl.service.functions import function, kind_menu
from cellctl.service.machines import MachineRef
from cellctl.service.methods import (
    INTERNAL_ERROR,
    INVALID_PARAMS,
    METHODS,
    Dispatcher,
    MachineCallParams,
    error_object,
)

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "cell"
#: The longest a call may take before the test calls it a hang.
CALL_DEADLINE = 10.0


def _fields(method: str) -> list[str]:
    """The parameters ``method`` takes (a manual function's own, and ``machine``)."""
    entry = METHODS[method]
    names = list(entry.params.model_fields)
    if entry.params is MachineCallParams:
        family, name = method.split(".")
        names += list(function(family, name).params.model_fields)
    return names


def _on_this_cell(method: str) -> bool:
    """Whether the test cell's machine of the method's family has it: a plug-in kind's own
    function (tests/plugins) is refused on the others' machines, whatever its parameters."""
    family, _, name = method.partition(".")
    kind = {"robot": "ibm7545", "mill": "dyna2400"}.get(family)
    return kind is None or any(f.name == name for f in kind_menu(kind))


FIELDS = [(m, f) for m in METHODS if _on_this_cell(m) for f in _fields(m)]


def _nested(depth: int) -> Any:
    value: Any = 1
    for _ in range(depth):
        value = [value]
    return value


def _deep_dict(depth: int) -> Any:
    value: Any = {}
    for _ in range(depth):
        value = {"a": value}
    return value


#: Values no parameter of any method takes.
FITS_NOTHING = st.one_of(
    st.integers(min_value=2**64, max_value=2**300),
    st.integers(min_value=-(2**300), max_value=-(2**64)),
    st.integers(min_value=100, max_value=3000).map(_nested),
    st.integers(min_value=100, max_value=3000).map(_deep_dict),
    st.integers(min_value=10_000, max_value=200_000).map(lambda n: [[n]] * n),
    st.integers(min_value=21, max_value=100_000).map(lambda n: [{"x": n}] * n),
)
#: Anything JSON can carry, hostile or not.
ANY_JSON = (
    st.recursive(
        st.none()
        | st.booleans()
        | st.integers(min_value=-(2**80), max_value=2**80)
        | st.floats(allow_nan=False, allow_infinity=False)
        | st.text(max_size=30),
        lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=10), inner),
        max_leaves=20,
    )
    | FITS_NOTHING
)


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])  # closed again when the block ends: connections refused


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("props") / "cell"
    shutil.copytree(EXAMPLE, directory)
    open_journal(directory).close()
    return directory


def _call(cell: Path, method: str, params: Any) -> dict[str, Any] | None:
    """The JSON-RPC error object the call gives (None for a result)."""
    port = _closed_port()
    refs = {
        "robot": MachineRef("robot", "ibm7545", f"socket://127.0.0.1:{port}", ROBOT_LINE),
        "cnc1": MachineRef("cnc1", "dyna2400", f"socket://127.0.0.1:{port}", MILL_LINE),
    }

    async def run() -> dict[str, Any] | None:
        async with LocalCell(cell, refs) as access:
            try:
                async with asyncio.timeout(CALL_DEADLINE):
                    await Dispatcher(access).call(method, params)
            except CellctlError as e:
                return error_object(e)
        return None

    return asyncio.run(run())


def _machine_for(method: str) -> dict[str, Any]:
    """A valid ``machine`` for a manual function, so its own parameters are checked."""
    family = method.split(".")[0]
    return (
        {"machine": {"robot": "robot", "mill": "cnc1"}[family]}
        if family in ("robot", "mill")
        else {}
    )


@settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
@given(target=st.sampled_from(FIELDS), value=FITS_NOTHING)
def test_a_value_that_fits_no_field_is_invalid_params_naming_it(
    cell: Path, target: tuple[str, str], value: Any
) -> None:
    method, field = target
    params = {**_machine_for(method), field: value}
    error = _call(cell, method, params)
    assert error is not None, f"{method} took {field}={str(value)[:80]}"
    assert error["code"] == INVALID_PARAMS, error
    assert field in error["message"], error


@settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
@given(
    method=st.sampled_from(sorted(METHODS)),
    data=st.data(),
)
def test_any_parameters_give_a_result_or_a_typed_refusal(
    cell: Path, method: str, data: st.DataObject
) -> None:
    names = _fields(method)
    keys = st.sampled_from(names) | st.text(min_size=1, max_size=20) if names else st.text()
    params: Any = data.draw(st.dictionaries(keys, ANY_JSON, max_size=4) | ANY_JSON, label="params")
    if isinstance(params, dict) and data.draw(st.booleans(), label="with machine"):
        params = {**_machine_for(method), **params}
    error = _call(cell, method, params)
    if error is not None:
        assert error["code"] != INTERNAL_ERROR, error
        assert len(error["message"]) < 2000, error["message"][:200]
