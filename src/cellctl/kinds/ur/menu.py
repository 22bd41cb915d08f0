"""A UR's manual functions (console, CLI, control API): its Dashboard Server's actions.

``robot.unlock`` is the operator's, after inspecting the cause of a protective stop: the
cell never calls it by itself.
"""

from __future__ import annotations

from typing import Any

from cellctl.kinds.menu import MachineFunction, NoParams, Prepared, Progress, ok
from cellctl.kinds.ur.driver import UrRobot


async def _status(r: UrRobot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    st = await r.status()
    return ok(
        str(st),
        name=r.name,
        robot_mode=st.mode.text,
        safety_status=st.safety.text,
        program_state=st.runtime.text,
        loaded_program=st.loaded,
        remote_control=st.remote,
        inputs=[st.input(n) for n in range(8)],
        outputs=[st.output(n) for n in range(8)],
        lines=st.lines(),
    )


async def _init(r: UrRobot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.initialize()
    return ok("Robotmode: RUNNING", lines=["Powering on", "Brake releasing"])


async def _unlock(r: UrRobot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.unlock_protective_stop()
    return ok("Protective stop releasing")


async def _popup(r: UrRobot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.close_safety_popup()
    return ok("closing safety popup")


async def _play(r: UrRobot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.resume()
    return ok("Starting program")


async def _pause(r: UrRobot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.pause()
    return ok("Pausing program")


async def _stop(r: UrRobot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.stop()
    return ok("Stopped")


async def _power_off(r: UrRobot, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    await r.power_off()
    return ok("Powering off")


MENU: tuple[MachineFunction, ...] = (
    MachineFunction("robot", "status", "STATUS", None,
                    "Robot mode, safety status, program state, I/O, remote control.",
                    NoParams, _status, observes=True),
    MachineFunction("robot", "init", "POWER ON", None,
                    "Power on and release the brakes (robot mode RUNNING).", NoParams, _init),
    MachineFunction("robot", "unlock", "UNLOCK PROTECTIVE STOP", None,
                    "Unlock a protective stop, after inspecting its cause (5 s after it).",
                    NoParams, _unlock),
    MachineFunction("robot", "close_safety_popup", "CLOSE SAFETY POPUP", None,
                    "Close the pendant's safety popup.", NoParams, _popup),
    MachineFunction("robot", "play", "PLAY", None, "Play (resume) the loaded program.",
                    NoParams, _play),
    MachineFunction("robot", "pause", "PAUSE", None, "Pause the running program.",
                    NoParams, _pause),
    MachineFunction("robot", "stop", "STOP", None, "Stop whatever runs.", NoParams, _stop),
    MachineFunction("robot", "power_off", "POWER OFF", None, "Power the arm off.",
                    NoParams, _power_off),
)  # fmt: skip
