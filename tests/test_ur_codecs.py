"""The UR kind's codecs: RTDE packets, the Dashboard Server's table, URScript (no I/O)."""

from __future__ import annotations

import contextlib
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.errors import CellctlError, ProtocolError, UsageError
from cellctl.kinds.ur import rtde
from cellctl.kinds.ur.dashboard import (
    COMMANDS,
    RobotMode,
    SafetyStatus,
    program_state_of,
    robot_mode_of,
    safety_status_of,
    split_command,
)
from cellctl.kinds.ur.motion import ARMS, HOME, move_time
from cellctl.kinds.ur.program import compile_program, preview_svg
from cellctl.kinds.ur.urscript import OffRobot, ScriptError, check, estimate, parse, run

UR5E = ARMS["UR5e"]


# -- RTDE framing ---------------------------------------------------------------------------------


def test_packet_bytes_as_the_protocol_lays_them_out() -> None:
    # size (uint16, header included), type 'V', version 2 as uint16
    request = rtde.request_protocol_version(2)
    assert rtde.encode(rtde.PacketType.REQUEST_PROTOCOL_VERSION, request) == b"\x00\x05V\x00\x02"
    assert rtde.encode(rtde.PacketType.START) == b"\x00\x03S"


@given(st.integers(0, 255), st.binary(max_size=300))
def test_decode_whole_split_and_byte_by_byte(packet_type: int, payload: bytes) -> None:
    packet = rtde.encode(packet_type, payload)
    assert rtde.decode(packet + b"extra") == (packet_type, payload, len(packet))
    for cut in range(len(packet)):
        assert rtde.decode(packet[:cut])[2] == 0  # need more
    buffer = bytearray()
    got = None
    for byte in packet:
        buffer.append(byte)
        t, p, used = rtde.decode(buffer)
        if used:
            got = (t, p)
    assert got == (packet_type, payload)


@given(st.binary(max_size=64))
def test_decode_anything_a_peer_sends(data: bytes) -> None:
    try:
        _, _, used = rtde.decode(data)
    except ProtocolError as e:
        assert e.raw
    else:
        assert used == 0 or used == struct.unpack(">H", data[:2])[0]


_fields = st.lists(st.sampled_from(sorted(rtde.OUTPUTS)), min_size=1, max_size=12, unique=True)


def _value(kind: str) -> st.SearchStrategy[object]:
    floats = st.floats(allow_nan=False, allow_infinity=False, width=64)
    return {
        "DOUBLE": floats,
        "INT32": st.integers(-(2**31), 2**31 - 1),
        "UINT32": st.integers(0, 2**32 - 1),
        "UINT64": st.integers(0, 2**64 - 1),
        "VECTOR6D": st.tuples(*[floats] * 6),
        "VECTOR6INT32": st.tuples(*[st.integers(-(2**31), 2**31 - 1)] * 6),
    }[kind]


@given(st.data(), _fields, st.integers(1, 255), st.sampled_from([1, 2]))
def test_data_package_round_trip(
    data: st.DataObject, names: list[str], recipe_id: int, version: int
) -> None:
    recipe = rtde.recipe_for(recipe_id, names, rtde.OUTPUTS)
    assert recipe.ok
    values = {n: data.draw(_value(rtde.OUTPUTS[n])) for n in names}
    payload = rtde.pack_data(recipe, values, version)
    assert rtde.unpack_data(recipe, payload, version) == values
    with pytest.raises(ProtocolError):
        rtde.unpack_data(recipe, payload[:-1], version)


@given(_fields, st.sampled_from([1, 2]), st.one_of(st.none(), st.floats(1, 500)))
def test_setup_round_trip_and_refusals(
    names: list[str], version: int, frequency: float | None
) -> None:
    frequency = None if version == 1 else (frequency or 125.0)  # version 2 always sends one
    payload = rtde.setup_outputs_payload(frequency, [*names, "no_such_field"])
    got_frequency, got_names = rtde.parse_setup_outputs(payload, version)
    assert got_frequency == frequency and got_names == [*names, "no_such_field"]
    recipe = rtde.recipe_for(3, got_names, rtde.OUTPUTS)
    reply = rtde.parse_setup_reply(rtde.setup_reply(recipe, version), got_names, version)
    assert not reply.ok and reply.refused() == ["no_such_field (NOT_FOUND)"]


def test_version_and_text_messages() -> None:
    version = rtde.ControllerVersion(5, 15, 0, 1)
    assert rtde.parse_controller_version_reply(rtde.controller_version_reply(version)) == version
    assert version.max_frequency == 500 and rtde.ControllerVersion(3, 15, 0, 0).max_frequency == 125
    assert rtde.parse_text_message(rtde.text_message("frequency too high")) == (
        "frequency too high",
        "RTDE",
        rtde.ERROR,
    )


@given(st.binary(max_size=40))
def test_parsers_take_anything(payload: bytes) -> None:
    for parse_one in (
        rtde.parse_controller_version_reply,
        rtde.parse_start_reply,
        rtde.parse_text_message,
        lambda p: rtde.parse_setup_reply(p, ["actual_q"]),
    ):
        with contextlib.suppress(ProtocolError):
            parse_one(payload)


# -- the Dashboard Server's table -----------------------------------------------------------------


def test_answers_in_urs_words() -> None:
    assert COMMANDS["power on"].ok("Powering on")
    assert COMMANDS["brake release"].ok("Brake releasing")
    assert COMMANDS["load"].ok("Loading program: /programs/a.urp", "/programs/a.urp")
    assert not COMMANDS["load"].ok("File not found: /programs/a.urp", "/programs/a.urp")
    assert COMMANDS["unlock protective stop"].ok("Protective stop releasing")
    assert robot_mode_of("Robotmode: RUNNING") is RobotMode.RUNNING
    assert safety_status_of("Safetystatus: PROTECTIVE_STOP") is SafetyStatus.PROTECTIVE_STOP
    assert program_state_of("PAUSED tend.urp")[1] == "tend.urp"
    assert split_command("unlock protective stop") == (COMMANDS["unlock protective stop"], "")
    assert split_command("load /programs/a b.urp")[1] == "/programs/a b.urp"


@given(st.text(max_size=80))
def test_any_line_is_a_command_or_none(line: str) -> None:
    command, _ = split_command(line)
    assert command is None or line.strip().startswith(command.text)
    for parse_one in (robot_mode_of, safety_status_of, program_state_of):
        with contextlib.suppress(CellctlError):
            parse_one(line)


# -- URScript -------------------------------------------------------------------------------------

TEND = """\
def tend():
  movej([0, -1.57, 1.0, -1.57, 0, 0], a=1.4, v=1.05)
  set_standard_digital_out(0, True)
  i = 0
  while i < 3:
    sleep(0.5)
    i = i + 1
  end
  if get_standard_digital_in(1):
    movel(p[0.4, 0.2, 0.3, 0, 3.14, 0], v=0.25)
  else:
    halt()
  end
end
"""


def test_check_passes_a_good_program_and_times_it() -> None:
    assert check(TEND, UR5E, "tend.script") == []
    seconds, moves = estimate(parse(TEND), UR5E)
    joint_move = move_time(1.0, 1.05, 1.4)  # the elbow travels 1 rad
    assert len(moves) == 2
    assert seconds > joint_move + 1.5  # the move, three sleeps, then the line


def test_check_finds_what_fails_on_the_robot_with_line_and_column() -> None:
    bad = (
        "def x():\n"
        "  movjj([0,0,0,0,0,0])\n"
        "  movel(p[1.0, 0.5, 0.2, 0, 0, 0])\n"
        "  movej([9,0,0,0,0,0])\n"
        "  y = (\n"
    )
    assert check(bad, UR5E, "b.script") == [
        "b.script:1:1: 'def x():' has no 'end'",
        "b.script:2:3: unknown function 'movjj'",
        "b.script:3:9: pose out of reach for a UR5e: 1.136 m from the base, its reach is 0.850 m",
        "b.script:4:9: joint 0 at 9.000 rad is beyond its limit ±6.283 rad",
        "b.script:5:7: does not parse: '(' was never closed",
    ]
    # The same pose is within a UR10e's reach.
    assert not any("reach" in p for p in check(bad, ARMS["UR10e"], "b.script"))
    assert check("end\n", UR5E, "e") == ["e:1:1: 'end' without a block to close"]


def test_a_break_outside_a_loop_is_found_and_ends_a_run_in_the_robots_words() -> None:
    # A break in a function ends nothing in the loop that called it.
    text = (
        "def main():\n"
        "  def leave():\n"
        "    break\n"
        "  end\n"
        "  while True:\n"
        "    if True:\n"
        "      continue\n"
        "    end\n"
        "  end\n"
        "end\n"
    )
    assert check(text, UR5E, "p") == ["p:3:5: 'break' outside a loop"]
    assert check("continue\n", UR5E, "p") == ["p:1:1: 'continue' outside a loop"]
    called = (
        "def main():\n  def leave():\n    break\n  end\n  while True:\n    leave()\n  end\nend\n"
    )
    with pytest.raises(ScriptError, match="Runtime error: 'break' outside a loop"):
        list(run(parse(called), OffRobot(), UR5E))
    # The estimate of such a program stops where the robot would.
    assert estimate(parse("movej([0,0,0,0,0,0])\nbreak\nsleep(5)\n"), UR5E, limit_s=10)[0] < 5


def test_a_nul_character_is_a_problem_at_its_place_on_every_python() -> None:
    # Python 3.11.2's ast.parse raised ValueError on a NUL (3.11.7's a SyntaxError): a crash.
    assert check("x = 1 +\x00 2\n", UR5E, "p") == ["p:1:8: does not parse: a NUL character"]
    with pytest.raises(ScriptError, match="a NUL character"):
        list(run(parse("x = \x00\n"), OffRobot(), UR5E))


@given(st.text(max_size=200))
@settings(max_examples=200)
def test_check_takes_any_text(text: str) -> None:
    problems = check(text, UR5E, "any")
    assert all(p.startswith("any:") for p in problems)
    estimate(parse(text), UR5E, limit_s=10)


def test_program_forms_and_preview() -> None:
    script = compile_program(TEND, "tend", "robot/tend.script")
    sent = script.sendable(24, 7)
    assert sent.splitlines()[-2] == "  write_output_integer_register(24, 7)"
    assert sent.splitlines()[-1] == "end"
    urp = compile_program("/programs/tend_cnc1.urp\n", "tend", "robot/tend.urp")
    assert urp.on_robot and urp.path == "/programs/tend_cnc1.urp"
    with pytest.raises(UsageError, match="unknown function 'movjj'"):
        compile_program("def a():\n  movjj()\nend\n", "a", "a.script")
    svg, moves = preview_svg(TEND, "tend", UR5E)
    assert moves == 2 and svg.startswith("<svg") and "polyline" in svg
    assert UR5E.tcp(HOME)[2] > 1.0  # upright: the flange above the base
