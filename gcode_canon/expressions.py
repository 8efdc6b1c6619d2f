"""Numbers, parameter references, ``[...]`` expressions and functions (LinuxCNC grammar).

The reader works on a line already folded by :mod:`gcode_canon.lexer` (lower case, no spaces, each
comment replaced by a ``(`` marker) and evaluates as it reads, as LinuxCNC does: expressions on a line
are evaluated when the line is read, before anything on it is executed.

Precedence, highest first: ``**``; ``* / MOD``; ``+ -``; ``EQ NE GT GE LT LE``; ``AND OR XOR``.
Operators of one level apply left to right. Angles are degrees. Equality (EQ, NE) has a 0.0001
tolerance; GT, GE, LT and LE compare strictly, as LinuxCNC does, unless the reader's
``tolerant_order`` is set (the gcode-canon dialect: its documentation applies the tolerance to every
comparison, so ``[0.99999 LT 1]`` is 0 there and 1 in LinuxCNC).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from typing import Protocol, TypeVar

from gcode_canon.errors import GCodeError

TOLERANCE_EQUAL = 0.0001
"""Values closer than this compare equal (LinuxCNC's TOLERANCE_EQUAL); also the near-integer rule."""

TOLERANCE_GE_LE = 1e-6
"""LinuxCNC's GE and LE also hold for values this close (interp_execute.cc execute_binary2, master's
TOLERANCE_EQUAL); its GT and LT are strict."""

MAX_PARAMETER = 5601
"""Highest parameter number: LinuxCNC's ``RS274NGC_MAX_PARAMETERS`` (5602, ``interp_parameter_def.hh``) is
the size of its parameter array, and ``read_parameter`` / ``read_parameter_setting`` (``interp_read.cc``)
refuse an index below 1 or not below that size, so #1-#5601 exist and #5602 does not."""

PARAMETER_OUT_OF_RANGE = "Parameter number out of range"  # LinuxCNC NCE_PARAMETER_NUMBER_OUT_OF_RANGE
NON_INTEGER = "Non integer value for integer"  # LinuxCNC NCE_NON_INTEGER_VALUE_FOR_INTEGER

_NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)")

# name -> precedence (higher binds tighter)
_PRECEDENCE = {
    "**": 4,
    "*": 3, "/": 3, "mod": 3,
    "+": 2, "-": 2,
    "eq": 1, "ne": 1, "gt": 1, "ge": 1, "lt": 1, "le": 1,
    "and": 0, "or": 0, "xor": 0,
}
_WORD_OPS = ("mod", "eq", "ne", "gt", "ge", "lt", "le", "and", "or", "xor")
_FUNCTIONS = ("abs", "acos", "asin", "atan", "cos", "exists", "exp", "fix", "fup", "round", "ln", "sin",
              "sqrt", "tan")


class ParameterReader(Protocol):
    def get_numbered(self, index: int) -> float: ...

    def get_named(self, name: str) -> float: ...

    def exists(self, name: str) -> bool: ...


def near_int(value: float, what: str = "value") -> int:
    """The integer ``value`` is within 0.0001 of, or a GCodeError."""
    r = round(value)
    if abs(value - r) > TOLERANCE_EQUAL:
        raise GCodeError(f"{what} must be an integer, not {value:g}")
    return int(r)


def _finite(value: float, what: str = "Result") -> float:
    if not math.isfinite(value):
        raise GCodeError(f"{what} out of range (overflow)")
    return value


class ExpressionReader:
    """Reads real values from a folded line; holds the parameter store and the nesting limit."""

    __slots__ = ("max_depth", "params", "tolerant_order")

    def __init__(self, params: ParameterReader, max_depth: int = 64, tolerant_order: bool = False) -> None:
        self.params = params
        self.max_depth = max_depth
        self.tolerant_order = tolerant_order

    # --- values -----------------------------------------------------------------------------------

    def real_value(self, s: str, i: int, depth: int = 0) -> tuple[float, int]:
        """A number, ``#`` parameter, ``[expression]``, function or signed one of those at ``s[i]``."""
        if depth > self.max_depth:
            raise GCodeError(f"Expression nested too deeply (more than {self.max_depth} levels)")
        if i >= len(s):
            raise GCodeError("Missing value at end of line")
        c = s[i]
        if c == "[":
            return self.expression(s, i, depth + 1)
        if c == "#":
            return self.parameter(s, i, depth + 1)
        if c in "+-" and i + 1 < len(s) and s[i + 1] not in "0123456789.":
            value, j = self.real_value(s, i + 1, depth + 1)
            return (-value if c == "-" else value), j
        if "a" <= c <= "z":
            return self.function(s, i, depth + 1)
        m = _NUMBER.match(s, i)
        if m is None:
            if c == "(":
                raise GCodeError("Comment between a word and its value")
            raise GCodeError(f"Bad number format at {s[i:i + 12]!r}")
        return _finite(float(m.group()), "Number"), m.end()

    def parameter(self, s: str, i: int, depth: int) -> tuple[float, int]:
        """``#n``, ``##n``, ``#[expr]`` or ``#<name>`` at ``s[i] == '#'``."""
        key, j = self.parameter_key(s, i, depth)
        if isinstance(key, str):
            return self.params.get_named(key), j
        return self.params.get_numbered(key), j

    def parameter_key(self, s: str, i: int, depth: int) -> tuple[int | str, int]:
        """The parameter named at ``s[i] == '#'``: an index 1..MAX_PARAMETER or a folded name."""
        i += 1
        if i < len(s) and s[i] == "<":
            return named_key(s, i)
        index, j = self._parameter_number(s, i, depth)
        if not 1 <= index <= MAX_PARAMETER:
            raise GCodeError(f"{PARAMETER_OUT_OF_RANGE}: #{index} (1 to {MAX_PARAMETER})")
        return index, j

    def _parameter_number(self, s: str, i: int, depth: int) -> tuple[int, int]:
        """The integer after ``#`` (LinuxCNC's ``read_integer_value``: within 0.0001 of an integer)."""
        value, j = self.real_value(s, i, depth + 1)
        index = round(value)
        if abs(value - index) > TOLERANCE_EQUAL:
            raise GCodeError(f"{NON_INTEGER}: parameter number #{value:g}")
        return int(index), j

    # --- expressions ------------------------------------------------------------------------------

    def expression(self, s: str, i: int, depth: int) -> tuple[float, int]:
        """``[ value (op value)* ]`` at ``s[i] == '['``, evaluated with LinuxCNC precedence."""
        if depth > self.max_depth:
            raise GCodeError(f"Expression nested too deeply (more than {self.max_depth} levels)")
        return bracketed(s, i, depth, self.real_value, self._combine)

    def _combine(self, op: str, a: float, b: float) -> float:
        return _apply(op, a, b, self.tolerant_order)

    def function(self, s: str, i: int, depth: int) -> tuple[float, int]:
        name, j = function_name(s, i)
        if name == "exists":
            return self._exists(s, j, depth)
        arg, j = self.expression(s, j, depth + 1)
        if name == "atan":
            x, j = self.expression(s, atan_divisor(s, j), depth + 1)
            return math.degrees(math.atan2(arg, x)), j
        return _unary(name, arg), j

    def _exists(self, s: str, j: int, depth: int) -> tuple[float, int]:
        """``EXISTS[#<name>]`` or ``EXISTS[#n]`` at ``s[j] == '['``, as LinuxCNC's ``read_unary`` /
        ``read_bracketed_parameter``: a name exists when defined (predefined ones always); a number
        ``n`` (any integer expression: ``#5``, ``#[2+3]``, ``##2``) when 1 <= n <= MAX_PARAMETER,
        whatever value the parameter holds. Neither reads the parameter's value."""
        name, end = exists_name(s, j)
        if name is not None:
            return (1.0 if self.params.exists(name) else 0.0), end
        index, k = self._parameter_number(s, j + 2, depth)
        return (1.0 if 1 <= index <= MAX_PARAMETER else 0.0), exists_close(s, k)


T = TypeVar("T")


def bracketed(s: str, i: int, depth: int, read: Callable[[str, int, int], tuple[T, int]],
              combine: Callable[[str, T, T], T]) -> tuple[T, int]:
    """``[ value (op value)* ]`` at ``s[i] == '['``: values from ``read``, reduced by ``combine`` in
    LinuxCNC's order (operators of one level left to right, each reduction as soon as the next
    operator shows it may be done, i.e. before the value after that operator is read)."""
    n = len(s)
    i += 1
    values: list[T] = []
    ops: list[str] = []
    while True:
        value, i = read(s, i, depth + 1)
        values.append(value)
        if i >= n:
            raise GCodeError("Unclosed expression: missing ']'")
        c = s[i]
        if c == "]":
            i += 1
            break
        op, i = _operator(s, i)
        prec = _PRECEDENCE[op]
        while ops and _PRECEDENCE[ops[-1]] >= prec:
            b = values.pop()
            values[-1] = combine(ops.pop(), values[-1], b)
        ops.append(op)
    while ops:
        b = values.pop()
        values[-1] = combine(ops.pop(), values[-1], b)
    return values[0], i


def _operator(s: str, i: int) -> tuple[str, int]:
    c = s[i]
    if c == "*":
        if s.startswith("**", i):
            return "**", i + 2
        return "*", i + 1
    if c in "/+-":
        return c, i + 1
    for op in _WORD_OPS:
        if s.startswith(op, i):
            return op, i + len(op)
    if c == "(":
        raise GCodeError("Unclosed expression: a comment before the closing ']'")
    raise GCodeError(f"Unknown operation at {s[i:i + 12]!r}")


def named_key(s: str, i: int) -> tuple[str, int]:
    """The folded name of ``#<name>`` with ``s[i] == '<'``, and where it ends."""
    end = s.find(">", i + 1)
    if end < 0:
        raise GCodeError("Named parameter not terminated by '>'")
    name = s[i + 1:end]
    if not name:
        raise GCodeError("Named parameter with an empty name")
    if "(" in name:
        raise GCodeError("Comment inside a parameter name")
    return name, end + 1


def function_name(s: str, i: int) -> tuple[str, int]:
    """The function named at ``s[i]`` and where its ``[`` is."""
    for name in _FUNCTIONS:
        if s.startswith(name, i):
            break
    else:
        raise GCodeError(f"Unknown function or word at {s[i:i + 12]!r}")
    j = i + len(name)
    if j >= len(s) or s[j] != "[":
        raise GCodeError(f"Left bracket missing after function name {name.upper()}")
    return name, j


def atan_divisor(s: str, j: int) -> int:
    """Where the ``[x]`` of ``ATAN[y]/[x]`` starts, ``j`` just after ``[y]``."""
    if j >= len(s) or s[j] != "/":
        raise GCodeError("Slash missing after first ATAN argument: ATAN[y]/[x]")
    if j + 1 >= len(s) or s[j + 1] != "[":
        raise GCodeError("Left bracket missing after slash with ATAN: ATAN[y]/[x]")
    return j + 1


def exists_name(s: str, j: int) -> tuple[str | None, int]:
    """For ``EXISTS[`` at ``s[j]``: the name of ``EXISTS[#<name>]`` and the end, or None (a number)."""
    if not s.startswith("#", j + 1):
        raise GCodeError("EXISTS takes one parameter: EXISTS[#<name>] or EXISTS[#n]")
    if s.startswith("#<", j + 1):
        end = s.find(">", j + 3)
        if end < 0 or end + 1 >= len(s) or s[end + 1] != "]":
            raise GCodeError("EXISTS takes one parameter: EXISTS[#<name>] or EXISTS[#n]")
        return s[j + 3:end], end + 2
    return None, j


def exists_close(s: str, k: int) -> int:
    if k >= len(s) or s[k] != "]":
        raise GCodeError("Expected ] reading bracketed parameter (EXISTS[#n] takes one parameter)")
    return k + 1


def _unary(name: str, x: float) -> float:
    if name == "abs":
        return abs(x)
    if name == "acos":
        if not -1.0 <= x <= 1.0:
            raise GCodeError(f"Argument to ACOS out of range: {x:g}")
        return math.degrees(math.acos(x))
    if name == "asin":
        if not -1.0 <= x <= 1.0:
            raise GCodeError(f"Argument to ASIN out of range: {x:g}")
        return math.degrees(math.asin(x))
    if name == "cos":
        return math.cos(math.radians(x))
    if name == "sin":
        return math.sin(math.radians(x))
    if name == "tan":
        return math.tan(math.radians(x))
    if name == "exp":
        try:
            return _finite(math.exp(x), "EXP result")
        except OverflowError:
            raise GCodeError("EXP result out of range (overflow)") from None
    if name == "fix":
        return float(math.floor(x))
    if name == "fup":
        return float(math.ceil(x))
    if name == "round":
        return float(math.floor(x + 0.5)) if x >= 0 else -float(math.floor(-x + 0.5))
    if name == "ln":
        if x <= 0.0:
            raise GCodeError(f"Zero or negative argument to LN: {x:g}")
        return math.log(x)
    if name == "sqrt":
        if x < 0.0:
            raise GCodeError(f"Negative argument to SQRT: {x:g}")
        return math.sqrt(x)
    raise GCodeError(f"Unknown function {name.upper()}")  # pragma: no cover (names are checked first)


def _apply(op: str, a: float, b: float, tolerant: bool = False) -> float:
    if op == "+":
        return _finite(a + b)
    if op == "-":
        return _finite(a - b)
    if op == "*":
        return _finite(a * b)
    if op == "/":
        if b == 0.0:
            raise GCodeError("Attempt to divide by zero")
        return _finite(a / b)
    if op == "mod":
        if b == 0.0:
            raise GCodeError("Attempt to divide by zero (MOD 0)")
        r = math.fmod(a, b)
        if r < 0.0:
            r += abs(b)
        return r
    if op == "**":
        if a < 0.0 and b != math.floor(b):
            raise GCodeError("Attempt to raise negative to non-integer power")
        if a == 0.0 and b < 0.0:
            raise GCodeError("Attempt to divide by zero (zero to a negative power)")
        try:
            return _finite(math.pow(a, b))
        except OverflowError:
            raise GCodeError("Result out of range (overflow)") from None
    if op == "eq":
        return 1.0 if abs(a - b) < TOLERANCE_EQUAL else 0.0
    if op == "ne":
        return 0.0 if abs(a - b) < TOLERANCE_EQUAL else 1.0
    if op == "gt":
        return 1.0 if a > b and (not tolerant or abs(a - b) >= TOLERANCE_EQUAL) else 0.0
    if op == "ge":
        return 1.0 if a >= b or abs(a - b) < (TOLERANCE_EQUAL if tolerant else TOLERANCE_GE_LE) else 0.0
    if op == "lt":
        return 1.0 if a < b and (not tolerant or abs(a - b) >= TOLERANCE_EQUAL) else 0.0
    if op == "le":
        return 1.0 if a <= b or abs(a - b) < (TOLERANCE_EQUAL if tolerant else TOLERANCE_GE_LE) else 0.0
    if op == "and":
        return 1.0 if (a != 0.0 and b != 0.0) else 0.0
    if op == "or":
        return 1.0 if (a != 0.0 or b != 0.0) else 0.0
    if op == "xor":
        return 1.0 if ((a != 0.0) != (b != 0.0)) else 0.0
    raise GCodeError(f"Unknown operation {op}")  # pragma: no cover
