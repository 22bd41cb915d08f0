"""Stopping transfers as a shop's user does: Ctrl-C of a ``dnc send``/``drip`` client (its own
transfer only, ended the clean way), a second transfer to a busy machine refused at once,
``dnc serve`` stopped during a drip-feed, a shop with a machine that cannot be reached.
Real processes (``cellctl dnc ...``) against emulated controls over a pty and TCP."""

from __future__ import annotations

import asyncio
import signal
from pathlib import Path

import pytest
from click.testing import CliRunner

from cellctl.emulators.serve import serve
from cellctl.kinds.iso_cnc.dnc.store import ShopStore
from cellctl.kinds.iso_cnc.emulator import IsoCncEmulator, Mode
from cellctl.ui.cli import main as cli_main
from tests.conftest import CELLCTL, refusing_port, until
from tests.test_dnc_cli import (  # noqa: F401  (shop and served are fixtures)
    LINE,
    Shop,
    cellctl,
    finished,
    served,
    shop,
    wait_state,
)
from tests.test_dnc_server import surfacing

#: Moves of the drip-feeds stopped mid-way: about 45 s of line time at 9600 baud, so a feed
#: is still running when the test, on a loaded box, looks at it or stops it (400 moves took
#: 5 s, and a `cellctl dnc status` started on a busy box once came after its end).
MOVES = 4000


async def progress_under_way(where: Shop, name: str) -> None:
    async def going() -> bool:
        p = (await where.status())["machines"][name]["progress"] or {}
        return 0 < int(p.get("done", 0)) < int(p.get("total", 0)) - 100

    await until(going, f"{name}'s transfer under way", 30)


async def run_here(*args: str) -> tuple[int, str]:
    """``cellctl ARGS`` in this process (a worker thread, its own loop): for a refusal, which
    needs no signal, without a process start."""

    def invoke() -> tuple[int, str]:
        result = CliRunner().invoke(cli_main, list(args))
        return result.exit_code, result.output

    async with asyncio.timeout(60):
        return await asyncio.to_thread(invoke)


async def test_ctrl_c_cancels_a_waiting_send_and_a_second_send_is_refused(served: Shop) -> None:  # noqa: F811
    root = str(served.root)
    first = await cellctl("dnc", "send", "mill1", "O1234", "--dir", root)
    await wait_state(served, "mill1", "reading O1234.nc")
    # A second transfer to the busy machine: refused at once, in use (exit 6), how to stop it.
    for command in ("send", "drip"):
        code, said = await finished(await cellctl("dnc", command, "mill1", "O1234", "--dir", root))
        assert code == 6, said
        assert "mill1 is busy: reading O1234.nc" in said and "cellctl dnc stop mill1" in said
        what = "drip-feed" if command == "drip" else "read-in"
        assert f"mill1: {what} of O1234" not in said  # refused before any prompt
    first.send_signal(signal.SIGINT)  # the user's Ctrl-C
    code, said = await finished(first)
    assert code == 130, said
    assert "was cancelled before the control began its read (nothing was sent)" in said
    await wait_state(served, "mill1", "idle")
    # The cancelled read-in is not carried out later: the control's READ gets one tape only,
    # the next one sent.
    control = served.controls["mill1"]
    control.read()
    again = await cellctl("dnc", "send", "mill1", "O1234", "--dir", root)
    code, said = await finished(again)
    assert code == 0, said
    log = ShopStore(served.root).log_lines("mill1")
    assert sum("O1234.nc: read in," in line for line in log) == 1, log
    assert any("stopped by its sender: the read-in of O1234.nc was cancelled" in x for x in log)
    # `dnc stop` with nothing running says so (never an empty line).
    code, said = await finished(await cellctl("dnc", "stop", "mill1", "--dir", root))
    assert code == 0 and "mill1: nothing to stop" in said, said


async def test_ctrl_c_ends_a_running_drip_feed_cleanly_and_status_shows_progress(
    served: Shop,  # noqa: F811
    tmp_path: Path,
) -> None:
    program = tmp_path / "surface.nc"
    program.write_text(surfacing(MOVES))
    control = served.controls["mill2"]
    control.set_mode(Mode.RMT)
    drip = await cellctl("dnc", "drip", "mill2", str(program), "--dir", str(served.root))
    await wait_state(served, "mill2", "drip-feeding surface.nc")
    control.cycle_start()
    await progress_under_way(served, "mill2")
    # `dnc status` in text: the progress the console shows, not only the state.
    code, said = await finished(await cellctl("dnc", "status", "--dir", str(served.root)))
    assert code == 0, said
    row = next(x for x in said.splitlines() if x.startswith("mill2:"))
    assert "mill2: busy: drip-feeding surface.nc" in row
    assert " chars (" in row and "chars/s" in row and "stall " in row, row
    drip.send_signal(signal.SIGINT)
    code, said = await finished(drip)
    assert code == 130, said
    assert "stopped by its sender: the drip-feed of surface.nc ended at " in said
    # Its progress bar ends "stopped", not "done" (a pipe gets the bar's line as it stops).
    bar = [x for x in said.splitlines() if x.startswith("surface.nc") and "chars" in x][-1]
    assert " stopped " in f"{bar} " and " done " not in f"{bar} ", said
    # Ended as the spec ends a tape: the rest of a block, then %: the control ran what it
    # held and left the read, no alarm; the program was not run to its end.
    await until(lambda: control.activity == "idle", "the control out of its read")
    assert control.runs[-1].done and not control.alarms
    assert control.runs[-1].blocks < MOVES
    await wait_state(served, "mill2", "idle")
    log = "\n".join(ShopStore(served.root).log_lines("mill2"))
    assert "stopped by its sender: the drip-feed of surface.nc ended at" in log


async def test_status_text_shows_a_refused_request_whose_punch_is_kept(served: Shop) -> None:  # noqa: F811
    control = served.controls["mill1"]
    control.memory[9999] = "O9999 (LOAD O7777)\n"
    control.punch(9999)

    async def refused() -> bool:
        error = (await served.status())["machines"]["mill1"]["error"] or {}
        return "refused" in str(error.get("text"))

    await until(refused, "the request refused", 30)
    code, said = await finished(await cellctl("dnc", "status", "--dir", str(served.root)))
    assert code == 0, said
    assert "mill1: idle | last error: request load O7777 refused: no program O7777" in said
    (kept,) = ShopStore(served.root).received("mill1", 9999)
    assert kept.path.read_text() == "O9999 (LOAD O7777)\n"


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM])
async def test_serve_stopped_during_a_drip_feed_ends_it_and_tells_its_client(
    shop: Shop,  # noqa: F811
    tmp_path: Path,
    stop: signal.Signals,
) -> None:
    program = tmp_path / "surface.nc"
    program.write_text(surfacing(MOVES))
    server = await cellctl("dnc", "serve", "--dir", str(shop.root))
    try:
        await until(lambda: (shop.root / "api.sock").exists(), "dnc serve's API", 30)
        control = shop.controls["mill2"]
        control.set_mode(Mode.RMT)
        drip = await cellctl("dnc", "drip", "mill2", str(program), "--dir", str(shop.root))
        await wait_state(shop, "mill2", "drip-feeding surface.nc")
        control.cycle_start()
        await progress_under_way(shop, "mill2")
        server.send_signal(stop)  # Ctrl-C, or systemd stopping the service
        code, said = await finished(server, 30)
        assert code == 0, said
        assert "DNC server stopping: ending what is in flight the clean way" in said
        assert "mill2: drip-feeding surface.nc" in said
        code, told = await finished(drip, 30)
        assert code == 130, told  # stopped before its end: as Ctrl-C, not a failure
        assert "the DNC server stopped: the drip-feed of surface.nc ended at " in told, told
        assert "closed the connection" not in told
        log = "\n".join(ShopStore(shop.root).log_lines("mill2"))
        assert "the DNC server stopped: the drip-feed of surface.nc ended at" in log
        assert not control.alarms
    finally:
        if server.returncode is None:
            server.kill()
            await finished(server)


async def test_serve_starts_with_a_machine_offline_and_takes_it_when_it_comes(
    tmp_path: Path,
) -> None:
    held = refusing_port()  # nothing answers there until the machine comes
    port = held.getsockname()[1]
    alive = IsoCncEmulator()
    alive_server = await serve(alive, "socket://127.0.0.1:0", LINE)
    root = tmp_path / "shop"
    root.mkdir()
    (root / "dnc.toml").write_text(
        f'[machines.a]\nlink = "socket://127.0.0.1:{port}"\n\n'
        f'[machines.b]\nlink = "{alive_server.url}"\n'
    )
    b_shop = Shop(root, {"b": alive}, [alive_server])
    proc = await cellctl("dnc", "serve", "--dir", str(root))
    late = None
    try:
        await until(lambda: proc.returncode is not None or (root / "api.sock").exists(), "API")
        assert proc.returncode is None
        machines = (await b_shop.status())["machines"]
        assert machines["b"]["condition"] == "idle"
        assert machines["a"]["condition"] == "offline"
        assert machines["a"]["error"]["text"].startswith("a: offline: ")
        _, said = await finished(await cellctl("dnc", "status", "--dir", str(root)))
        assert "a: offline | last error: a: offline: " in said, said
        # The machine comes: the server takes it (as it does a link that failed later).
        held.close()
        late = await serve(IsoCncEmulator(), f"socket://127.0.0.1:{port}", LINE)

        async def online() -> bool:
            return str((await b_shop.status())["machines"]["a"]["condition"]) == "idle"

        await until(online, "machine a online", 30)
        # Its log says both, in one style: offline (once), then online again.
        said = [line.split(" ", 1)[1] for line in ShopStore(root).log_lines("a")]
        offline = [i for i, x in enumerate(said) if x.startswith("error: a: offline: ")]
        back = f"a: online: its link socket://127.0.0.1:{port} is open again"
        assert len(offline) == 1 and back in said[offline[0] + 1 :], said
    finally:
        held.close()
        await b_shop.close()
        proc.terminate()
        await finished(proc, 20)
        await alive_server.close()
        if late is not None:
            await late.close()


async def test_an_unknown_machine_is_named_and_nothing_is_created(shop: Shop) -> None:  # noqa: F811
    root = str(shop.root)
    for args in (
        ("send", "mill3", "O1234"),
        ("drip", "mill3", "O1234"),
        ("receive", "mill3"),
        ("stop", "mill3"),
        ("diff", "mill3"),
        ("diff", "mill3", "O1234"),
    ):
        code, said = await run_here("dnc", *args, "--dir", root)
        assert code == 2, (args, said)
        assert "unknown machine 'mill3'" in said and "(known: mill1, mill2)" in said, said
        assert not (shop.root / "mill3").exists(), args
    # and a read of a known machine with nothing yet creates nothing either
    code, said = await run_here("dnc", "diff", "mill2", "--dir", root)
    assert code == 2 and "nothing received from mill2 yet" in said, said
    assert not (shop.root / "mill2" / "received").exists()


async def test_refusals_come_before_any_prompt(
    shop: Shop,  # noqa: F811
    tmp_path: Path,
) -> None:
    root = str(shop.root)
    code, said = await run_here("dnc", "receive", "mill1", "--timeout", "0", "--dir", root)
    assert code == 2 and "--timeout" in said and "press PUNCH" not in said, said
    # A program file whose name and text disagree on its O-number: refused, nothing sent.
    store = ShopStore(shop.root)
    (store.machine("mill1") / "programs" / "O1001.nc").write_text("O1234\nG00 X0\nM30\n")
    code, said = await run_here("dnc", "send", "mill1", "O1001", "--dir", root)
    assert code == 2, said
    assert "its name says O1001 but its text is O1234" in said
    assert shop.controls["mill1"].chars_read == 0
    # The link held by another shop's server: refused (exit 6) before the operator is asked.
    other = tmp_path / "other"
    other.mkdir()
    url = shop.servers[0].url
    (other / "dnc.toml").write_text(f'[machines.other]\nlink = "{url}"\n')
    holder = await cellctl("dnc", "serve", "--dir", root)
    try:
        await until(lambda: (shop.root / "api.sock").exists(), "dnc serve's API", 30)
        (ShopStore(other).machine("other") / "programs" / "O1234.nc").write_text(
            "O1234\nG00 X0\nM30\n"
        )
        code, said = await finished(
            await cellctl("dnc", "send", "other", "O1234", "--dir", str(other))
        )
        assert code == 6, said
        assert "other: read-in of O1234" not in said  # refused before the prompt
        again = await finished(await cellctl("dnc", "serve", "--dir", root))
        assert "the shop in" in again[1] and "the cell in" not in again[1], again
    finally:
        holder.terminate()
        await finished(holder, 20)


async def test_use_cell_serves_and_reads_the_cells_own_shop(tmp_path: Path) -> None:
    control = IsoCncEmulator()
    link = await serve(control, "socket://127.0.0.1:0", LINE)
    cell = tmp_path / "cell"
    cell.mkdir()
    (cell / "cell.toml").write_text(f'[machines.vf2]\nkind = "iso-cnc"\nlink = "{link.url}"\n')
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    args = ("--cell", str(cell), "dnc")

    async def in_elsewhere(*more: str) -> tuple[int, str]:
        return await finished(await started(*more))

    async def started(*more: str) -> asyncio.subprocess.Process:
        return await asyncio.create_subprocess_exec(
            *CELLCTL,
            *args,
            *more,
            cwd=elsewhere,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
        )

    try:
        # No server: a read, from an unrelated directory, creates nothing anywhere.
        code, said = await in_elsewhere("status", "--use-cell")
        assert code == 0 and "vf2: no server runs" in said, said
        assert not (elsewhere / "shop").exists() and not (cell / "shop").exists()
        server = await started("serve", "--use-cell")
        try:
            await until(lambda: (cell / "shop" / "api.sock").exists(), "the cell's shop API", 30)
            code, said = await in_elsewhere("status", "--use-cell")
            assert code == 0 and "vf2: idle" in said and "idle: idle" not in said, said
            assert not (elsewhere / "shop").exists()
        finally:
            server.terminate()
            await finished(server, 20)
    finally:
        await link.close()
