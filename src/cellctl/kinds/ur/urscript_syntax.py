"""URScript's syntax, the subset a tending program uses: blocks, statements, expressions.

The layer under the check (:mod:`cellctl.kinds.ur.urscript`) and the runner
(:mod:`cellctl.kinds.ur.urscript_run`); import them from :mod:`~cellctl.kinds.ur.urscript`::

    program = parse(text)                   # problems in program.problems, never raised
    tree = parse_expression("x + 1")        # Python's ast, ``p[...]`` read as a call of ``p``
"""

from __future__ import annotations

import ast
import functools
import re
from dataclasses import dataclass, field

#: Block openers and what closes them.
_OPENERS = ("def ", "while ", "if ", "thread ")
_CONTINUERS = ("elif ", "else:")


@dataclass
class Statement:
    """One line of the program: its text, where it is, and its block (if it opens one)."""

    text: str
    line: int
    column: int
    body: list[Statement] = field(default_factory=list)
    orelse: list[Statement] = field(default_factory=list)

    @property
    def keyword(self) -> str:
        return self.text.split(None, 1)[0].rstrip(":") if self.text else ""


@dataclass
class Program:
    """A parsed program: its top-level statements and the problems parsing found."""

    statements: list[Statement]
    problems: list[tuple[int, int, str]]
    functions: dict[str, Statement]

    @property
    def entry(self) -> Statement | None:
        """The program that runs: the first top-level ``def`` (None: bare statements)."""
        return next((s for s in self.statements if s.keyword == "def"), None)


_COMMENT = re.compile(r"#.*$")


def _strip_comment(line: str) -> str:
    # A '#' inside a string literal stays.
    out, quote = [], ""
    for ch in line:
        if quote:
            out.append(ch)
            if ch == quote:
                quote = ""
        elif ch in "\"'":
            quote = ch
            out.append(ch)
        elif ch == "#":
            break
        else:
            out.append(ch)
    return "".join(out).rstrip()


def parse(text: str) -> Program:
    """The program's statements, blocks nested; unbalanced blocks are problems."""
    problems: list[tuple[int, int, str]] = []
    root: list[Statement] = []
    stack: list[tuple[Statement, list[Statement]]] = []
    functions: dict[str, Statement] = {}
    for number, raw in enumerate(text.splitlines(), start=1):
        stripped = _strip_comment(raw)
        body = stripped.strip()
        if not body:
            continue
        column = len(stripped) - len(stripped.lstrip()) + 1
        target = stack[-1][1] if stack else root
        if body == "end":
            if not stack:
                problems.append((number, column, "'end' without a block to close"))
            else:
                stack.pop()
            continue
        if body.startswith(_CONTINUERS):
            if not stack or stack[-1][0].keyword not in ("if", "elif"):
                problems.append((number, column, f"'{body.split()[0]}' without an 'if'"))
                continue
            opener, _ = stack.pop()
            st = Statement(body, number, column)
            opener.orelse.append(st)
            stack.append((st, st.body))
            # An elif/else closes with the if's single 'end': keep the if's frame count.
            continue
        st = Statement(body, number, column)
        target.append(st)
        if body.startswith(_OPENERS):
            if not body.endswith(":"):
                problems.append((number, column + len(body), f"'{st.keyword}' needs a ':'"))
            if st.keyword == "def":
                name = body[4:].split("(", 1)[0].strip()
                functions[name] = st
            stack.append((st, st.body))
    for opener, _ in stack:
        problems.append((opener.line, opener.column, f"'{opener.text}' has no 'end'"))
    return Program(root, problems, functions)


# -- expressions ----------------------------------------------------------------------------------


def _python(expr: str) -> str:
    """``p[...]`` as a call of ``p`` (same length: columns stay where they were)."""
    out = list(expr)
    stack: list[bool] = []
    quote = ""
    for i, ch in enumerate(expr):
        if quote:
            if ch == quote:
                quote = ""
            continue
        if ch in "\"'":
            quote = ch
        elif ch == "[":
            pose = (
                i > 0
                and expr[i - 1] == "p"
                and (i < 2 or not (expr[i - 2].isalnum() or expr[i - 2] == "_"))
            )
            stack.append(pose)
            if pose:
                out[i] = "("
        elif ch == "]" and stack and stack.pop():
            out[i] = ")"
    return "".join(out)


@functools.lru_cache(maxsize=4096)
def parse_expression(expr: str) -> ast.expr:
    """An expression's tree; SyntaxError (with its offset) when it does not parse.

    Cached: a program's loop evaluates the same lines again and again (the trees are only
    read, never changed)."""
    source = _python(expr.strip())
    nul = source.find("\0")
    if nul >= 0:
        # Early 3.11 releases (3.11.2) raise ValueError here, later ones (3.11.7) a
        # SyntaxError without its place: said the same on every release, with the column.
        raise SyntaxError("a NUL character", ("<script>", 1, nul + 1, source, 1, nul + 2))
    tree = ast.parse(source, mode="eval")
    return tree.body


def _split_statement(text: str) -> tuple[str, str | None, str]:
    """``(kind, target, expression)``: kind is "assign", "expr", a keyword's, or "def"."""
    word = text.split(None, 1)[0].rstrip(":")
    if word in ("while", "if", "elif"):
        return word, None, text[len(word) :].rstrip(":").strip()
    if word in ("else", "def", "thread", "return", "break", "continue", "halt"):
        rest = text[len(word) :].strip()
        return word, None, rest
    body = text
    for prefix in ("global ", "local "):
        if body.startswith(prefix):
            body = body[len(prefix) :]
    m = re.match(r"^([A-Za-z_]\w*)\s*=(?!=)(.*)$", body)
    if m:
        return "assign", m.group(1), m.group(2)
    return "expr", None, body
