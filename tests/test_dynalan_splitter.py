"""Block splitter and toolpath: properties (split then join gives the program back, no block over
900 lines) and the refusals."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.kinds.dyna2400.dynalan import (
    Kind,
    MachineState,
    MoveKind,
    SplitError,
    Units,
    build_toolpath,
    join_blocks,
    parse_program,
    split_program,
    validate,
)
from cellctl.kinds.dyna2400.dynalan.table import BLOCK_MAX_LINES

PROGRAMS = Path(__file__).resolve().parent.parent / "examples" / "programs"

_simple = st.sampled_from(
    [
        "GR X .001",
        "GR Y .001",
        "GO Z -.010",
        "FR XY = 12.0",
        "SPINDLE ON",
        "; PASS",
        "DWELL 0",
        "COOLANT OFF",
    ]
)
_move_group = st.tuples(st.sampled_from(["GR X .001", "GO X 1.000"]), st.sampled_from(["  Y .5"]))
_repeat = st.integers(1, 30).map(lambda n: ["REPEAT 02"] + ["GR X .001"] * n + ["REPEAT END"])


@st.composite
def statement_lists(draw: st.DrawFn) -> list[str]:
    """Statement texts (no numbers): plain lines, move+continuation groups, short REPEATs."""
    pieces = draw(
        st.lists(
            st.one_of(
                _simple.map(lambda s: [s]),
                _move_group.map(list),
                _repeat,
            ),
            min_size=1,
            max_size=400,
        )
    )
    count = draw(st.integers(0, 3))
    filler = ["GR Y .0001"] * (count * 700)
    return [text for piece in pieces for text in piece] + filler


def _wrap_numbered(texts: list[str]) -> str:
    out = []
    for i, text in enumerate(texts):
        sep = "" if text.startswith("  ") else " "
        out.append(f"{i % 1000:03d}{sep}{text}")
    return "\n".join(out) + "\n"


def _texts(program_text: str) -> list[str]:
    """The statements as written, without numbers and without block closers."""
    program = parse_program(program_text)
    out = []
    lines = program.lines
    for i, line in enumerate(lines):
        closer = line.kind is Kind.SKIP and i + 1 < len(lines) and lines[i + 1].number == 900
        if closer or (line.number == 900 and line.kind is Kind.BLANK):
            continue
        out.append(line.raw[3:])
    return out


@settings(max_examples=40, deadline=None)
@given(statement_lists())
def test_split_then_join_gives_back_the_program(texts: list[str]) -> None:
    original = _wrap_numbered(texts)
    blocks = split_program(parse_program(original))
    joined = join_blocks(blocks)
    assert _texts(joined) == _texts(original)
    for block in blocks:
        assert len(block.lines) <= BLOCK_MAX_LINES
        numbers = [line.number for line in block.lines]
        assert numbers[:-1] == list(range(len(numbers) - 1))
        assert numbers[-1] == 900
        assert block.lines[-2].render().endswith("SKIP TO 900")
    # Splitting what was sent gives the same blocks again.
    again = split_program(parse_program(joined))
    assert [b.text() for b in again] == [b.text() for b in blocks]


@settings(max_examples=25, deadline=None)
@given(statement_lists())
def test_no_cut_separates_a_continuation_or_a_repeat(texts: list[str]) -> None:
    blocks = split_program(parse_program(_wrap_numbered(texts)))
    for block in blocks:
        kinds = [line.statement.kind for line in block.lines if line.statement]
        assert kinds[0] is not Kind.AXIS
        depth = 0
        for kind in kinds:
            depth += (kind is Kind.REPEAT) - (kind is Kind.REPEAT_END)
            assert depth >= 0
        assert depth == 0


def test_long_sample_becomes_three_blocks_of_at_most_900_lines() -> None:
    text = (PROGRAMS / "toy_mill_table_finish_cnc2.dyn").read_text()
    result = validate(parse_program(text))
    assert result.ok and result.blocks is not None
    assert len(result.blocks) == 3
    assert [len(b.lines) for b in result.blocks][:2] == [900, 900]
    assert sum(b.statement_count for b in result.blocks) == len(text.splitlines()) - 2


def test_files_own_blocks_are_kept_and_renumbered() -> None:
    text = "000 GO X 1.000\n001   Y 1.000\n003 GO X 1.100\n004 SKIP TO 900\n900\n"
    (block,) = split_program(parse_program(text + text))[:1]
    assert block.text() == ("000 GO X 1.000\n001   Y 1.000\n002 GO X 1.100\n003 SKIP TO 900\n900\n")
    assert len(split_program(parse_program(text + text))) == 2


def test_skip_to_is_remapped_inside_its_block() -> None:
    text = "000 GO X 1.000\n005 SKIP TO 010\n007 GO X 2.000\n010 GO X 3.000\n"
    (block,) = split_program(parse_program(text))
    assert [line.render() for line in block.lines] == [
        "000 GO X 1.000",
        "001 SKIP TO 003",
        "002 GO X 2.000",
        "003 GO X 3.000",
        "004 SKIP TO 900",
        "900",
    ]


def test_skip_whose_target_starts_the_next_block_becomes_skip_to_900() -> None:
    texts = ["GR X .0001"] * 890 + ["SKIP TO 000"] + ["GR Y .001"] * 7 + ["GR X .001"] * 10
    numbered = [f"{i % 1000:03d} {t}" for i, t in enumerate(texts)]
    numbered[890] = f"890 SKIP TO {898 % 1000:03d}"
    blocks = split_program(parse_program("\n".join(numbered) + "\n"))
    assert blocks[0].lines[890].render() == "890 SKIP TO 900"
    assert blocks[1].lines[0].render() == "000 GR X .001"


def test_repeat_longer_than_a_block_is_refused_with_a_clear_message() -> None:
    texts = ["REPEAT 02"] + ["GR X .0001"] * 950 + ["REPEAT END"]
    numbered = "\n".join(f"{i % 1000:03d} {t}" for i, t in enumerate(texts)) + "\n"
    with pytest.raises(SplitError, match=r"REPEAT at line 000 .*REPEAT END at line 951"):
        split_program(parse_program(numbered))
    result = validate(parse_program(numbered))
    assert [p.code for p in result.errors] == ["split"]


def test_skip_across_more_than_a_block_is_refused() -> None:
    texts = ["SKIP TO 950"] + ["GR X .0001"] * 949 + ["GR X .0001"] + ["GR X .1"] * 5
    numbered = "\n".join(f"{i % 1000:03d} {t}" for i, t in enumerate(texts)) + "\n"
    with pytest.raises(SplitError, match="SKIP TO 950"):
        split_program(parse_program(numbered))


# ---- toolpath -------------------------------------------------------------------------------
def test_toolpath_times_follow_feed_and_rapid_rates() -> None:
    text = "000 FR X = 6.0\n001 GO X 1.000\n002 GOf X 0\n003 DWELL 2\n004 SKIP TO 900\n900\n"
    blocks = split_program(parse_program(text))
    path = build_toolpath(blocks, MachineState.initial(Units.INS))
    assert path.seconds(MoveKind.FEED) == pytest.approx(10.0)  # 1 in at 6 in/min
    assert path.seconds(MoveKind.RAPID) == pytest.approx(1.2)  # 1 in at 50 in/min
    assert path.seconds(MoveKind.DWELL) == pytest.approx(2.0)
    assert path.machining_seconds == pytest.approx(13.2)


def test_arc_goes_round_the_local_zero() -> None:
    text = "000 GO X 3.000\n001   Y 2.000\n002 ZERO AT\n003 X 2.000\n004 Y 2.000\n005 GR A 180\n"
    path = build_toolpath(split_program(parse_program(text)), MachineState.initial())
    end = path.moves[-1].move.end
    assert end[0] == pytest.approx(1.0) and end[1] == pytest.approx(2.0)
    assert path.moves[-1].move.length == pytest.approx(3.14159, rel=1e-3)


def test_samples_stay_inside_travel_and_mark_blocks() -> None:
    text = (PROGRAMS / "toy_mill_table_finish_cnc2.dyn").read_text()
    result = validate(parse_program(text))
    assert result.toolpath is not None
    path = result.toolpath
    assert path.blocks == 3 and len(path.block_starts) == 3
    assert {tm.block for tm in path.moves} == {1, 2, 3}
    low, high = path.bounds()
    assert low[0] >= 0 and high[0] <= 8 and low[2] >= -4 and high[2] <= 0
    assert path.faults == []


def test_cycles_cut_down_to_their_depth_and_return() -> None:
    text = "000 GOf X 2.000\n001   Y 2.000\n002 CPOCKET R= .500 ZD= -.300 DP= .100\n"
    path = build_toolpath(split_program(parse_program(text)), MachineState.initial())
    zs = {round(p[2], 6) for tm in path.moves for p in tm.move.path}
    assert {-0.1, -0.2, -0.3} <= zs
    assert path.moves[-1].move.end == pytest.approx((2.0, 2.0, 0.0))
