"""DYNALAN, the Dyna 2400 mill's language: statement table, parser, validator, splitter and
toolpath. Pure: no I/O, no clocks.

Usage::

    from cellctl.kinds.dyna2400 import dynalan

    program = dynalan.parse_program(text, name="BASE.DYN")
    result = dynalan.validate(program, dynalan.ValidationContext(units=dynalan.Units.INS))
    for problem in result.problems:
        print(problem.format("BASE.DYN"))
    if result.ok:
        for block in result.blocks: ...          # at most 900 lines each, closed, renumbered
        result.toolpath.machining_seconds

The statement table (:mod:`cellctl.kinds.dyna2400.dynalan.table`) is the one place the language is
described; see ``docs/mill.md`` for the syntax, including the project's own canned cycles.
"""

from cellctl.kinds.dyna2400.dynalan.machine import (
    MachineConfig,
    MachineState,
    Move,
    MoveKind,
    Outcome,
    ProgramFault,
    Step,
    execute,
    run_block,
    travel_fault,
)
from cellctl.kinds.dyna2400.dynalan.model import (
    Line,
    Problem,
    Program,
    ProgramRole,
    Severity,
    Statement,
)
from cellctl.kinds.dyna2400.dynalan.parser import (
    END_OF_TRANSMISSION,
    decode_line,
    encode_line,
    parse_line,
    parse_program,
    parse_statement,
)
from cellctl.kinds.dyna2400.dynalan.splitter import (
    Block,
    BlockLine,
    SplitError,
    join_blocks,
    split_program,
)
from cellctl.kinds.dyna2400.dynalan.table import STATEMENTS, Kind, Origin, Travel, Units
from cellctl.kinds.dyna2400.dynalan.toolpath import Toolpath, build_toolpath
from cellctl.kinds.dyna2400.dynalan.validator import (
    Validation,
    ValidationContext,
    resolve_role,
    validate,
)

__all__ = [
    "END_OF_TRANSMISSION",
    "STATEMENTS",
    "Block",
    "BlockLine",
    "Kind",
    "Line",
    "MachineConfig",
    "MachineState",
    "Move",
    "MoveKind",
    "Origin",
    "Outcome",
    "Problem",
    "Program",
    "ProgramFault",
    "ProgramRole",
    "Severity",
    "SplitError",
    "Statement",
    "Step",
    "Toolpath",
    "Travel",
    "Units",
    "Validation",
    "ValidationContext",
    "build_toolpath",
    "decode_line",
    "encode_line",
    "execute",
    "join_blocks",
    "parse_line",
    "parse_program",
    "parse_statement",
    "resolve_role",
    "run_block",
    "split_program",
    "travel_fault",
    "validate",
]
