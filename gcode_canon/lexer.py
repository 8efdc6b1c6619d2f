"""One line of text to a :class:`Block`: words, parameter settings and comments.

The line is folded as LinuxCNC's reader does: comments are cut out (each leaves a ``(`` marker, so a
comment between a letter and its value is still an error), spaces and tabs are removed and the rest is
lower-cased. Values are evaluated as they are read (:mod:`gcode_canon.expressions`).

:data:`FAST_LINE` is the fast path's pattern: a line holding nothing but an optional ``G0``/``G1`` and
literal X, Y, Z, F words in that order. The interpreter uses it to skip the general machinery for the
bulk of CAM output; anything else goes through :func:`parse_line`.
"""

from __future__ import annotations

import re

from gcode_canon.errors import GCodeError
from gcode_canon.expressions import TOLERANCE_EQUAL, ExpressionReader

_NUM = r"([-+]?+(?:[0-9]++(?:\.[0-9]*+)?+|\.[0-9]++))"  # possessive: no backtracking on long lines
FAST_LINE = re.compile(
    r"[ \t]*+(?>[Gg]0?([01])(?![0-9.])[ \t]*+|)"
    rf"(?>[Xx]{_NUM}[ \t]*+|)(?>[Yy]{_NUM}[ \t]*+|)(?>[Zz]{_NUM}[ \t]*+|)(?>[Ff]{_NUM}[ \t]*+|)\Z"
)
"""Groups: motion (0/1 or None), x, y, z, f (text of the number or None).

Each optional word is an atomic group with an empty alternative (``(?>...|)``), not ``(?:...)?``:
the same matches (``tests/test_interp_lexer.py`` compares them on random lines), in about 55 % of
the time on a CAM line (Python's ``re`` runs a ``?`` group through its general repeat), and no going
back into a word once read when the line does not match (250 spaces and a letter: 1 µs, not 45)."""

_COMMENT_START = re.compile(r"[(;]")
_PLAIN_NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)").match
_NUMBER_TAIL = frozenset("0123456789.")
_BAD_CONTROL = re.compile(r"[\x00-\x08\x0a-\x1f\x7f]")
_FOLD = str.maketrans("", "", " \t\r")
_LINE_NUMBER = re.compile(r"n[0-9]+(?:\.[0-9]+)?")

AXIS_LETTERS = "xyzabcuvw"
WORD_LETTERS = frozenset("abcdefhijklpqrstuvwxyz@^")
_AXIS_WORDS = frozenset("xyzabcuvw@^")
"""Letters that take a value once per line (G and M may repeat, N only first, O is flow control)."""


class Block:
    """What one line says, before any of it is executed."""

    __slots__ = ("assigns", "axes", "comments", "deleted", "fast", "g", "line_number", "m", "o_text",
                 "origin", "plain", "shape", "words")

    def __init__(self) -> None:
        self.g: list[int] = []  # G codes times ten: G38.2 -> 382
        self.m: list[int] = []
        self.words: dict[str, float] = {}
        self.assigns: list[tuple[int | str, float]] = []
        self.comments: list[str] = []
        self.line_number: float | None = None
        self.deleted = False
        self.o_text: str | None = None  # the folded line when it starts with an O word (flow control)
        self.axes = False  # any of X Y Z A B C U V W @ ^
        self.plain: tuple[int | None, str | None] | None = None
        """Set by :mod:`gcode_canon.compiled` on a line read again that the fast path can run (an
        optional G0/G1 with X Y Z F words only, or G2/G3 with X Y Z I J K R F words; no active
        comment): (motion code or None, the text of its comment or None); None: the general path."""
        self.fast = None
        """For a Block the line cache keeps: the program loop's run of this line on the fast path (no
        arguments; the commands, or None for the general path), or None (``LineCache``'s ``fast_for``)."""
        self.shape: tuple | None = None
        """What its execution depends on besides its values (the interpreter's ``_shape``), kept
        with the line once computed; None: not yet."""
        self.origin = None
        """The compiled line that made this Block, where its shape is kept (None: the Block itself)."""

    def keep_shape(self, shape: tuple) -> None:
        self.shape = shape
        if self.origin is not None:
            self.origin.shape = shape

    def has_axes(self) -> bool:
        return self.axes

    def take(self, letter: str) -> float | None:
        """The value of ``letter``, or None."""
        return self.words.get(letter)


def split_comments(raw: str) -> tuple[str, list[str]]:
    """The code part of ``raw`` (comments replaced by ``(``) and the comment texts, in order."""
    code: list[str] = []
    comments: list[str] = []
    i = 0
    n = len(raw)
    while i < n:
        m = _COMMENT_START.search(raw, i)
        if m is None:
            code.append(raw[i:])
            break
        code.append(raw[i:m.start()])
        if m.group() == ";":
            comments.append(raw[m.end():].strip())  # as LinuxCNC: "; note" is the comment "note"
            code.append("(")
            break
        end = raw.find(")", m.end())
        if end < 0:
            raise GCodeError("Unclosed comment found")
        body = raw[m.end():end]
        if "(" in body:
            raise GCodeError("Nested comment found")
        comments.append(body)
        code.append("(")
        i = end + 1
    return "".join(code), comments


def check_characters(raw: str) -> None:
    """Control characters (NUL ...) anywhere, or bytes that were not UTF-8, are refused."""
    m = _BAD_CONTROL.search(raw)
    if m is not None:
        raise GCodeError(f"Bad character used: control character {ord(m.group()):#04x}")
    if not raw.isascii():
        for ch in raw:
            if "\udc80" <= ch <= "\udcff":
                raise GCodeError("Line is not valid UTF-8 text")


def fold(raw: str) -> tuple[str, list[str]]:
    """The line as the reader reads it (comments cut to ``(`` markers, no spaces, lower case) and its
    comments."""
    check_characters(raw)
    if "(" in raw or ";" in raw:
        code, comments = split_comments(raw)
    else:
        code, comments = raw, []
    s = code.translate(_FOLD)
    if not s.isascii():
        bad = next(ch for ch in s if not ch.isascii())
        raise GCodeError(f"Bad character used: {bad!r} (only comments may hold non-ASCII text)")
    return s.lower(), comments


def read_prefix(s: str) -> tuple[bool, float | None, int]:
    """Block delete ``/`` and the N word at the start of a folded line: (deleted, number, where next)."""
    deleted = False
    number = None
    n = len(s)
    i = 0
    if i < n and s[i] == "/":
        deleted = True
        i += 1
    if i < n and s[i] == "n":
        m = _LINE_NUMBER.match(s, i)
        if m is None:
            raise GCodeError("Bad format of line number (N word)")
        number = float(m.group()[1:])
        i = m.end()
    return deleted, number, i


def g_code(value: float) -> int:
    """A G word's value as its code times ten (G38.2 -> 382), or the reader's error."""
    tenths = value * 10.0
    if tenths - tenths != 0.0:  # G1e308: no integer to round to
        raise GCodeError(f"G code out of range: G{value:g}")
    code10 = round(tenths)
    if abs(tenths - code10) > TOLERANCE_EQUAL * 10.0:
        raise GCodeError(f"Unknown G code used: G{value:g}")
    if not 0 <= code10 < 1000:
        raise GCodeError(f"G code out of range: G{value:g}")
    return int(code10)


def m_code(value: float) -> int:
    mcode = round(value)
    if abs(value - mcode) > TOLERANCE_EQUAL:
        raise GCodeError(f"Unknown M code used: M{value:g}")
    if not 0 <= mcode <= 199:
        raise GCodeError(f"M code out of range: M{value:g}")
    return int(mcode)


def parse_line(raw: str, reader: ExpressionReader) -> Block:
    """Parse (and evaluate the values of) one line without its end-of-line characters."""
    s, comments = fold(raw)
    block = Block()
    block.comments = comments
    block.deleted, block.line_number, i = read_prefix(s)
    n = len(s)
    if i < n and s[i] == "o":
        block.o_text = s[i:]
        return block
    words = block.words
    while i < n:
        c = s[i]
        if c == "(":
            i += 1
        elif c == "#":
            key, i = reader.parameter_key(s, i, 0)
            if i >= n or s[i] != "=":
                raise GCodeError("Equal sign missing in parameter setting")
            value, i = reader.real_value(s, i + 1)
            block.assigns.append((key, value))
        elif c == "g":
            value, i = reader.real_value(s, i + 1)
            block.g.append(g_code(value))
        elif c == "m":
            value, i = reader.real_value(s, i + 1)
            mcode = m_code(value)
            if len(block.m) == 4:
                raise GCodeError("Too many M codes on line (at most four)")
            block.m.append(mcode)
        elif c in WORD_LETTERS:
            if c in words:
                raise GCodeError(f"Multiple {c.upper()} words on one line")
            m = _PLAIN_NUMBER(s, i + 1)  # the common case, a literal number: no expression reader
            if m is not None and (m.end() >= n or s[m.end()] not in _NUMBER_TAIL):
                value = float(m.group())
                if value - value != 0.0:  # inf: the reader reports it
                    value, i = reader.real_value(s, i + 1)
                else:
                    i = m.end()
            else:
                value, i = reader.real_value(s, i + 1)
            words[c] = value
            if c in _AXIS_WORDS:
                block.axes = True
        elif c == "n":
            raise GCodeError("Line number (N word) must come first on the line")
        elif c == "o":
            raise GCodeError("O word (flow control) must come first on the line")
        elif c == "/":
            raise GCodeError("Block delete '/' must be the first character of the line")
        else:
            raise GCodeError(f"Bad character used: {c!r}")
    return block
