"""``cellctl program check|preview``: a program of any installed kind (the shipped ones and
the saw plug-in) checked and drawn by its kind's own language, the kind found by the file's
ending, ``--kind`` or the cell's ``--machine`` (whose options apply); refusals in words,
exit 2, nothing else done. The example programs run as a user runs them (``cellctl`` in a
process of its own); the rest on the real command line in this process."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

from click.testing import CliRunner, Result

from cellctl.ui.cli import main
from tests.conftest import CELLCTL

ROOT = Path(__file__).resolve().parent.parent
TENDING = ROOT / "examples" / "cell-tending"
CELL = ROOT / "examples" / "cell"
SAW = ROOT / "tests" / "plugins" / "kerf_cell" / "programs" / "bars.cut"

#: A G-code program with an O-number of five digits (four by default).
FIVE_DIGITS = "%\nO12345 (BRACKET)\nG21 G90 G17\nG00 X0 Y0\nG01 X10 Y10 F300\nM30\n%\n"


def cellctl(*args: str) -> Result:
    return CliRunner().invoke(main, list(args))


def test_every_kinds_example_programs_check_by_their_ending() -> None:
    files = [
        TENDING / "programs" / "O1001.nc",
        TENDING / "programs" / "cnc2_setup.dyn",
        *sorted((TENDING / "robot").glob("*.script")),
        *sorted((CELL / "robot").glob("*.aml")),
        SAW,
    ]
    done = subprocess.run(
        [*CELLCTL, "program", "check", *map(str, files)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    said = dict(line.split(": ", 1) for line in done.stdout.splitlines())
    kinds = {Path(f).name: re.match(r"a good (\S+) program, \d+ line", said[str(f)]) for f in files}
    assert all(kinds.values()), done.stdout
    by_ending = {Path(name).suffix: m.group(1) for name, m in kinds.items() if m}
    # The 7545 and the 7547 read .aml alike: the first of them is named.
    assert by_ending == {
        ".nc": "iso-cnc",
        ".dyn": "dyna2400",
        ".script": "ur",
        ".aml": "ibm7545",
        ".cut": "kerf100",
    }
    # A mill program's run time is estimated by its kind's motion model.
    assert re.search(r"est\. run time \d+:\d\d:\d\d$", said[str(files[0])]), done.stdout


def test_problems_with_their_lines_and_exit_1(tmp_path: Path) -> None:
    nofeed = tmp_path / "nofeed.nc"
    nofeed.write_text("%\nO1001\nG21 G90\nG00 X0 Y0\nG01 X10 Y10\nM30\n%\n")
    good = tmp_path / "good.nc"
    good.write_text(FIVE_DIGITS.replace("O12345", "O1234"))
    result = cellctl("program", "check", str(good), str(nofeed))
    assert result.exit_code == 1, result.output
    assert f"{good}: a good iso-cnc program" in result.output
    assert f"{nofeed}:5: G01 move with no feed" in result.output
    assert f"{nofeed}: 1 problem(s) as an iso-cnc program" in result.output


def test_a_problem_on_line_100_is_said_so_not_drawn_as_an_emoji(tmp_path: Path) -> None:
    rows = ["000 START INS 01", *(f"{i:03d} GO X 1" for i in range(1, 99))]
    rows += ["099 GO X 99999", "100 SKIP TO 900", "900"]
    program = tmp_path / "far.dyn"
    program.write_text("\n".join(rows) + "\n")
    for command in (["program", "check"], ["mill", "check"]):
        result = cellctl(*command, str(program))
        assert result.exit_code == 1, result.output
        assert f"{program}:100:" in result.output, result.output


def test_the_machines_options_apply(tmp_path: Path) -> None:
    (tmp_path / "cell.toml").write_text(
        '[machines.haas]\nkind = "iso-cnc"\nlink = "socket://127.0.0.1:1"\n'
        "options = { o_digits = 5 }\n"
    )
    program = tmp_path / "O12345.nc"
    program.write_text(FIVE_DIGITS)
    plain = cellctl("program", "check", str(program))
    assert plain.exit_code == 1 and "O12345: more than 4 digits" in plain.output
    haas = cellctl("--cell", str(tmp_path), "program", "check", "--machine", "haas", str(program))
    assert haas.exit_code == 0, haas.output
    mismatch = cellctl(
        "--cell", str(tmp_path), "program", "check", "--machine", "haas", "--kind", "ur",
        str(program),
    )  # fmt: skip
    assert mismatch.exit_code == 2
    assert "--kind ur: haas is an iso-cnc in cell.toml" in mismatch.output


def test_refusals_name_what_is_known(tmp_path: Path) -> None:
    text = tmp_path / "notes.txt"
    text.write_text("G01 X1\n")
    unknown = cellctl("program", "check", str(text))
    assert unknown.exit_code == 2
    assert "no installed kind's programs end in .txt (known: .aml ibm7545" in unknown.output
    assert ".nc iso-cnc" in unknown.output and "say --kind" in unknown.output
    missing = cellctl("program", "check", str(tmp_path / "gone.nc"))
    assert missing.exit_code == 2 and "gone.nc: no such file" in missing.output
    no_kind = cellctl("program", "check", "--kind", "lathe9", str(text))
    assert no_kind.exit_code == 2 and "unknown machine kind 'lathe9'" in no_kind.output
    no_machine = cellctl(
        "--cell", str(tmp_path), "program", "check", "--machine", "cnc9", str(text)
    )  # fmt: skip
    assert no_machine.exit_code == 2 and "unknown machine 'cnc9'" in no_machine.output
    as_nc = cellctl("program", "check", "--kind", "iso-cnc", str(text))
    assert as_nc.exit_code == 1 and "a good" not in as_nc.output


def test_preview_draws_a_mill_program_and_refuses_what_has_no_toolpath(tmp_path: Path) -> None:
    drawing = tmp_path / "o1001.svg"
    program = TENDING / "programs" / "O1001.nc"
    result = cellctl("program", "preview", str(program), "-o", str(drawing))
    assert result.exit_code == 0, result.output
    svg = drawing.read_text()
    assert svg.startswith("<svg") and "<polyline" in svg
    assert f"{drawing}: O1001.nc drawn, " in result.output
    robot = cellctl("program", "preview", str(CELL / "robot" / "conveyor_to_cnc1.aml"), "-o",
                    str(tmp_path / "r.svg"))  # fmt: skip
    assert robot.exit_code == 2 and "has no toolpath to draw" in robot.output
    assert not (tmp_path / "r.svg").exists()
    png = cellctl("program", "preview", str(program), "-o", str(tmp_path / "o.png"))
    assert png.exit_code == 2 and "must end in .svg" in png.output
    bad = tmp_path / "bad.nc"
    bad.write_text("%\nO1001\nG01 X10 Y10\nM30\n%\n")
    refused = cellctl("program", "preview", str(bad), "-o", str(tmp_path / "bad.svg"))
    assert refused.exit_code == 2 and "cannot draw" in refused.output
    assert not (tmp_path / "bad.svg").exists()


def test_the_dyna_2400s_check_sends_another_kinds_program_to_program_check() -> None:
    program = str(TENDING / "programs" / "O1001.nc")
    by_kind = cellctl("mill", "--kind", "iso-cnc", "check", program)
    assert by_kind.exit_code == 2, by_kind.output
    assert "`cellctl program check|preview FILE`" in by_kind.output
    by_name = cellctl("--cell", str(TENDING), "mill", "vf2", "check", program)
    assert by_name.exit_code == 2, by_name.output
    assert "vf2 is an iso-cnc: `mill check` reads DYNALAN" in by_name.output
    assert "`cellctl program check --machine vf2 FILE`" in by_name.output
    works = cellctl("--cell", str(TENDING), "program", "check", "--machine", "vf2", program)
    assert works.exit_code == 0, works.output


def test_json_for_a_pipeline(tmp_path: Path) -> None:
    nofeed = tmp_path / "nofeed.nc"
    nofeed.write_text("%\nO1001\nG21 G90\nG00 X0 Y0\nG01 X10 Y10\nM30\n%\n")
    good = TENDING / "programs" / "O1001.nc"
    result = CliRunner().invoke(main, ["program", "check", "--json", str(nofeed), str(good)])
    assert result.exit_code == 1, result.output
    bad_one, good_one = json.loads(result.stdout)
    assert (bad_one["file"], bad_one["kind"], bad_one["ok"]) == (str(nofeed), "iso-cnc", False)
    assert bad_one["problems"] == [f"{nofeed}:5: G01 move with no feed: no F before it"]
    assert good_one["ok"] is True and good_one["problems"] == []
    # The same figures as the line a person reads.
    said = cellctl("program", "check", str(good)).output
    assert f"{good_one['lines']} line(s)" in said and good_one["machining_s"] > 0
