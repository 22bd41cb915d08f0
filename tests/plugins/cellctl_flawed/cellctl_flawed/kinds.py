"""The Kerf 100 saw with one mistake each, under a name of its own (``KIND_NAME``): the
entry point ``NAME = "cellctl_flawed.kinds:ATTRIBUTE"`` declares it."""

from __future__ import annotations

import dataclasses
from typing import Any

from cellctl_saw.emulator import FAULTS, KerfEmulator
from cellctl_saw.kind import KERF100

from cellctl.emulators.switches import check_switch
from cellctl.kinds.kind import EmulatorSpec, LazyTable, MachineKind


def _saw(name: str, emulator: type[KerfEmulator] | None = None, **changes: Any) -> MachineKind:
    """The saw as kind ``name``, its emulator of class ``emulator``, ``changes`` made."""
    if emulator is not None:
        made = emulator

        def build(spec: EmulatorSpec) -> KerfEmulator:
            return made(clock=spec.emulator_clock())

        changes["emulator"] = build
    return dataclasses.replace(KERF100, name=name, **changes)


# -- emulators that do not keep the mill family's emulator protocol --------------------------


class StartRaises(KerfEmulator):
    """Its power-on fails."""

    def start(self) -> None:
        raise RuntimeError("motor controller not found")


class NoRunHooks(KerfEmulator):
    """No ``run_hooks`` and no ``cycle_start()``: the emulated cell can neither note its
    cuts nor start them."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        del self.run_hooks

    def __getattribute__(self, name: str) -> Any:
        if name == "cycle_start":
            raise AttributeError(name)
        return super().__getattribute__(name)


class AsyncStart(KerfEmulator):
    """``start()`` as a coroutine: called as a plain function, it would never run."""

    async def start(self) -> None:  # type: ignore[override]
        return None


START_RAISES = _saw("flawed-start", StartRaises)
NO_RUN_HOOKS = _saw("flawed-hooks", NoRunHooks)
ASYNC_START = _saw("flawed-async", AsyncStart)

# -- fault tables a LazyTable cannot read -----------------------------------------------------

NO_MODULE = _saw("flawed-nomodule", faults=LazyTable("cellctl_flawed.nowhere:FAULTS"))
NO_TABLE = _saw("flawed-notable", faults=LazyTable("cellctl_saw.emulator:FAULTZ"))

# -- emulated options its own options model refuses -------------------------------------------


def _unknown_option(scale: float) -> dict[str, float]:
    return {"cut_margn": 2.0 / scale, "home_timeout": 10.0}


def _bad_value(scale: float) -> dict[str, float]:
    return {"home_timeout": -1.0}


UNKNOWN_OPTION = _saw("flawed-optname", emulated_options=_unknown_option)
BAD_OPTION = _saw("flawed-optvalue", emulated_options=_bad_value)

# -- fault switches ---------------------------------------------------------------------------

SLOW_FAULTS = {**FAULTS, "slow": "=MS: answer every command MS milliseconds late"}


class LaxSwitches(KerfEmulator):
    """``slow`` given without its ``=MS`` is taken (the switch checked by name only), and a
    bad ``=MS`` raises ValueError, not a UsageError."""

    slow_ms: float = 0.0

    def set_fault(self, name: str, arg: str | None = None) -> None:
        if name != "slow":
            super().set_fault(name, arg)
            return
        check_switch(SLOW_FAULTS, name, arg)
        self.slow_ms = float(arg) if arg is not None else self.slow_ms


LAX_SWITCHES = _saw("flawed-switch", LaxSwitches, faults=SLOW_FAULTS)
