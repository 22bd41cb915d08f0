"""The Dyna 2400's manual functions: the source's CNC menu, then the tool-kit's extras."""

from __future__ import annotations

from typing import Any

from cellctl.errors import UsageError
from cellctl.kinds.dyna2400.driver import Dyna2400Mill
from cellctl.kinds.dyna2400.dynalan import Program, parse_program
from cellctl.kinds.families import RunProgress as MillProgress
from cellctl.kinds.menu import (
    MachineFunction,
    NoParams,
    Prepared,
    ProgramParams,
    Progress,
    UploadParams,
    ok,
)


class MillInitParams(ProgramParams):
    force: bool = False


class MillDownloadParams(ProgramParams):
    wait: bool = True


def _parse_dynalan(params: Any) -> Program:
    return parse_program(params.text, name=params.program)


async def _mill_init(m: Dyna2400Mill, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    result = await m.initialize(p.parsed, force=p.params.force)
    return ok(
        result.message,
        code=result.code,
        lines=[],
        after=["operator: jog the axes to the reference zero, then press NEXT"],
    )


async def _mill_download(m: Dyna2400Mill, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    def report(d: MillProgress) -> None:
        if progress is not None:
            progress(
                {
                    "block": d.block,
                    "blocks": d.blocks,
                    "lines": d.lines_sent,
                    "lines_total": d.lines_total,
                    "bytes_sent": d.bytes_sent,
                    "bytes_total": d.bytes_total,
                    "phase": d.phase,
                    "estimate_s": d.estimate_s,
                    "estimate_done_s": d.estimate_done_s,
                    "estimate_cap_s": d.estimate_cap_s,
                    "at": d.at,
                    "running": d.running,
                }
            )

    result = await m.download(p.parsed, wait=p.params.wait, progress=report)
    return ok(result.message, code=result.code)


async def _mill_load(m: Dyna2400Mill, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    result = await m.load(p.parsed)
    return ok(result.message, code=result.code)


async def _mill_go(m: Dyna2400Mill, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    if m.start_output is None:
        raise UsageError(f"{m.name}: no start signal: set go_output (a PLC coil) in cell.toml")
    result = await m.go()
    return ok(result.message, code=result.code)


async def _mill_end(m: Dyna2400Mill, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    result = await m.end()
    return ok(result.message, code=result.code)


async def _mill_status(m: Dyna2400Mill, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    st = await m.status()
    lines = [f"{m.name}: state {st.state} ({st.state_text})"]
    if st.condition:
        lines.append(f"  {st.condition}")
    lines.append(f"  CTS {'high (ready)' if st.ready else 'low'}")
    return ok(
        f"state {st.state} ({st.state_text})",
        name=m.name,
        state=st.state,
        state_text=st.state_text,
        condition=st.condition,
        ready=st.ready,
        initialized=m.initialized,
        lines=lines,
    )


async def _mill_upload(m: Dyna2400Mill, p: Prepared, progress: Progress | None) -> dict[str, Any]:
    text = await m.upload(timeout=p.params.timeout)
    return ok(f"{len(text.splitlines())} lines received", text=text)


MENU: tuple[MachineFunction, ...] = (
    MachineFunction("mill", "init", "INITIALIZE", 1,
                    "Send the setup program; the operator sets the reference zero.",
                    MillInitParams, _mill_init, prepare=_parse_dynalan),
    MachineFunction("mill", "download", "DOWNLOAD", 2,
                    "Validate, split into blocks, stream them as the mill asks.",
                    MillDownloadParams, _mill_download, prepare=_parse_dynalan),
    MachineFunction("mill", "go", "GO", 3, "Start the loaded program (PLC start signal).",
                    NoParams, _mill_go),
    MachineFunction("mill", "status", "STATUS", 4, "State 0-4, its condition, CTS.",
                    NoParams, _mill_status, observes=True),
    MachineFunction("mill", "end", "HALT", 5,
                    "ENDLOAD: the end program; the mill returns to manual.", NoParams, _mill_end),
    MachineFunction("mill", "load", "PROGRAM LOAD", None,
                    "Load a program (at most 900 lines) to start with GO.",
                    ProgramParams, _mill_load, prepare=_parse_dynalan),
    MachineFunction("mill", "upload", "UPLOAD", None,
                    "Receive the mill's program (start UPLOAD on its panel).",
                    UploadParams, _mill_upload),
)  # fmt: skip
