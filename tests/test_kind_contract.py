"""What the cell holds a plug-in kind to, and what it does when one falls short of it: a run
that fails once begun holds its part (never cut twice), a mill that lost its setup while
the cell was down is set up again, a driver missing a member of its family or giving a
reading of the wrong type is refused naming the machine and its kind, and a reading whose
condition is not one makes that machine an error, the rest of the cell as it was.

Each kind here is the Kerf 100 saw (tests/plugins/cellctl_saw) with one thing changed,
registered in this process (:func:`cellctl.kinds.registry.registered`), in the mill-and-saw
cell (tests/plugins/kerf_cell) emulated by the rig: on virtual time where a test plays whole
orders (docs/clock.md), else on real time."""

from __future__ import annotations

import dataclasses
import json
import shutil
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest

from cellctl.clock import VirtualClock, current_clock
from cellctl.emulators.memserve import serve_mem
from cellctl.emulators.serve import DeviceLine, EmulatedDevice
from cellctl.errors import LinkClosed, UsageError
from cellctl.kinds import Condition, registry
from cellctl.kinds.families import KindContractError, RunProgress
from cellctl.kinds.kind import DriverSpec, MachineKind
from cellctl.link import LineSettings, open_link
from cellctl.service.status import build_status
from cellctl.service.status_model import CellInfo
from cellctl.testing.rig import CellRig

TEMPLATE = Path(__file__).resolve().parent / "plugins" / "kerf_cell"


def saw_variant(name: str, wrap: Callable[[Any], Any]) -> MachineKind:
    """The saw as kind ``name``, its driver passed through ``wrap`` once opened."""
    saw = registry.kind("kerf100")

    async def open_driver(spec: DriverSpec) -> Any:
        return wrap(await saw.open_driver(spec))

    return dataclasses.replace(saw, name=name, open_driver=open_driver, origin=None)


@asynccontextmanager
async def saw_cell(tmp_path: Path, kind: MachineKind | None = None) -> AsyncIterator[CellRig]:
    """The mill-and-saw cell, its saw of ``kind`` (the saw itself by default)."""
    template = tmp_path / "template"
    shutil.copytree(TEMPLATE, template)
    if kind is not None:
        toml = template / "cell.toml"
        toml.write_text(toml.read_text().replace('kind = "kerf100"', f'kind = "{kind.name}"'))
    with registry.registered(*([kind] if kind is not None else [])):
        # On virtual time the machines keep their own times; on real time 400 times faster.
        virtual = isinstance(current_clock(), VirtualClock)
        scale = {} if virtual else {"time_scale": 400.0}
        async with CellRig(tmp_path / "cell", template=template, **scale) as rig:
            yield rig


# -- 1. a run that fails once begun holds its part ------------------------------------------


class _Quiet:
    """The saw's driver, its run reporting progress only while it machines."""

    def __init__(self, inner: Any) -> None:
        self._inner = inner

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)

    async def run(self, program: Path, *, progress: Callable[[RunProgress], None] | None = None):  # type: ignore[no-untyped-def]
        def machining_only(p: RunProgress) -> None:
            if progress is not None and p.phase != "sending":
                progress(p)

        await self._inner.run(program, progress=machining_only)


@pytest.mark.virtual
async def test_a_run_that_fails_after_machining_began_holds_its_part(tmp_path: Path) -> None:
    kind = saw_variant("kerf100-quiet", _Quiet)
    async with saw_cell(tmp_path, kind) as rig:
        rig.switch_on("saw:jam")  # the first cut jams halfway
        rig.post("bar-end", 1, "A")
        await rig.start_controller()
        [held] = await rig.wait_for(rig.held_parts, "the jammed part held", timeout=60)
        assert held.location == "saw"
        assert "needs inspection: machining bars on saw failed" in held.note
        # 6. It stays in alarm with the part in its vise (no setup runs over a part): out of
        # service, said in the saw's words.
        [out] = await rig.wait_for(
            lambda: rig.alarms("saw", "out-of-service"), "the saw out of service", timeout=60
        )
        assert out.text.endswith("not ready: alarm, blade jammed"), out.text
        await rig.switch_off("saw:jam")
        await rig.wait_quiet()
        # Never run again on the part it may have cut, and no order says it was made.
        assert rig.cut_twice() == {}
        assert sum(r.get("saw", 0) for r in rig.cell.runs_per_part().values()) == 1
        assert rig.order_state("A") != "done"


# -- 2. a mill that lost its setup is set up again -------------------------------------------


def power_cycle_saw(rig: CellRig) -> None:
    """The saw's power cycled: what a restarted emulator shows (not homed, nothing loaded)."""
    from cellctl_saw.protocol import SawState

    saw = rig.cell.mills["saw"]
    saw.state, saw.alarm = SawState.NOT_HOMED, 0


async def test_a_saw_power_cycled_while_the_cell_was_down_is_set_up_again(
    tmp_path: Path,
) -> None:
    async with saw_cell(tmp_path) as rig:
        rig.post("bar-end", 1, "A")
        await rig.start_controller()
        await rig.wait_for(lambda: rig.order_state("A") == "done", "order A done", timeout=60)
        await rig.stop_controller()
        saved = json.loads((rig.directory / "state" / "saw.json").read_text())
        assert saved["homed"] is True
        power_cycle_saw(rig)
        rig.post("bar-end", 1, "B")
        controller = await rig.start_controller()
        await rig.wait_for(lambda: rig.order_state("B") == "done", "order B done", timeout=60)
        assert any(
            "saw: found not set up (not homed" in e.text and "setting it up again" in e.text
            for e in controller.events
        ), [e.text for e in controller.events]


@pytest.mark.virtual
async def test_a_saw_power_cycled_while_the_cell_runs_is_set_up_again(tmp_path: Path) -> None:
    async with saw_cell(tmp_path) as rig:
        rig.post("bar-end", 1, "A")
        await rig.start_controller()
        await rig.wait_for(lambda: rig.order_state("A") == "done", "order A done", timeout=60)
        await rig.wait_quiet()
        power_cycle_saw(rig)
        [alarm] = await rig.wait_for(lambda: rig.alarms("saw"), "the saw's alarm", timeout=30)
        assert alarm.text.startswith("found not set up (not homed")
        rig.post("bar-end", 1, "B")
        await rig.wait_for(lambda: rig.order_state("B") == "done", "order B done", timeout=60)
        assert rig.cut_twice() == {}


# -- 4, 5. a driver that does not keep its family's protocol ----------------------------------


class _NoStatus:
    """The saw's driver without status(), host_status() and end()."""

    def __init__(self, inner: Any) -> None:
        self._inner = inner
        self.name, self.link = inner.name, inner.link

    def __getattr__(self, name: str) -> Any:
        if name in ("status", "host_status", "end"):
            raise AttributeError(name)
        return getattr(self._inner, name)


async def test_a_driver_missing_a_member_of_its_family_is_refused_naming_it(
    tmp_path: Path,
) -> None:
    kind = saw_variant("kerf100-nostatus", _NoStatus)
    async with saw_cell(tmp_path, kind) as rig:
        with pytest.raises(KindContractError) as refused:
            await rig.start_controller()
    assert str(refused.value) == (
        "saw (kind kerf100-nostatus from tests): its driver has no host_status(), status(), end()"
    )


def _dict_status(driver: Any) -> Any:
    status = driver.status

    async def as_dict() -> Any:
        return {"state": int((await status()).state)}

    driver.status = as_dict
    return driver


def _purple(driver: Any) -> Any:
    status, host_status = driver.status, driver.host_status

    @dataclasses.dataclass(frozen=True)
    class Purple:
        reading: Any
        kind_condition: str = "purple"

        def __getattr__(self, name: str) -> Any:
            return getattr(self.reading, name)

    async def purple_status() -> Any:
        return Purple(await status())

    driver.status = purple_status
    driver.host_status = lambda: Purple(host_status())
    return driver


async def test_a_reading_of_the_wrong_type_is_that_machine_s_error_alone(tmp_path: Path) -> None:
    kind = saw_variant("kerf100-dict", _dict_status)
    async with saw_cell(tmp_path, kind) as rig:
        rig.post("bar-end", 1, "A")
        controller = await rig.start_controller()
        [alarm] = await rig.wait_for(lambda: rig.alarms("saw"), "the saw's alarm")
        words = "saw (kind kerf100-dict from tests): its status() gave a dict, not a reading"
        assert words in alarm.text
        assert words in controller.machines["saw"].state
        # The rest of the cell goes on: the part is cut on cnc1 and waits for the saw.
        await rig.wait_for(lambda: rig.finished_steps("machine") >= 1, "cnc1's cut", timeout=60)
        rig.check_running()


async def test_a_condition_that_is_not_one_shows_that_machine_as_an_error(
    tmp_path: Path,
) -> None:
    kind = saw_variant("kerf100-purple", _purple)
    async with saw_cell(tmp_path, kind) as rig:
        controller = await rig.start_controller()
        await rig.wait_for(lambda: rig.alarms("saw"), "the saw's alarm")
        saw = controller.machines["saw"]
        assert saw.machine_condition in (Condition.OFFLINE, Condition.ALARM)
        assert "kind_condition is 'purple', not a condition" in saw.state
        assert saw.error is not None and "kerf100-purple" in saw.error.text
        # Every surface's status (the API's, the console's) still has the whole cell.
        status = build_status(
            cell=CellInfo(
                name="t", directory="t", access="attached", mode="running", paused=False,
                started_at=0.0, pid=0, time=0.0,
            ),
            views=controller.machines, families={}, out_of_service={}, manual=(),
            journal=None, orders=[], events=(),
        )  # fmt: skip
        assert status.machines["saw"].condition in (Condition.OFFLINE, Condition.ALARM)
        assert status.machines["cnc1"].condition is not Condition.OFFLINE


# -- 7. an emulator that fails ------------------------------------------------------------------


def _exploding(spec: Any) -> Any:
    raise RuntimeError("emulator exploded at start")


async def test_an_emulator_that_fails_at_start_is_refused_naming_its_kind(tmp_path: Path) -> None:
    kind = dataclasses.replace(registry.kind("kerf100"), name="kerf100-boom", emulator=_exploding)
    with pytest.raises(UsageError) as refused:
        async with saw_cell(tmp_path, kind):
            pass
    assert str(refused.value) == (
        "kind kerf100-boom (from tests): its emulator failed to start: "
        "RuntimeError: emulator exploded at start"
    )


class _Crashing(EmulatedDevice):
    async def session(self, line: DeviceLine) -> None:
        raise ZeroDivisionError("session blew up")


async def test_an_emulator_s_session_crash_is_logged_with_its_machine(
    caplog: pytest.LogCaptureFixture,
) -> None:
    settings = LineSettings.parse("9600,8N1")
    server = await serve_mem(_Crashing(), settings, name="marker-t7", pacing=False)
    try:
        link = await open_link(server.url, settings)
        with pytest.raises(LinkClosed):  # the session ended: its line closed
            await link.read(1, timeout=10)
        await link.close()
    finally:
        await server.close()
    [record] = [r for r in caplog.records if "failed in its session" in r.message]
    assert record.message == (
        "emulator marker-t7 (tests.test_kind_contract._Crashing) failed in its session: "
        "ZeroDivisionError: session blew up"
    )
