"""The Dashboard Server (the controller's port 29999) and the state numbers: no I/O.

One line each way, ``\\n``-terminated. On connect the server says its banner
(:data:`BANNER`); each command gets one answer line, in UR's words, listed once in
:data:`COMMANDS`. The state numbers (robot mode, safety status, runtime state) are those
RTDE carries; the Dashboard Server names them (``Robotmode: RUNNING``)::

    spec = COMMANDS["power on"]
    spec.ok("Powering on")                      # True
    robot_mode_of("Robotmode: RUNNING")        # RobotMode.RUNNING
    safety_status_of("Safetystatus: PROTECTIVE_STOP")

The answers are those of UR's public Dashboard Server article (CB3 3.x and PolyScope 5).
Where the article gives no wording, the table says **assumed**.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import TypeVar

from cellctl.errors import UnexpectedReply
from cellctl.kinds.condition import Condition

#: The line the server writes when a client connects.
BANNER = "Connected: Universal Robots Dashboard Server"
#: The longest answer line taken (a program path, a popup's text).
MAX_ANSWER = 4096


class _Named(enum.IntEnum):
    """A state number whose UR name is its member's name (``.text``)."""

    @property
    def text(self) -> str:
        return self.name


class RobotMode(_Named):
    """``robot_mode`` (RTDE) and ``Robotmode: NAME`` (Dashboard Server)."""

    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5
    BACKDRIVE = 6
    RUNNING = 7
    UPDATING_FIRMWARE = 8


class SafetyStatus(_Named):
    """``safety_status`` (RTDE) and ``Safetystatus: NAME`` (Dashboard Server)."""

    NORMAL = 1
    REDUCED = 2
    PROTECTIVE_STOP = 3
    RECOVERY = 4
    SAFEGUARD_STOP = 5
    SYSTEM_EMERGENCY_STOP = 6
    ROBOT_EMERGENCY_STOP = 7
    VIOLATION = 8
    FAULT = 9
    VALIDATE_JOINT_ID = 10
    UNDEFINED_SAFETY_MODE = 11
    AUTOMATIC_MODE_SAFEGUARD_STOP = 12
    SYSTEM_THREE_POSITION_ENABLING_STOP = 13


class RuntimeState(_Named):
    """``runtime_state`` (RTDE); ``programState`` says the first word of the three it shows."""

    STOPPING = 0
    STOPPED = 1
    PLAYING = 2
    PAUSING = 3
    PAUSED = 4
    RESUMING = 5


#: Safety statuses in which the arm may move.
MOVING_SAFETY = frozenset({SafetyStatus.NORMAL, SafetyStatus.REDUCED})
#: Emergency stops: released at the button, then ``close safety popup`` and ``brake release``.
EMERGENCY = frozenset({SafetyStatus.SYSTEM_EMERGENCY_STOP, SafetyStatus.ROBOT_EMERGENCY_STOP})

#: ``safety_status_bits`` (RTDE): bit -> what it says.
SAFETY_BITS = {
    0: "normal mode",
    1: "reduced mode",
    2: "protective stopped",
    3: "recovery mode",
    4: "safeguard stopped",
    5: "system emergency stopped",
    6: "robot emergency stopped",
    7: "emergency stopped",
    8: "violation",
    9: "fault",
    10: "stopped due to safety",
}
#: The bits of each safety status.
STATUS_BITS: dict[SafetyStatus, int] = {
    SafetyStatus.NORMAL: 1 << 0,
    SafetyStatus.REDUCED: 1 << 1,
    SafetyStatus.PROTECTIVE_STOP: 1 << 2 | 1 << 10,
    SafetyStatus.RECOVERY: 1 << 3,
    SafetyStatus.SAFEGUARD_STOP: 1 << 4 | 1 << 10,
    SafetyStatus.SYSTEM_EMERGENCY_STOP: 1 << 5 | 1 << 7 | 1 << 10,
    SafetyStatus.ROBOT_EMERGENCY_STOP: 1 << 6 | 1 << 7 | 1 << 10,
    SafetyStatus.VIOLATION: 1 << 8 | 1 << 10,
    SafetyStatus.FAULT: 1 << 9 | 1 << 10,
}
#: ``robot_status_bits`` (RTDE).
POWER_ON_BIT, PROGRAM_RUNNING_BIT, TEACH_BUTTON_BIT, POWER_BUTTON_BIT = 1, 2, 4, 8


@dataclass(frozen=True)
class Command:
    """One Dashboard Server command: its answers on success and on failure, UR's words.

    ``{arg}`` stands for the command's argument, ``{0}`` for a value the server fills in.
    ``acts``: it changes the robot (refused in local mode on an e-Series).
    """

    text: str
    success: tuple[str, ...]
    failure: tuple[str, ...] = ()
    acts: bool = False
    since: str = ""

    def ok(self, answer: str, arg: str = "") -> bool:
        """True if ``answer`` is one of its success answers."""
        return any(_matches(pattern, answer, arg) for pattern in self.success)


def _matches(pattern: str, answer: str, arg: str) -> bool:
    pattern = pattern.replace("{arg}", arg)
    if "{0}" not in pattern:
        return answer == pattern
    head, _, tail = pattern.partition("{0}")
    return answer.startswith(head) and answer.endswith(tail) and len(answer) >= len(head + tail)


#: Every command the emulator answers and the driver sends: UR's answers, one table.
COMMANDS: dict[str, Command] = {
    c.text: c
    for c in (
        Command(
            "load",
            ("Loading program: {arg}",),
            ("File not found: {arg}", "Error while loading program: {arg}"),
            acts=True,
        ),
        Command("play", ("Starting program",), ("Failed to execute: play",), acts=True),
        Command("stop", ("Stopped",), ("Failed to execute: stop",), acts=True),
        Command("pause", ("Pausing program",), ("Failed to execute: pause",), acts=True),
        Command("quit", ("Disconnected",)),
        Command("shutdown", ("Shutting down",), acts=True),
        Command("running", ("Program running: true", "Program running: false")),
        Command("robotmode", ("Robotmode: {0}",)),
        Command("get loaded program", ("Loaded program: {0}", "No program loaded")),
        Command("popup", ("showing popup",), acts=True),
        Command("close popup", ("closing popup",)),
        Command("addToLog", ("Added log message",), ("No log message to add",)),
        Command("isProgramSaved", ("true {0}", "false {0}")),
        Command("programState", ("{0}",)),
        Command("PolyscopeVersion", ("URSoftware {0}",)),
        Command("power on", ("Powering on",), acts=True, since="3.0"),
        Command("power off", ("Powering off",), acts=True, since="3.0"),
        Command("brake release", ("Brake releasing",), acts=True, since="3.0"),
        Command("safetymode", ("Safetymode: {0}",)),
        Command("safetystatus", ("Safetystatus: {0}",), since="3.11 / 5.4"),
        Command(
            "unlock protective stop",
            ("Protective stop releasing",),
            (
                "Cannot unlock protective stop until 5s after occurrence. "
                "Always inspect cause of protective stop before unlocking",
            ),
            acts=True,
            since="3.1",
        ),
        Command("close safety popup", ("closing safety popup",), acts=True, since="3.1"),
        Command("restart safety", ("Restarting safety",), acts=True, since="3.7 / 5.1"),
        Command("is in remote control", ("true", "false"), since="5.6"),
        Command("get robot model", ("UR{0}",), since="3.12 / 5.6"),
        Command("get serial number", ("{0}",), since="3.12 / 5.6"),
    )
}
#: A command the server does not know (its words, with the line as it came).
NOT_UNDERSTOOD = "could not understand: '{line}'"
#: An acting command while an e-Series pendant is in local mode (**assumed** wording: the
#: driver never relies on it; it asks ``is in remote control`` first).
LOCAL_MODE_REFUSAL = "Command is not allowed due to safety reasons. Robot is in local control"


def split_command(line: str) -> tuple[Command | None, str]:
    """The command a line names and its argument (``load /programs/a.urp``)."""
    line = line.strip()
    for text in sorted(COMMANDS, key=len, reverse=True):
        if line == text or line.startswith(text + " "):
            return COMMANDS[text], line[len(text) :].strip()
    return None, ""


def robot_mode_of(answer: str) -> RobotMode:
    """``Robotmode: RUNNING`` -> RobotMode.RUNNING; UnexpectedReply otherwise."""
    return _named(RobotMode, answer, "Robotmode: ")


def safety_status_of(answer: str) -> SafetyStatus:
    """``Safetystatus: NORMAL`` -> SafetyStatus.NORMAL; UnexpectedReply otherwise."""
    return _named(SafetyStatus, answer, "Safetystatus: ")


def program_state_of(answer: str) -> tuple[RuntimeState, str]:
    """``PLAYING tend.urp`` -> (PLAYING, "tend.urp")."""
    word, _, name = answer.partition(" ")
    state = _named(RuntimeState, word, "")
    return state, name


_State = TypeVar("_State", bound=_Named)


def _named(cls: type[_State], answer: str, prefix: str) -> _State:
    if not answer.startswith(prefix):
        raise UnexpectedReply(f"expected {prefix!r}..., the Dashboard Server said {answer!r}")
    word = answer[len(prefix) :].strip()
    for member in cls:
        if member.text == word:
            return member
    raise UnexpectedReply(f"unknown {cls.__name__} in the answer {answer!r}")


def condition_of(mode: int, safety: int, runtime: int) -> Condition:
    """The family's condition of a UR: alarm when stopped by safety, not ready unless RUNNING
    (powered, brakes released), busy while a program plays."""
    if safety not in MOVING_SAFETY:
        return Condition.ALARM
    if mode != RobotMode.RUNNING:
        return Condition.NOT_READY
    if runtime in (RuntimeState.PLAYING, RuntimeState.RESUMING, RuntimeState.PAUSING):
        return Condition.BUSY
    return Condition.IDLE
