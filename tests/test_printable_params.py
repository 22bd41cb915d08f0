"""Free text a caller gives (a reason, a name, an id) is printable text, as order ids are: an
escape sequence or a NUL in an emergency stop's reason would be logged raw and act on every
operator's terminal that lists the alarms. It is refused in the order ids' words, the field
named, and nothing is done."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from cellctl.cell.owner import acquire_controller_lock
from cellctl.errors import NOT_PRINTABLE, UsageError
from cellctl.mailbox.base import check_new_order
from cellctl.mailbox.wire import WireError, parse_to_cell
from cellctl.service.access import AttachedCell
from cellctl.service.client import RemoteCell, attach
from cellctl.service.server import ApiServer
from cellctl.testing.rig import CellRig
from cellctl.testing.rig import cli as rig_cli

#: What the review's operator sent: a NUL, then red text on the terminal.
ESCAPE = "\u0000\u001b[31mRED"


@pytest.fixture
async def attached(tmp_path: Path) -> AsyncIterator[tuple[CellRig, RemoteCell]]:
    async with CellRig(tmp_path / "cell") as rig:
        await rig.start_controller()
        assert rig.controller is not None
        server = ApiServer(AttachedCell(rig.controller), rig.directory)
        await server.start()
        client = await attach(rig.directory)
        try:
            yield rig, client
        finally:
            await client.close()
            await server.close()


@pytest.mark.parametrize(
    ("method", "params", "field"),
    [
        ("cell.estop", {"reason": ESCAPE}, "reason"),
        ("machines.out_of_service", {"machine": "cnc1", "reason": "bad\x1b]0;pwned\x07"}, "reason"),
        ("parts.scrap", {"id": "A-1", "reason": "line\nALARM 9 cell: forged"}, "reason"),
        ("orders.submit", {"part_type": "wax\x1b[2J"}, "part_type"),
        ("alarms.history", {"machine": "cnc1\u202e"}, "machine"),
        ("plan.run", {"add": ["wax-robot-base:1\x1b[0m"]}, "add.0"),
    ],
)  # fmt: skip
async def test_control_characters_in_free_text_are_refused_and_nothing_is_done(
    attached: tuple[CellRig, RemoteCell], method: str, params: dict[str, Any], field: str
) -> None:
    _rig, client = attached
    before = await client.call("cell.status")
    with pytest.raises(UsageError) as refused:
        await client.call(method, params)
    assert str(refused.value) == f"{method}: {field}: {NOT_PRINTABLE}"
    after = await client.call("cell.status")
    assert after["cell"]["mode"] == before["cell"]["mode"] == "running"
    assert after["alarms"] == before["alarms"] == []
    assert after["orders"] == before["orders"]
    assert all(m["in_service"] for m in after["machines"].values())


async def test_the_cli_says_it_and_the_log_and_alarms_stay_clean(
    attached: tuple[CellRig, RemoteCell],
) -> None:
    rig, client = attached
    with acquire_controller_lock(rig.directory):  # the CLI asks the controller's API
        await cli_refuses_then_takes(rig, client)


async def cli_refuses_then_takes(rig: CellRig, client: RemoteCell) -> None:
    result = await rig_cli(rig.directory, "estop", ESCAPE)
    assert result.exit_code == 2, result.output
    assert f"cell.estop: reason: {NOT_PRINTABLE}" in result.output
    assert "\x1b" not in result.output and "\x00" not in result.output
    listed = await rig_cli(rig.directory, "alarm", "list")
    assert listed.exit_code == 0 and "no active alarms" in listed.output, listed.output
    # A printable reason is taken as given (a space, accents and symbols are text).
    result = await rig_cli(rig.directory, "estop", "Tür offen — 2× geprüft")
    assert result.exit_code == 0, result.output
    status = await client.call("cell.status")
    assert [a["code"] for a in status["alarms"]] == ["estop"]
    assert "Tür offen — 2× geprüft" in status["alarms"][0]["text"]


def test_order_ids_keep_their_words_from_the_one_rule() -> None:
    with pytest.raises(UsageError) as refused:
        check_new_order("wax", 1, 0, "A\x1b[31m")
    assert str(refused.value) == f"order id 'A\\x1b[31m' {NOT_PRINTABLE}"


def test_a_cancel_from_the_factory_with_an_escape_in_its_reason_is_refused() -> None:
    payload = {"v": 1, "cancel": "order", "id": "F7", "by": "ann", "reason": ESCAPE, "asked": 1.0}
    with pytest.raises(WireError) as refused:
        parse_to_cell(json.dumps(payload).encode())
    assert f"reason: {NOT_PRINTABLE}" in str(refused.value)
    payload["reason"] = "wrong material"
    assert parse_to_cell(json.dumps(payload).encode()).reason == "wrong material"  # type: ignore[union-attr]
