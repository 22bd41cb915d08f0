"""URScript run on a motion model: the runtime behind :func:`run` and :func:`estimate`. No I/O.

The UR emulator runs a program's steps in its machine time, the time estimate adds them up;
both import these names from :mod:`cellctl.kinds.ur.urscript`::

    for step in run(program, env, arm):     # Move(seconds, q0, q1) / Sleep(seconds)
        ...
    seconds, moves = estimate(program, arm)

Expressions are evaluated by :class:`_Evaluator`, a walker over the few ``ast`` nodes
URScript has, never ``eval``; the check uses it too, for the constants it holds to the arm.
"""

from __future__ import annotations

import ast
import math
import re
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from cellctl.kinds.ur.motion import (
    HOME,
    MOVEJ_A,
    MOVEJ_V,
    MOVEL_A,
    MOVEL_V,
    Arm,
    Joints,
    joint_distance,
    line_distance,
    move_time,
)
from cellctl.kinds.ur.urscript_syntax import Program, Statement, _split_statement, parse_expression

#: How many statements may run without the robot's time moving on (a busy loop): the
#: controller stops such a program ("infinite loop detected"), so does the emulator.
MAX_STATEMENTS_WITHOUT_TIME = 100_000


@dataclass(frozen=True)
class Move:
    """The arm moves from ``start`` to ``end`` (joints) in ``seconds`` (machine time)."""

    seconds: float
    start: Joints
    end: Joints
    linear: bool = False


@dataclass(frozen=True)
class Sleep:
    """The program waits ``seconds`` (machine time)."""

    seconds: float


Step = Move | Sleep


class Env(Protocol):
    """What a running program reads and writes of its robot."""

    q: Joints

    def digital_in(self, n: int) -> bool: ...
    def digital_out(self, n: int) -> bool: ...
    def set_digital_out(self, n: int, value: bool) -> None: ...
    def write_register(self, n: int, value: int) -> None: ...
    def read_register(self, n: int) -> int: ...
    def message(self, text: str) -> None: ...


class ScriptError(Exception):
    """A runtime error in the controller's words (``Runtime error: ...``)."""


class _RuntimeError(ScriptError):
    pass


@dataclass(frozen=True)
class _Pose:
    values: tuple[float, ...]


class _Return(Exception):
    def __init__(self, value: Any) -> None:
        self.value = value


class _Halt(Exception):
    pass


class _Break(Exception):
    pass


class _Continue(Exception):
    pass


def _outside_loop(e: _Break | _Continue) -> ScriptError:
    word = "break" if isinstance(e, _Break) else "continue"
    return ScriptError(f"Runtime error: '{word}' outside a loop")


_BINOPS: dict[type, Callable[[Any, Any], Any]] = {
    ast.Add: lambda a, b: a + b,
    ast.Sub: lambda a, b: a - b,
    ast.Mult: lambda a, b: a * b,
    ast.Div: lambda a, b: a / b,
    ast.Mod: lambda a, b: a % b,
    ast.Pow: lambda a, b: a**b,
}
_COMPARE: dict[type, Callable[[Any, Any], bool]] = {
    ast.Eq: lambda a, b: a == b,
    ast.NotEq: lambda a, b: a != b,
    ast.Lt: lambda a, b: a < b,
    ast.LtE: lambda a, b: a <= b,
    ast.Gt: lambda a, b: a > b,
    ast.GtE: lambda a, b: a >= b,
}
_MATH: dict[str, Callable[..., Any]] = {
    "sqrt": math.sqrt, "sin": math.sin, "cos": math.cos, "tan": math.tan, "atan2": math.atan2,
    "acos": math.acos, "asin": math.asin, "atan": math.atan, "floor": math.floor,
    "ceil": math.ceil, "pow": math.pow, "log": math.log, "d2r": math.radians,
    "r2d": math.degrees, "norm": lambda v: math.sqrt(sum(x * x for x in v))
    if isinstance(v, list) else abs(v), "to_str": str, "str_cat": lambda a, b: f"{a}{b}",
    "str_len": len, "length": len,
}  # fmt: skip


class _Evaluator:
    """Values of expressions over ``variables``; calls go to ``functions``."""

    def __init__(self, variables: dict[str, Any], functions: dict[str, Callable[..., Any]]):
        self.variables = variables
        self.functions = functions

    def value(self, node: ast.expr) -> Any:
        if isinstance(node, ast.Constant):
            if isinstance(node.value, bool | int | float | str):
                return node.value
            raise _RuntimeError(f"not a value: {node.value!r}")
        if isinstance(node, ast.Name):
            if node.id in self.variables:
                return self.variables[node.id]
            raise _RuntimeError(f"Variable '{node.id}' is not initialized")
        if isinstance(node, ast.List | ast.Tuple):
            return [self.value(e) for e in node.elts]
        if isinstance(node, ast.UnaryOp):
            v = self.value(node.operand)
            if isinstance(node.op, ast.Not):
                return not v
            return -v if isinstance(node.op, ast.USub) else +v
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            return _BINOPS[type(node.op)](self.value(node.left), self.value(node.right))
        if isinstance(node, ast.BoolOp):
            if isinstance(node.op, ast.And):
                return all(self.value(v) for v in node.values)
            return any(self.value(v) for v in node.values)
        if isinstance(node, ast.Compare):
            left = self.value(node.left)
            for op, right_node in zip(node.ops, node.comparators, strict=True):
                right = self.value(right_node)
                if type(op) not in _COMPARE or not _COMPARE[type(op)](left, right):
                    return False
                left = right
            return True
        if isinstance(node, ast.Subscript):
            return self.value(node.value)[int(self.value(node.slice))]
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            args = [self.value(a) for a in node.args]
            kwargs = {k.arg: self.value(k.value) for k in node.keywords if k.arg}
            name = node.func.id
            if name == "p":
                if len(args) != 6 or not all(isinstance(a, int | float) for a in args):
                    raise _RuntimeError("a pose takes six numbers")
                return _Pose(tuple(float(a) for a in args))
            if name in _MATH:
                return _MATH[name](*args)
            if name in self.functions:
                return self.functions[name](*args, **kwargs)
            raise _RuntimeError(f"Unknown function '{name}'")
        raise _RuntimeError(f"not supported: {type(node).__name__}")


def run(program: Program, env: Env, arm: Arm) -> Iterator[Step]:
    """Run ``program`` on ``env``: yields each step that takes the robot's time.

    Raises :class:`ScriptError` (in the controller's words) for a runtime error.
    """
    runner = _Runner(program, env, arm)
    entry = program.entry
    statements = entry.body if entry is not None else program.statements
    try:
        yield from runner.block(statements, {})
    except (_Halt, _Return):
        return
    except (_Break, _Continue) as e:
        raise _outside_loop(e) from None
    except ScriptError:
        raise
    except (TypeError, ValueError, IndexError, ZeroDivisionError, OverflowError) as e:
        raise ScriptError(f"Runtime error: {e}") from None


class _Runner:
    def __init__(self, program: Program, env: Env, arm: Arm) -> None:
        self.program = program
        self.env = env
        self.arm = arm
        self.globals: dict[str, Any] = {}
        self.untimed = 0
        self.pending: list[Step] = []

    def _tick(self) -> None:
        self.untimed += 1
        if self.untimed > MAX_STATEMENTS_WITHOUT_TIME:
            raise ScriptError("Runtime error: infinite loop detected")

    def _calls(self, scope: dict[str, Any]) -> dict[str, Callable[..., Any]]:
        env, arm = self.env, self.arm

        def move(target: Any, linear: bool, a: float, v: float, t: float) -> None:
            start = env.q
            if isinstance(target, _Pose):
                end = arm.solve(target.values, start)
                if end is None:
                    raise ScriptError(
                        f"Runtime error: the pose {list(target.values)} cannot be reached"
                    )
                distance = (
                    line_distance(arm.tcp(start), target.values)
                    if linear
                    else joint_distance(start, end)
                )
            else:
                if not isinstance(target, list) or len(target) != 6:
                    raise ScriptError("Runtime error: a move takes a pose or six joints")
                end = (target[0], target[1], target[2], target[3], target[4], target[5])
                distance = (
                    line_distance(arm.tcp(start), arm.tcp(end))
                    if linear
                    else joint_distance(start, end)
                )
            seconds = move_time(distance, v, a, t)
            env.q = end
            self.pending.append(Move(seconds, start, end, linear))

        def movej(
            q: Any, a: float = MOVEJ_A, v: float = MOVEJ_V, t: float = 0.0, r: float = 0.0
        ) -> None:
            move(q, False, a, v, t)

        def movel(
            pose: Any, a: float = MOVEL_A, v: float = MOVEL_V, t: float = 0.0, r: float = 0.0
        ) -> None:
            move(pose, True, a, v, t)

        def sleep(t: float) -> None:
            self.pending.append(Sleep(max(0.0, float(t))))

        def sync() -> None:
            self.pending.append(Sleep(0.002))

        def halt() -> None:
            raise _Halt()

        def set_out(n: int, b: bool) -> None:
            env.set_digital_out(int(n), bool(b))

        def write_register(n: int, value: int) -> None:
            env.write_register(int(n), int(value))

        calls: dict[str, Callable[..., Any]] = {
            "movej": movej, "movel": movel, "movep": movel, "sleep": sleep, "sync": sync,
            "halt": halt, "set_standard_digital_out": set_out, "set_digital_out": set_out,
            "get_standard_digital_in": lambda n: env.digital_in(int(n)),
            "get_digital_in": lambda n: env.digital_in(int(n)),
            "get_configurable_digital_in": lambda n: env.digital_in(8 + int(n)),
            "get_configurable_digital_out": lambda n: env.digital_out(8 + int(n)),
            "set_configurable_digital_out": lambda n, b: set_out(8 + int(n), b),
            "get_standard_digital_out": lambda n: env.digital_out(int(n)),
            "get_digital_out": lambda n: env.digital_out(int(n)),
            "write_output_integer_register": write_register,
            "read_input_integer_register": lambda n: env.read_register(int(n)),
            "textmsg": lambda *a: env.message(" ".join(str(x) for x in a)),
            "popup": lambda *a, **k: env.message(str(a[0]) if a else ""),
            "get_actual_joint_positions": lambda: list(env.q),
            "get_target_joint_positions": lambda: list(env.q),
            "get_actual_tcp_pose": lambda: _Pose(arm.tcp(env.q)),
            "get_target_tcp_pose": lambda: _Pose(arm.tcp(env.q)),
            "set_tcp": lambda *a: None, "set_payload": lambda *a: None,
            "set_payload_mass": lambda *a: None, "set_gravity": lambda *a: None,
            "set_standard_analog_out": lambda *a: None, "stopj": lambda *a: None,
            "stopl": lambda *a: None,
        }  # fmt: skip
        return calls

    def _user_call(self, name: str) -> Callable[..., Any]:
        def call(*args: Any) -> Any:
            raise ScriptError(
                f"Runtime error: the emulator runs '{name}()' only as a statement "
                "or as an assignment's whole right side"
            )

        return call

    def _eval(self, expr: str, scope: dict[str, Any]) -> Any:
        functions = self._calls(scope)
        for name in self.program.functions:
            functions.setdefault(name, self._user_call(name))
        try:
            tree = parse_expression(expr)
        except SyntaxError as e:
            raise ScriptError(f"Runtime error: syntax error in {expr!r}: {e.msg}") from None
        return _Evaluator({**self.globals, **scope}, functions).value(tree)

    def block(self, statements: Sequence[Statement], scope: dict[str, Any]) -> Iterator[Step]:
        for st in statements:
            yield from self.statement(st, scope)

    def _flush(self) -> Iterator[Step]:
        while self.pending:
            step = self.pending.pop(0)
            self.untimed = 0
            yield step

    def _user_function(self, expr: str) -> tuple[Statement, list[str]] | None:
        m = re.match(r"^([A-Za-z_]\w*)\s*\((.*)\)\s*$", expr.strip())
        if m and m.group(1) in self.program.functions:
            args = [a for a in m.group(2).split(",") if a.strip()]
            return self.program.functions[m.group(1)], args
        return None

    def _invoke(self, fn: Statement, args: list[str], scope: dict[str, Any]) -> Iterator[Step]:
        header = fn.text[4:]
        params = [p.strip() for p in header.split("(", 1)[1].rsplit(")", 1)[0].split(",")]
        params = [p for p in params if p]
        local = {p: self._eval(a, scope) for p, a in zip(params, args, strict=False)}
        try:
            yield from self.block(fn.body, local)
        except _Return as r:
            self.globals["__result__"] = r.value
            return
        except (_Break, _Continue) as e:
            # Not the caller's loop: a function's break ends nothing outside it.
            raise _outside_loop(e) from None
        self.globals["__result__"] = None

    def statement(self, st: Statement, scope: dict[str, Any]) -> Iterator[Step]:
        self._tick()
        kind, target, expr = _split_statement(st.text)
        if kind == "def" or kind == "thread":
            return
        if kind == "while":
            while self._eval(expr, scope):
                self._tick()
                try:
                    yield from self.block(st.body, scope)
                except _Break:
                    break
                except _Continue:
                    continue
            return
        if kind in ("if", "elif"):
            if self._eval(expr, scope):
                yield from self.block(st.body, scope)
            else:
                for branch in st.orelse:
                    yield from self.statement(branch, scope)
            return
        if kind == "else":
            yield from self.block(st.body, scope)
            return
        if kind == "return":
            raise _Return(self._eval(expr, scope) if expr else None)
        if kind == "break":
            raise _Break()
        if kind == "continue":
            raise _Continue()
        if kind == "halt":
            raise _Halt()
        user = self._user_function(expr)
        if user is not None:
            yield from self._invoke(user[0], user[1], scope)
            value = self.globals.pop("__result__", None)
        else:
            value = self._eval(expr, scope)
            yield from self._flush()
        if kind == "assign" and target is not None:
            if target in self.globals or st.text.startswith("global "):
                self.globals[target] = value
            else:
                scope[target] = value


class OffRobot:
    """An environment for running a program off the robot (its time estimate, a test):
    inputs as they are asked to be, outputs kept, registers 0."""

    def __init__(self) -> None:
        self.q: Joints = HOME
        self.outputs: dict[int, bool] = {}

    def digital_in(self, n: int) -> bool:
        return True

    def digital_out(self, n: int) -> bool:
        return self.outputs.get(n, False)

    def set_digital_out(self, n: int, value: bool) -> None:
        self.outputs[n] = value

    def write_register(self, n: int, value: int) -> None:
        pass

    def read_register(self, n: int) -> int:
        return 0

    def message(self, text: str) -> None:
        pass


def estimate(program: Program, arm: Arm, limit_s: float = 3600.0) -> tuple[float, list[Move]]:
    """Machine seconds the program takes with every input on (waits cost nothing), and its
    moves; stops counting at ``limit_s``."""
    total = 0.0
    moves: list[Move] = []
    try:
        for step in run(program, OffRobot(), arm):
            total += step.seconds
            if isinstance(step, Move):
                moves.append(step)
            if total > limit_s:
                break
    except ScriptError:
        pass
    return total, moves
