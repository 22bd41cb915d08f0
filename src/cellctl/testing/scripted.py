"""Test helpers for drivers: replay the exact bytes of the manual.

``expected_exchange`` opens a scripted link: each ``(sent, reply)`` pair says what the
driver must send next and what the machine answers. The test fails if the driver sends
anything else, if a pair is left unused, or if reply bytes are left unread::

    async with expected_exchange([(b"R", b"\\x13\\x11"), (b"01\\r\\n", b"D02044044\\r\\n"),
                                  (b"\\x06", b"EG\\r\\n"), (b"\\x06", b"")]) as link:
        status = await RobotDriver(link).status()        # the robot kind's driver
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager

from cellctl.errors import format_raw
from cellctl.link import ROBOT_LINE, LineSettings, Link


class ScriptedLink(Link):
    """A link that checks what is written against a script and answers from it."""

    def __init__(self, script: Sequence[tuple[bytes, bytes]], settings: LineSettings) -> None:
        super().__init__("scripted://", settings, None, "scripted")
        self.script = list(script)
        self.step = 0
        self._got = bytearray()

    async def _send(self, data: bytes) -> None:
        self._got += data
        while self.step < len(self.script):
            want, reply = self.script[self.step]
            if len(self._got) < len(want):
                if not want.startswith(bytes(self._got)):
                    self._mismatch(want)
                return
            if not self._got.startswith(want):
                self._mismatch(want)
            del self._got[: len(want)]
            self.step += 1
            self._loop.call_soon(self._feed, reply)
        if self._got:
            raise AssertionError(f"driver sent extra bytes after the script: {self._got!r}")

    def _mismatch(self, want: bytes) -> None:
        raise AssertionError(
            f"step {self.step}: driver sent {bytes(self._got)!r} "
            f"({format_raw(bytes(self._got))}), the script expects {want!r}"
        )

    async def _shutdown(self) -> None:
        return None

    def check_done(self) -> None:
        """Fail unless every pair was used and every reply byte read."""
        if self.step != len(self.script):
            raise AssertionError(
                f"script not finished: {len(self.script) - self.step} pair(s) unused, "
                f"next expected {self.script[self.step][0]!r}"
            )
        if self._got:
            raise AssertionError(f"driver sent unexpected bytes: {bytes(self._got)!r}")
        if self.pending():
            raise AssertionError(f"reply bytes left unread: {self.pending()!r}")


@asynccontextmanager
async def expected_exchange(
    script: Sequence[tuple[bytes, bytes]], settings: LineSettings = ROBOT_LINE
) -> AsyncIterator[ScriptedLink]:
    """A scripted link that must be used exactly as ``script`` says (see module docstring)."""
    link = ScriptedLink(script, settings)
    yield link
    link.check_done()
