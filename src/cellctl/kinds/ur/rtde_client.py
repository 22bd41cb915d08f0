"""The UR driver's RTDE side: the fields it subscribes to, the status record they decode to
(with its :class:`~cellctl.kinds.condition.Condition`), and the client that reads the stream.

:class:`RtdeClient` is mixed into :class:`~cellctl.kinds.ur.driver.UrRobot`: the driver opens
the RTDE link and sets the attributes the mixin declares, runs ``_rtde_handshake`` and then
``_read_rtde`` (a task) on the link, and reads the latest state as ``_status_of(_fresh())``
or waits for one with ``_wait_state``. The codecs are :mod:`cellctl.kinds.ur.rtde`.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from cellctl.clock import Clock
from cellctl.errors import (
    CellctlError,
    LinkClosed,
    LinkTimeout,
    ProtocolError,
    SignalTimeout,
    UnexpectedReply,
)
from cellctl.kinds.condition import Condition
from cellctl.kinds.ur import rtde
from cellctl.kinds.ur.dashboard import (
    MOVING_SAFETY,
    RobotMode,
    RuntimeState,
    SafetyStatus,
    condition_of,
)
from cellctl.kinds.ur.options import UrOptions
from cellctl.link import Link

#: The RTDE fields the driver relies on (the independent client's test reads these).
FIELDS = (
    "timestamp",
    "actual_q",
    "robot_mode",
    "safety_mode",
    "safety_status_bits",
    "runtime_state",
    "actual_digital_input_bits",
    "actual_digital_output_bits",
)


@dataclass(frozen=True)
class UrStatus:
    """The robot's state as RTDE shows it; ``str()`` says it in UR's words."""

    mode: RobotMode
    safety: SafetyStatus
    runtime: RuntimeState
    inputs: int = 0
    outputs: int = 0
    q: tuple[float, ...] = ()
    loaded: str | None = None
    remote: bool | None = None

    @property
    def ok(self) -> bool:
        """Powered, brakes released, no safety stop: the arm may move."""
        return self.safety in MOVING_SAFETY and self.mode == RobotMode.RUNNING

    @property
    def condition(self) -> Condition:
        return condition_of(self.mode, self.safety, self.runtime)

    def input(self, n: int) -> bool:
        return bool(self.inputs >> n & 1)

    def output(self, n: int) -> bool:
        return bool(self.outputs >> n & 1)

    def __str__(self) -> str:
        if self.safety not in MOVING_SAFETY:
            return f"Safetystatus: {self.safety.text}"
        if self.mode != RobotMode.RUNNING:
            return f"Robotmode: {self.mode.text}"
        return f"Robotmode: RUNNING, programState {self.runtime.text}"

    def lines(self) -> list[str]:
        out = [
            f"Robotmode: {self.mode.text}",
            f"Safetystatus: {self.safety.text}",
            f"programState: {self.runtime.text} {self.loaded or ''}".rstrip(),
            "DI " + "".join("1" if self.input(n) else "." for n in range(8))
            + "  DO " + "".join("1" if self.output(n) else "." for n in range(8)),
        ]  # fmt: skip
        if self.remote is not None:
            out.append(f"is in remote control: {'true' if self.remote else 'false'}")
        return out


@dataclass
class _State:
    values: dict[str, Any] = field(default_factory=dict)
    at: float = -math.inf
    count: int = 0


def _member(cls: Any, value: int, default: Any) -> Any:
    try:
        return cls(value)
    except ValueError:
        return default


class RtdeClient:
    """The RTDE client of a UR driver: handshake, the reading task, the latest state and
    waits on it. The driver sets the attributes below (``_recipe`` in the handshake)."""

    name: str
    options: UrOptions
    version: rtde.ControllerVersion | None
    rtde_error: CellctlError | None
    _state: _State
    _changed: asyncio.Event
    _recipe: rtde.Recipe

    if TYPE_CHECKING:

        @property
        def clock(self) -> Clock: ...

    async def _packet(self, link: Link, timeout: float) -> tuple[int, bytes]:
        header = await link.read_exactly(rtde.HEADER.size, timeout=timeout)
        size, _ = rtde.HEADER.unpack(header)
        if size < rtde.HEADER.size:
            raise ProtocolError(f"{self.name}: RTDE packet size {size}", header)
        body = await link.read_exactly(size - rtde.HEADER.size, timeout=timeout)
        packet_type, payload, _ = rtde.decode(header + body)
        return packet_type, payload

    async def _request(self, link: Link, packet_type: int, payload: bytes) -> bytes:
        await link.write(rtde.encode(packet_type, payload))
        while True:
            got, reply = await self._packet(link, self.options.reply_timeout)
            if got == packet_type:
                return reply
            if got != rtde.PacketType.TEXT_MESSAGE:
                raise UnexpectedReply(f"{self.name}: RTDE answered type {got} to {packet_type}",
                                      reply[:32])  # fmt: skip

    async def _rtde_handshake(self, link: Link) -> None:
        t = rtde.PacketType
        reply = await self._request(
            link, t.REQUEST_PROTOCOL_VERSION, rtde.request_protocol_version(2)
        )
        if not rtde.parse_protocol_version_reply(reply):
            raise ProtocolError(f"{self.name}: the controller refused RTDE protocol version 2")
        self.version = rtde.parse_controller_version_reply(
            await self._request(link, t.GET_URCONTROL_VERSION, b"")
        )
        fields = list(FIELDS)
        if self.options.end_register is not None:
            fields.append(f"output_int_register_{self.options.end_register}")
        frequency = min(self.options.rtde_frequency, self.version.max_frequency)
        reply = await self._request(
            link, t.SETUP_OUTPUTS, rtde.setup_outputs_payload(frequency, fields)
        )
        self._recipe = rtde.parse_setup_reply(reply, fields)
        if not self._recipe.ok:
            raise ProtocolError(
                f"{self.name}: RTDE refused fields: {', '.join(self._recipe.refused())}"
            )
        if not rtde.parse_start_reply(await self._request(link, t.START, b"")):
            raise ProtocolError(f"{self.name}: RTDE did not start")

    async def _read_rtde(self, link: Link) -> None:
        try:
            while True:
                packet_type, payload = await self._packet(link, self.options.state_timeout * 5)
                if packet_type == rtde.PacketType.DATA_PACKAGE:
                    state = self._state
                    state.values = rtde.unpack_data(self._recipe, payload)
                    state.at = self.clock.monotonic()
                    state.count += 1
                    self._changed.set()
        except CellctlError as e:
            self.rtde_error = e
            self._changed.set()

    def _fresh(self) -> dict[str, Any]:
        """The latest RTDE values; LinkTimeout/LinkClosed when the stream stopped."""
        if self.rtde_error is not None:
            raise LinkClosed(f"{self.name}: RTDE stream ended: {self.rtde_error}")
        age = self.clock.monotonic() - self._state.at
        if age > self.options.state_timeout:
            raise LinkTimeout(
                f"{self.name}: no RTDE package for {age:.1f} s "
                f"(state_timeout {self.options.state_timeout:g} s)"
            )
        return self._state.values

    def _status_of(self, values: dict[str, Any]) -> UrStatus:
        return UrStatus(
            mode=_member(RobotMode, values["robot_mode"], RobotMode.NO_CONTROLLER),
            safety=_member(SafetyStatus, values["safety_mode"], SafetyStatus.FAULT),
            runtime=_member(RuntimeState, values["runtime_state"], RuntimeState.STOPPED),
            inputs=values["actual_digital_input_bits"],
            outputs=values["actual_digital_output_bits"],
            q=values["actual_q"],
        )

    async def _wait_state(self, ok: Any, timeout: float, what: str) -> UrStatus:
        """Wait (deadline ``timeout``) for an RTDE package whose status satisfies ``ok``."""
        deadline = self.clock.monotonic() + timeout
        while True:
            if self._state.count:
                status = self._status_of(self._fresh())
                if ok(status):
                    return status
            elif self.rtde_error is not None:
                self._fresh()
            left = deadline - self.clock.monotonic()
            if left <= 0:
                now = self._status_of(self._fresh()) if self._state.count else None
                raise SignalTimeout(
                    f"{self.name}: no {what} within {timeout:g} s"
                    + (f" ({now})" if now is not None else "")
                )
            self._changed.clear()
            with contextlib.suppress(TimeoutError):
                async with self.clock.timeout(min(left, self.options.state_timeout)):
                    await self._changed.wait()


__all__ = ["FIELDS", "RtdeClient", "UrStatus"]
