"""``cellctl dnc`` as a user runs it: ``dnc serve`` in its own process, the hand commands
through its control API (and on their own link when no server runs), against emulated
controls over a pty and TCP."""

from __future__ import annotations

import asyncio
import json
import os
import re
import socket
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from cellctl.drivers.state import StateStore
from cellctl.emulators.serve import Server, serve
from cellctl.errors import AccessDenied, LinkError
from cellctl.kinds.iso_cnc.dnc.store import ShopStore
from cellctl.kinds.iso_cnc.emulator import EmulatorOptions, IsoCncEmulator, Mode
from cellctl.kinds.iso_cnc.status import IsoCncState
from cellctl.link import LineSettings
from cellctl.link.lock import holder
from cellctl.service.client import RemoteCell
from cellctl.service.token import read_token
from tests.conftest import CELLCTL, refusing_port, until

LINE = LineSettings.parse("9600,7E2")
BRACKET = "O1234 (BRACKET)\nG21 G90 G17\nG00 X0 Y0 Z5.\nG01 Z-1. F300\nG01 X10. Y5.\nM30\n"
DRIP = "O5000 (SURFACE)\nG21 G90 G17\nG01 X1. F3000\nX2. Z-0.1\nX3. Z-0.2\nM30\n"


@dataclass
class Shop:
    root: Path
    controls: dict[str, IsoCncEmulator]
    servers: list[Server]
    #: One connection to ``dnc serve``'s API for all of a test's polls: a connection a poll
    #: (fifty a second) kept a loaded box's server answering handshakes, not the test.
    api: RemoteCell | None = None

    async def status(self) -> dict[str, Any]:
        """``cell.status`` of the running ``dnc serve``; reconnects once if it went away."""
        try:
            return await self._call_status()
        except LinkError:
            await self.close()
            return await self._call_status()

    async def _call_status(self) -> dict[str, Any]:
        if self.api is None:
            self.api = await RemoteCell.connect(
                token=read_token(self.root), socket_path=self.root / "api.sock"
            )
        result: dict[str, Any] = await self.api.call("cell.status")
        return result

    async def close(self) -> None:
        if self.api is not None:
            api, self.api = self.api, None
            await api.close()


async def cellctl(*args: str) -> asyncio.subprocess.Process:
    return await asyncio.create_subprocess_exec(
        *CELLCTL,
        *args,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
        env={**os.environ, "COLUMNS": "200"},
    )


async def finished(proc: asyncio.subprocess.Process, timeout: float = 60) -> tuple[int, str]:
    """The exit code and output of ``proc`` once it ends; a process still running after
    ``timeout`` is killed and the failure shows what it had said."""
    communicating = asyncio.ensure_future(proc.communicate())
    done, _ = await asyncio.wait({communicating}, timeout=timeout)
    if not done:
        proc.kill()
        out, err = await communicating
        said = (out + err).decode(errors="replace")[-3000:]
        raise AssertionError(f"still running after {timeout:g} s; it had said:\n{said}")
    out, err = communicating.result()
    return proc.returncode or 0, out.decode() + err.decode()


async def state_of(shop: Shop, name: str) -> str:
    return str((await shop.status())["machines"][name]["state"])


async def wait_state(shop: Shop, name: str, prefix: str, timeout: float = 30.0) -> None:
    """Wait (the suite's :func:`until`) for machine ``name``'s state to start with ``prefix``;
    a failure says the state last seen."""
    seen = [""]

    async def there() -> bool:
        seen[0] = await state_of(shop, name)
        return seen[0].startswith(prefix)

    try:
        await until(there, f"{name} {prefix!r}", timeout)
    except AssertionError as e:
        raise AssertionError(f"{e}; its state: {seen[0]!r}") from None


@pytest.fixture
async def shop(tmp_path: Path) -> AsyncIterator[Shop]:
    controls = {"mill1": IsoCncEmulator(EmulatorOptions()), "mill2": IsoCncEmulator()}
    servers = [
        await serve(controls["mill1"], "pty", LINE),
        await serve(controls["mill2"], "socket://127.0.0.1:0", LINE),
    ]
    root = tmp_path / "shop"
    root.mkdir()
    rows = [
        f'[machines.{name}]\nlink = "{server.url}"\n'
        for name, server in zip(controls, servers, strict=True)
    ]
    (root / "dnc.toml").write_text("\n".join(rows))
    (ShopStore(root).machine("mill1") / "programs" / "O1234.nc").write_text(BRACKET)
    shop = Shop(root, controls, servers)
    try:
        yield shop
    finally:
        await shop.close()
        for server in servers:
            await server.close()


@pytest.fixture
async def served(shop: Shop) -> AsyncIterator[Shop]:
    proc = await cellctl("dnc", "serve", "--dir", str(shop.root))
    try:
        await until(lambda: (shop.root / "api.sock").exists(), "dnc serve's API", 30)
        await until(lambda: proc.returncode is None, "dnc serve running")
        yield shop
    finally:
        await shop.close()
        proc.terminate()
        code, output = await finished(proc, 20)
        assert code in (0, -15), output


def started_then_ended(log: list[str], program: str, *, drip: bool) -> None:
    """The machine's log has a transfer by hand's start, then its end, in one style: the
    program, what, and the same characters of program."""
    what, done = ("drip-feed", "drip-fed") if drip else ("read-in", "read in")
    start = [i for i, line in enumerate(log) if f" {program}: {what} by hand, " in line]
    end = [i for i, line in enumerate(log) if f" {program}: {done}, " in line]
    assert start and end and start[-1] < end[-1], log
    press = "CYCLE START" if drip else "READ"
    assert f"characters of program: waiting for read: press {press} on the" in log[start[-1]]
    counts = [re.search(r", (\d+) characters of program", log[i]) for i in (start[-1], end[-1])]
    assert all(counts) and len({c.group(1) for c in counts if c}) == 1, log


async def test_send_by_hand_goes_through_the_running_server(served: Shop) -> None:
    status = await served.status()
    assert {m["kind"] for m in status["machines"].values()} == {"iso-cnc"}
    assert status["machines"]["mill2"]["condition"] == "idle"
    proc = await cellctl("dnc", "send", "mill1", "O1234", "--dir", str(served.root))
    await wait_state(served, "mill1", "reading")
    served.controls["mill1"].read()  # the operator presses READ
    code, output = await finished(proc)
    assert code == 0, output
    # What the operator does for a read-in, in the words `dnc status` and the log use.
    prompt = "mill1: read-in of O1234: waiting for read: press READ on the control, in EDIT mode"
    assert prompt in output and "CYCLE START" not in output, output
    assert "O1234.nc: read in, " in output
    assert served.controls["mill1"].memory[1234] == BRACKET
    started_then_ended(ShopStore(served.root).log_lines("mill1"), "O1234.nc", drip=False)
    # `dnc status --json`: the server's view of each machine, for scripts.
    code, output = await finished(
        await cellctl("dnc", "status", "--json", "--dir", str(served.root))
    )
    assert code == 0, output
    shown = json.loads(output)
    assert sorted(shown) == ["mill1", "mill2"]
    assert shown["mill2"]["condition"] == "idle"


async def test_drip_a_file_and_receive_by_hand(served: Shop, tmp_path: Path) -> None:
    program = tmp_path / "surface.nc"
    program.write_text(DRIP)
    proc = await cellctl("dnc", "drip", "mill2", str(program), "--dir", str(served.root))
    await wait_state(served, "mill2", "drip-feeding")
    control = served.controls["mill2"]
    control.set_mode(Mode.RMT)
    control.cycle_start()
    try:
        code, output = await finished(proc)
    except AssertionError as e:  # what the control did, beside what the command said
        seen = f"control: {control.mode} {control.activity}, alarms {control.alarms}"
        raise AssertionError(f"{e}\n{seen}, chars read {control.chars_read}") from None
    assert code == 0, output
    # A drip-feed is started by CYCLE START in RMT: READ in EDIT would store it instead.
    prompt = (
        "mill2: drip-feed of surface.nc: waiting for read: press CYCLE START on the control, "
        "in RMT (DNC) mode"
    )
    assert prompt in " ".join(output.split()) and "press READ" not in output, output
    assert "surface.nc: drip-fed" in output
    assert control.runs[-1].done and control.runs[-1].blocks == 6
    # receive: the operator punches the program back
    receiver = await cellctl(
        "dnc", "receive", "mill2", "--timeout", "30", "--dir", str(served.root)
    )
    await wait_state(served, "mill2", "waiting for punch")
    control.memory[5000] = DRIP
    control.set_mode(Mode.EDIT)
    control.punch(5000)
    code, output = await finished(receiver)
    assert code == 0, output
    assert "received O5000" in output
    (kept,) = ShopStore(served.root).received("mill2", 5000)
    assert kept.path.read_text() == DRIP
    diff = await cellctl("dnc", "diff", "mill2", "O5000", "--dir", str(served.root))
    code, output = await finished(diff)
    assert code == 0 and "matches O5000_" in output, output  # what was drip-fed came back
    # edited at the machine, punched again: a second version, and diff shows the edit
    receiver = await cellctl("dnc", "receive", "mill2", "--dir", str(served.root))
    await wait_state(served, "mill2", "waiting for punch")
    await until(lambda: control.activity == "idle", "the control idle")
    control.memory[5000] = DRIP.replace("X3. Z-0.2", "X3. Z-0.25")
    control.punch(5000)
    code, output = await finished(receiver)
    assert code == 0, output
    assert len(ShopStore(served.root).received("mill2", 5000)) == 2
    diff = await cellctl("dnc", "diff", "mill2", "O5000", "--dir", str(served.root))
    code, output = await finished(diff)
    assert code == 1
    assert "-X3. Z-0.2\n+X3. Z-0.25" in output


async def test_a_wrong_token_is_refused_and_a_second_server_too(served: Shop) -> None:
    with pytest.raises(AccessDenied):
        await RemoteCell.connect(token="x" * 43, socket_path=served.root / "api.sock")
    again = await cellctl("dnc", "serve", "--dir", str(served.root))
    code, output = await finished(again)
    assert code != 0
    assert "already run by cellctl dnc serve" in output


async def test_a_shop_on_a_link_served_elsewhere_is_refused_before_it_writes_a_file(
    served: Shop, tmp_path: Path
) -> None:
    """Another shop naming a link this server holds: refused, naming the holder, and its
    directory left as it was (no API token, no lock, no machine directory)."""
    other = tmp_path / "other"
    other.mkdir()
    (other / "dnc.toml").write_text(f'[machines.again]\nlink = "{served.servers[1].url}"\n')
    code, output = await finished(await cellctl("dnc", "serve", "--dir", str(other)))
    assert code == 6, output
    assert f"{served.servers[1].url} is in use by cellctl dnc serve (pid " in output, output
    assert sorted(os.listdir(other)) == ["dnc.toml"]


async def test_a_shop_whose_listen_address_is_taken_is_refused_before_it_writes_a_file(
    tmp_path: Path,
) -> None:
    taken = socket.socket()  # another server answers on the address
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    link = refusing_port()  # the machine: never reached
    port = taken.getsockname()[1]
    try:
        (tmp_path / "dnc.toml").write_text(
            f'[dnc]\nlisten = "127.0.0.1:{port}"\n\n[machines.a]\n'
            f'link = "socket://127.0.0.1:{link.getsockname()[1]}"\n'
        )
        code, output = await finished(await cellctl("dnc", "serve", "--dir", str(tmp_path)))
    finally:
        taken.close()
        link.close()
    assert code == 2, output
    said = f'dnc.toml: [dnc] listen = "127.0.0.1:{port}": cannot listen there: address already'
    assert said in output, output
    assert sorted(os.listdir(tmp_path)) == ["dnc.toml"]


async def test_hand_send_without_a_server_opens_the_link_itself(shop: Shop) -> None:
    proc = await cellctl("dnc", "send", "mill1", "O1234", "--dir", str(shop.root))
    control = shop.controls["mill1"]
    store = StateStore(shop.root)
    # no server: the command holds the link itself and waits for the control's DC1
    await until(
        lambda: store.load("mill1").get("state") == IsoCncState.READING, "the send waiting", 30
    )
    assert holder(store.lock_path("mill1")) is not None
    control.read()
    code, output = await finished(proc)
    assert code == 0, output
    assert control.memory[1234] == BRACKET
    started_then_ended(ShopStore(shop.root).log_lines("mill1"), "O1234.nc", drip=False)
    # With no server, `dnc status --json` says so and gives each machine's last log line.
    code, output = await finished(await cellctl("dnc", "status", "--json", "--dir", str(shop.root)))
    assert code == 0, output
    shown = json.loads(output)
    assert shown["mill1"]["server"] is False
    assert "O1234.nc: read in" in shown["mill1"]["log"]
    assert holder(store.lock_path("mill1")) is None


async def test_a_bad_program_is_refused_before_a_byte_goes_out(shop: Shop, tmp_path: Path) -> None:
    bad = tmp_path / "bad.nc"
    bad.write_text("O1234\nG01 X10.\nM30\n")  # G01 without a feed
    proc = await cellctl("dnc", "send", "mill1", str(bad), "--dir", str(shop.root))
    code, output = await finished(proc)
    assert code != 0
    assert "bad.nc:2" in output
    assert shop.controls["mill1"].chars_read == 0
