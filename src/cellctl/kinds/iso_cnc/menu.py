"""An ISO-code control's manual functions (console, CLI, control API).

A control on RS-232 answers no status request: ``mill.status`` reports the host's view (idle,
reading, punching or drip-feeding with its progress and stall time, or the alarm the control
sent), no byte sent. Programs go to the control through the cell, or by hand through
``cellctl dnc``.
"""

from __future__ import annotations

from typing import Any

from cellctl.kinds.iso_cnc.driver import IsoCncDriver
from cellctl.kinds.menu import MachineFunction, NoParams, Prepared, Progress, ok


async def _status(d: IsoCncDriver, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    st = await d.status()
    return ok(
        st.shown,
        name=d.name,
        state=int(st.state),
        state_text=st.state.text,
        chars_sent=st.chars_sent,
        chars_total=st.chars_total,
        stall_s=st.stall_s,
        alarm=st.alarm,
        alarm_text=st.alarm_text,
    )


MENU: tuple[MachineFunction, ...] = (
    MachineFunction("mill", "status", "STATUS", None,
                    "The host's view: idle, reading, punching or drip-feeding (progress, "
                    "stall), or the control's alarm. No byte is sent.",
                    NoParams, _status, observes=True),
)  # fmt: skip
