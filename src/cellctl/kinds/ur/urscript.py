"""URScript, the subset a tending program uses: parse, check, run on a motion model. No I/O.

:func:`parse` gives a program's blocks (``def``/``while``/``if``/``elif``/``else``/``end``)
and its statements; :func:`check` lists what would fail on the robot before it gets there,
each with its line and column: unknown functions, unbalanced ``def``/``end``, expressions
that do not parse, poses out of the model's reach, joints beyond their limits::

    program = parse(text)                   # UsageError never: problems are in .problems
    problems = check(text, arm=ARMS["UR5e"], origin="tend.script")
    for step in run(program, env):          # Move(seconds, q0, q1) / Sleep(seconds)
        ...

Expressions are URScript's (numbers, ``True``/``False``, lists, poses ``p[...]``, calls
with keyword arguments, arithmetic, comparisons, ``and``/``or``/``not``): they are read with
Python's own parser (the grammar is the same for this subset, ``p[`` read as a call of
``p``) and evaluated by a walker that knows only these nodes, never ``eval``.

This module holds the check; the parser is :mod:`~cellctl.kinds.ur.urscript_syntax`, the
runtime :mod:`~cellctl.kinds.ur.urscript_run`. Import every name from here.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Sequence
from typing import Any

from cellctl.kinds.ur.motion import JOINT_LIMIT, Arm
from cellctl.kinds.ur.urscript_run import (
    MAX_STATEMENTS_WITHOUT_TIME,
    Env,
    Move,
    OffRobot,
    ScriptError,
    Sleep,
    Step,
    _Evaluator,
    _Pose,
    _RuntimeError,
    estimate,
    run,
)
from cellctl.kinds.ur.urscript_syntax import (
    Program,
    Statement,
    _split_statement,
    parse,
    parse_expression,
)

# Re-exported: the language's users import from this one module, whichever part holds a name.
__all__ = [
    "KNOWN_FUNCTIONS",
    "MAX_STATEMENTS_WITHOUT_TIME",
    "Env",
    "Move",
    "OffRobot",
    "Program",
    "ScriptError",
    "Sleep",
    "Statement",
    "Step",
    "check",
    "estimate",
    "parse",
    "parse_expression",
    "run",
]

#: The functions the check knows (the URScript manual's, those a tending program calls).
KNOWN_FUNCTIONS = frozenset(
    """
    movej movel movep movec servoj speedj speedl stopj stopl sleep sync halt textmsg popup
    set_standard_digital_out set_digital_out set_tool_digital_out
    set_configurable_digital_out get_standard_digital_in get_digital_in
    get_standard_digital_out get_digital_out get_tool_digital_in get_configurable_digital_in
    get_configurable_digital_out
    set_standard_analog_out get_standard_analog_in write_output_integer_register
    write_output_float_register write_output_boolean_register read_input_integer_register
    read_input_float_register read_input_boolean_register read_output_integer_register
    get_actual_joint_positions get_actual_tcp_pose get_target_tcp_pose
    get_target_joint_positions pose_trans pose_inv pose_add pose_sub pose_dist point_dist
    get_inverse_kin get_forward_kin set_tcp set_payload set_payload_mass set_gravity
    is_steady d2r r2d sqrt sin cos tan atan2 acos asin atan norm floor ceil pow log to_str
    str_cat str_len length
    """.split()  # noqa: SIM905 - a list to read, one word each
)


_ALLOWED = (
    ast.Expression, ast.Constant, ast.Name, ast.Load, ast.List, ast.Tuple, ast.BinOp,
    ast.UnaryOp, ast.BoolOp, ast.Compare, ast.Call, ast.keyword, ast.Subscript,
    ast.Add, ast.Sub, ast.Mult, ast.Div, ast.Mod, ast.Pow, ast.USub, ast.UAdd, ast.Not,
    ast.And, ast.Or, ast.Eq, ast.NotEq, ast.Lt, ast.LtE, ast.Gt, ast.GtE,
)  # fmt: skip


# -- the check ------------------------------------------------------------------------------------


def check(text: str, arm: Arm, origin: str = "program") -> list[str]:
    """Every problem of a program, ``origin:line:column: text``, in the order found."""
    program = parse(text)
    found = list(program.problems)
    defined = set(program.functions)

    def visit(statements: Sequence[Statement], in_loop: bool) -> None:
        for st in statements:
            kind, _, expr = _split_statement(st.text)
            expr = expr.strip()
            if kind in ("break", "continue") and not in_loop:
                found.append((st.line, st.column, f"'{kind}' outside a loop"))
            offset = st.text.find(expr) if expr else 0
            if kind in ("while", "if", "elif", "assign", "expr", "return") and expr:
                try:
                    tree = parse_expression(expr)
                except SyntaxError as e:
                    col = st.column + offset + max(0, (e.offset or 1) - 1)
                    found.append((st.line, col, f"does not parse: {e.msg}"))
                else:
                    for problem in _expression_problems(tree, defined, arm):
                        found.append((st.line, st.column + offset + problem[0], problem[1]))
            # A function's body starts outside any loop, wherever it is defined.
            body_in_loop = kind == "while" or (in_loop and kind not in ("def", "thread"))
            visit(st.body, body_in_loop)
            visit(st.orelse, in_loop)

    visit(program.statements, False)
    found.sort()
    return [f"{origin}:{line}:{col}: {text}" for line, col, text in found]


def _constant(node: ast.expr) -> Any:
    try:
        return _Evaluator({}, {}).value(node)
    except (_RuntimeError, TypeError, ValueError, ZeroDivisionError, OverflowError):
        return None


def _expression_problems(tree: ast.expr, defined: set[str], arm: Arm) -> list[tuple[int, str]]:
    out: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if not isinstance(node, _ALLOWED):
            col = getattr(node, "col_offset", 0)
            out.append((col, f"not URScript: {type(node).__name__}"))
            continue
        if not isinstance(node, ast.Call):
            continue
        if not isinstance(node.func, ast.Name):
            out.append((node.col_offset, "only functions by name may be called"))
            continue
        name = node.func.id
        if name == "p":
            pose = _constant(node)
            if isinstance(pose, _Pose):
                distance = math.sqrt(sum(c * c for c in pose.values[:3]))
                if distance > arm.reach:
                    out.append(
                        (
                            node.col_offset,
                            f"pose out of reach for a {arm.name}: {distance:.3f} m from the "
                            f"base, its reach is {arm.reach:.3f} m",
                        )
                    )
            continue
        if name not in KNOWN_FUNCTIONS and name not in defined:
            out.append((node.func.col_offset, f"unknown function '{name}'"))
        if name in ("movej", "movel", "movep") and node.args:
            q = _constant(node.args[0])
            if isinstance(q, list) and len(q) == 6:
                for i, v in enumerate(q):
                    if isinstance(v, int | float) and abs(v) > JOINT_LIMIT:
                        out.append(
                            (
                                node.args[0].col_offset,
                                f"joint {i} at {v:.3f} rad is beyond its limit "
                                f"±{JOINT_LIMIT:.3f} rad",
                            )
                        )
    return out
