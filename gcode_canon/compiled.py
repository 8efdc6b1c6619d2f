"""Lines read once, run many times: loops, subroutines and repeated CAM patterns re-read the same text.

:class:`LineCache` turns a line's text into its :class:`~gcode_canon.lexer.Block` faster the second
time:

* a line whose values cannot change (no ``#``: numbers, constant expressions and functions only)
  is parsed once and its Block reused (Blocks are not changed once parsed);
* a line with parameters is compiled, on its second reading, into its words and closures that
  evaluate its expressions: the text is not read again, the values are computed each time.

The reference stays :func:`~gcode_canon.lexer.parse_line`: the compiler mirrors its reading and the
:class:`~gcode_canon.expressions.ExpressionReader`'s (the same depth count, the same checks), and
any line it cannot compile without an error goes through ``parse_line`` every time, so a wrong
line's error (which one, in which order) is always the reader's own. Evaluated, the closures apply
the reader's own operations (``_apply``, ``_unary``) in the reader's order (left to right, each
reduction before the value after it), so the values and the errors of a run are the same too.

The cache holds at most ``size`` lines (cleared when full): its memory does not grow with the program.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable

from gcode_canon.errors import GCodeError
from gcode_canon.expressions import (
    _NUMBER,
    MAX_PARAMETER,
    NON_INTEGER,
    PARAMETER_OUT_OF_RANGE,
    TOLERANCE_EQUAL,
    ExpressionReader,
    _apply,
    _finite,
    _unary,
    atan_divisor,
    bracketed,
    exists_close,
    exists_name,
    function_name,
    named_key,
)
from gcode_canon.lexer import (
    _AXIS_WORDS,
    _NUMBER_TAIL,
    _PLAIN_NUMBER,
    WORD_LETTERS,
    Block,
    fold,
    g_code,
    m_code,
    parse_line,
    read_prefix,
)
from gcode_canon.messages import classify

Node = float | Callable[[], float]
"""A compiled value: a constant, or a function that computes it now."""

class _Marker:
    """A line cache entry that is not a line: no fast path."""

    fast = None


_SEEN = _Marker()  # read once: compiled when read again
_NOT_COMPILED = _Marker()  # the compiler refused it: parse_line every time
FAST_SEEN = _Marker()
"""A line the program loop ran once by its pattern (``FAST_LINE``), without parsing it: parsed when
read again, and kept with its fast path (:attr:`LineCache.entries`)."""
_G, _M, _WORD, _ASSIGN = range(4)


_Op = Callable[[float, float], float]


def _right_constant(fn: _Op, a: Callable[[], float], b: float) -> Callable[[], float]:
    def node() -> float:
        v = fn(a(), b)
        return v if v - v == 0.0 else _finite(v)  # v - v is 0 for a finite v only: _finite's error
    return node


def _left_constant(fn: _Op, a: float, b: Callable[[], float]) -> Callable[[], float]:
    def node() -> float:
        v = fn(a, b())
        return v if v - v == 0.0 else _finite(v)
    return node


def _neither_constant(fn: _Op, a: Callable[[], float], b: Callable[[], float]) -> Callable[[], float]:
    def node() -> float:
        v = fn(a(), b())
        return v if v - v == 0.0 else _finite(v)
    return node


_ARITHMETIC = {"+": operator.add, "-": operator.sub, "*": operator.mul}
"""``_apply``'s + - *, whose only check is the result's being finite."""

_radians = math.radians
_DIRECT_FUNCTIONS: dict[str, Callable[[Callable[[], float]], Callable[[], float]]] = {
    # _unary's own expressions for these, without its chain of name tests
    "sin": lambda arg: lambda: math.sin(_radians(arg())),
    "cos": lambda arg: lambda: math.cos(_radians(arg())),
    "tan": lambda arg: lambda: math.tan(_radians(arg())),
    "abs": lambda arg: lambda: abs(arg()),
}


class _Compiler:
    """:class:`~gcode_canon.expressions.ExpressionReader`'s grammar, producing nodes."""

    __slots__ = ("max_depth", "params", "tolerant")

    def __init__(self, reader: ExpressionReader) -> None:
        self.params = reader.params
        self.max_depth = reader.max_depth
        self.tolerant = reader.tolerant_order

    def value(self, s: str, i: int, depth: int = 0) -> tuple[Node, int]:
        if depth > self.max_depth:
            raise GCodeError("nested too deeply")
        if i >= len(s):
            raise GCodeError("Missing value at end of line")
        c = s[i]
        if c == "[":
            return self.expression(s, i, depth + 1)
        if c == "#":
            return self.parameter(s, i, depth + 1)
        if c in "+-" and i + 1 < len(s) and s[i + 1] not in "0123456789.":
            node, j = self.value(s, i + 1, depth + 1)
            if c == "+":
                return node, j
            if callable(node):
                return (lambda: -node()), j
            return -node, j
        if "a" <= c <= "z":
            return self.function(s, i, depth + 1)
        m = _NUMBER.match(s, i)
        if m is None:
            raise GCodeError("bad number")
        return _finite(float(m.group()), "Number"), m.end()

    def parameter(self, s: str, i: int, depth: int) -> tuple[Node, int]:
        key, j = self.parameter_key(s, i, depth)
        params = self.params
        if isinstance(key, str):
            get_named = params.get_named
            return (lambda: get_named(key)), j
        get_numbered = params.get_numbered
        if callable(key):
            return (lambda: get_numbered(key())), j
        return (lambda: get_numbered(key)), j

    def parameter_key(self, s: str, i: int, depth: int) -> tuple[str | int | Callable[[], int], int]:
        i += 1
        if i < len(s) and s[i] == "<":
            return named_key(s, i)
        index, j = self._parameter_number(s, i, depth)
        if callable(index):
            number = index

            def checked() -> int:
                n = number()
                if not 1 <= n <= MAX_PARAMETER:
                    raise GCodeError(f"{PARAMETER_OUT_OF_RANGE}: #{n} (1 to {MAX_PARAMETER})")
                return n

            return checked, j
        if not 1 <= index <= MAX_PARAMETER:
            raise GCodeError("out of range")
        return index, j

    def _parameter_number(self, s: str, i: int, depth: int) -> tuple[int | Callable[[], int], int]:
        node, j = self.value(s, i, depth + 1)
        if callable(node):
            def number() -> int:
                value = node()
                index = round(value)
                if abs(value - index) > TOLERANCE_EQUAL:
                    raise GCodeError(f"{NON_INTEGER}: parameter number #{value:g}")
                return int(index)

            return number, j
        index = round(node)
        if abs(node - index) > TOLERANCE_EQUAL:
            raise GCodeError("non-integer")
        return int(index), j

    def expression(self, s: str, i: int, depth: int) -> tuple[Node, int]:
        if depth > self.max_depth:
            raise GCodeError("nested too deeply")
        return bracketed(s, i, depth, self.value, self._combine)

    def _combine(self, op: str, a: Node, b: Node) -> Node:
        tolerant = self.tolerant
        if not callable(a) and not callable(b):
            return _apply(op, a, b, tolerant)  # an error here: the line is not compiled
        fn = _ARITHMETIC.get(op)
        if fn is not None:  # + - * with the finite check inline, a constant side read as it is
            if not callable(b):
                return _right_constant(fn, a, b)  # type: ignore[arg-type]
            if not callable(a):
                return _left_constant(fn, a, b)
            return _neither_constant(fn, a, b)
        fa = a if callable(a) else (lambda: a)
        fb = b if callable(b) else (lambda: b)
        return lambda: _apply(op, fa(), fb(), tolerant)

    def function(self, s: str, i: int, depth: int) -> tuple[Node, int]:
        name, j = function_name(s, i)
        if name == "exists":
            return self._exists(s, j, depth)
        arg, j = self.expression(s, j, depth + 1)
        if name == "atan":
            x, j = self.expression(s, atan_divisor(s, j), depth + 1)
            if not callable(arg) and not callable(x):
                return math.degrees(math.atan2(arg, x)), j
            fy = arg if callable(arg) else (lambda: arg)
            fx = x if callable(x) else (lambda: x)
            return (lambda: math.degrees(math.atan2(fy(), fx()))), j
        if not callable(arg):
            return _unary(name, arg), j
        direct = _DIRECT_FUNCTIONS.get(name)
        if direct is not None:
            return direct(arg), j
        return (lambda: _unary(name, arg())), j

    def _exists(self, s: str, j: int, depth: int) -> tuple[Node, int]:
        name, end = exists_name(s, j)
        if name is not None:
            exists = self.params.exists
            return (lambda: 1.0 if exists(name) else 0.0), end
        index, k = self._parameter_number(s, j + 2, depth)
        k = exists_close(s, k)
        if callable(index):
            number = index
            return (lambda: 1.0 if 1 <= number() <= MAX_PARAMETER else 0.0), k
        return (1.0 if 1 <= index <= MAX_PARAMETER else 0.0), k


_PLAIN_WORDS = frozenset("xyzf")
_ARC_WORDS = frozenset("xyzijkrf")


def plain_shape(g: list[int], m: list[int], letters, comments: list[str], deleted: bool,
                line_number: float | None) -> tuple[int | None, str | None] | None:
    """:attr:`Block.plain` of a line with these codes, word letters and comments."""
    if m or deleted or line_number is not None or len(g) > 1:
        return None
    if g and g[0] in (20, 30):
        if not _ARC_WORDS.issuperset(letters):
            return None
    elif (g and g[0] not in (0, 10)) or not _PLAIN_WORDS.issuperset(letters):
        return None
    comment = None
    if comments:
        keyword, comment = classify(comments[-1])
        if keyword:
            return None
    return (g[0] if g else None), comment


def _with_plain(block: Block) -> Block:
    if block.o_text is None and not block.assigns:
        block.plain = plain_shape(block.g, block.m, block.words, block.comments, block.deleted,
                                  block.line_number)
    return block


class CompiledLine:
    """One line's words in order, each a constant or a closure; :meth:`run` makes its Block."""

    __slots__ = ("assigns", "axes", "comments", "deleted", "fast", "g", "items", "line_number", "m", "plain",
                 "quick", "shape", "simple", "static", "values")

    def __init__(self, raw: str, compiler: _Compiler) -> None:
        s, self.comments = fold(raw)
        self.deleted, self.line_number, i = read_prefix(s)
        n = len(s)
        if i < n and s[i] == "o":
            raise GCodeError("o-word lines are cached as Blocks")
        items: list[tuple[int, str, Node, object]] = []
        letters: set[str] = set()
        m_count = 0
        while i < n:
            c = s[i]
            if c == "(":
                i += 1
            elif c == "#":
                key, i = compiler.parameter_key(s, i, 0)
                if i >= n or s[i] != "=":
                    raise GCodeError("equal sign missing")
                node, i = compiler.value(s, i + 1)
                items.append((_ASSIGN, "", node, key))
            elif c == "g":
                node, i = compiler.value(s, i + 1)
                items.append((_G, "", node, None))
            elif c == "m":
                node, i = compiler.value(s, i + 1)
                m_count += 1
                if m_count > 4:
                    raise GCodeError("too many M codes")
                items.append((_M, "", node, None))
            elif c in WORD_LETTERS:
                if c in letters:
                    raise GCodeError("repeated word")
                letters.add(c)
                m = _PLAIN_NUMBER(s, i + 1)
                if m is not None and (m.end() >= n or s[m.end()] not in _NUMBER_TAIL):
                    value = float(m.group())
                    if value - value != 0.0:
                        raise GCodeError("number out of range")
                    node, i = value, m.end()
                else:
                    node, i = compiler.value(s, i + 1)
                items.append((_WORD, c, node, None))
            else:
                raise GCodeError("bad character")
        self.items = tuple(items)
        self.shape = None  # Block.shape, the same for every run when the G and M codes are constants
        self.static = all(kind in (_WORD, _ASSIGN) or not callable(node) for kind, _, node, _ in items)
        if self.static:
            # constant codes read now (an error here: not compiled, parse_line says it in its place);
            # a run evaluates only the words and settings, in their order on the line
            self.g = [g_code(node) for kind, _, node, _ in items if kind == _G]  # type: ignore[arg-type]
            self.m = [m_code(node) for kind, _, node, _ in items if kind == _M]  # type: ignore[arg-type]
            self.values = tuple((letter, node) for kind, letter, node, _ in items if kind == _WORD)
            self.axes = any(letter in _AXIS_WORDS for letter, _ in self.values)
            self.assigns = tuple((key, node) for kind, _, node, key in items if kind == _ASSIGN)
        self.simple = self.static and not (self.assigns and self.values)  # both: the general run
        self.plain = None
        if all(kind == _WORD or (kind == _G and not callable(node)) for kind, _, node, _ in items):
            self.plain = plain_shape([g_code(node) for kind, _, node, _ in items if kind == _G],  # type: ignore[arg-type]
                                     [], [letter for kind, letter, _, _ in items if kind == _WORD],
                                     self.comments, self.deleted, self.line_number)
        self.quick: Callable[[], object] | None = None
        """The program loop's shortcut (``_quick_line``), made of this line's own nodes: for a straight
        fast-path line (:attr:`plain`, no G2/G3) a function giving its X Y Z F values (None where a word
        is absent); for a line of parameter settings alone, the settings as :meth:`run`'s Block holds
        them. Both evaluate in the line's order, as :meth:`run` does."""
        self.fast = None
        """The program loop's run of this line (:attr:`Block.fast`), set by the line cache."""
        if self.plain is not None and self.plain[0] in (None, 0, 10):
            self.quick = _values_function(self.values)
        elif (self.static and self.assigns and not self.values and not self.g and not self.m
              and not self.comments and not self.deleted):
            self.quick = _assigns_function(self.assigns)

    def run(self) -> Block:
        """The Block ``parse_line`` would give now (values from the parameters in force)."""
        if self.simple:
            return self._run_simple()
        return self._run_items()

    def _run_simple(self) -> Block:
        """Constant codes (shared by every run: a Block is never changed), then the words' values or
        the parameter settings."""
        block = self._new_block()
        block.g = self.g
        block.m = self.m
        block.axes = self.axes
        words = block.words
        for letter, node in self.values:
            words[letter] = node() if callable(node) else node
        if self.assigns:
            assigns = block.assigns
            for key, node in self.assigns:  # the key (#[...] evaluated) before the value, as parse_line
                key = key() if callable(key) else key
                assigns.append((key, node() if callable(node) else node))
        return block

    def _new_block(self) -> Block:
        """A Block with what every run of this line shares: comments, block delete, N number, the fast
        path's shape, and the line's shape once known (else, constant codes, this line to learn it)."""
        block = Block()
        block.comments = self.comments
        block.deleted = self.deleted
        block.line_number = self.line_number
        block.plain = self.plain
        if self.shape is not None:
            block.shape = self.shape
        elif self.static:
            block.origin = self
        return block

    def _run_items(self) -> Block:
        block = self._new_block()
        words = block.words
        for kind, letter, node, key in self.items:
            value = node() if callable(node) else node
            if kind == _WORD:
                words[letter] = value
                if letter in _AXIS_WORDS:
                    block.axes = True
            elif kind == _ASSIGN:
                # parse_line reads the key (evaluating #[...] / ##n) before the value
                block.assigns.append((key() if callable(key) else key, value))  # type: ignore[operator]
            elif kind == _G:
                block.g.append(g_code(value))
            else:
                block.m.append(m_code(value))
        return block


_FACTORIES: dict[str, Callable[..., Callable[[], object]]] = {}
"""Generated factories by their source: a line's shortcut is made by calling the factory of its
shape (which words, which of them computed) with its own values, so ``compile`` runs once a shape."""


def _generated(names: list[str], body: str, values: list[object]) -> Callable[[], object]:
    """``quick()`` with ``body`` (indented source of its statements) over ``names`` bound to
    ``values`` (closure cells, as fast to read as locals)."""
    source = f"def make({', '.join(names)}):\n def quick():\n{body} return quick\n"
    make = _FACTORIES.get(source)
    if make is None:
        namespace: dict[str, object] = {}
        exec(compile(source, "<compiled line>", "exec"), namespace)
        make = _FACTORIES[source] = namespace["make"]  # type: ignore[assignment]
    return make(*values)


def _values_function(values: tuple[tuple[str, Node], ...]) -> Callable[[], object]:
    """``() -> (x, y, z, f)`` for a straight fast-path line: the words' values evaluated in the
    line's order, None for an absent word."""
    names, steps, slots = [], [], dict.fromkeys("xyzf", "None")
    for k, (letter, node) in enumerate(values):
        names.append(f"n{k}")
        if callable(node):
            steps.append(f"  v{k} = n{k}()\n")
            slots[letter] = f"v{k}"
        else:
            slots[letter] = f"n{k}"
    body = "".join(steps) + f"  return ({slots['x']}, {slots['y']}, {slots['z']}, {slots['f']})\n"
    return _generated(names, body, [node for _, node in values])


def _assigns_function(assigns: tuple[tuple[object, Node], ...]) -> Callable[[], object]:
    """``() -> [(key, value), ...]`` for a line of parameter settings alone: each key (``#[...]``
    evaluated) before its value, in the line's order, as ``parse_line`` reads them."""
    names: list[str] = []
    bound: list[object] = []
    pairs = []
    for k, (key, node) in enumerate(assigns):
        names += [f"k{k}", f"n{k}"]
        bound += [key, node]
        pairs.append(f"(k{k}{'()' if callable(key) else ''}, n{k}{'()' if callable(node) else ''})")
    return _generated(names, f"  return [{', '.join(pairs)}]\n", bound)


FastFor = Callable[[Block | CompiledLine], Callable[[], object] | None]
"""The program loop's maker of a kept line's fast path (:attr:`LineCache.fast_for`)."""


class LineCache:
    """Text of a line to its Block (module docstring)."""

    __slots__ = ("_compiler", "_entries", "fast_for", "reader", "size")

    def __init__(self, reader: ExpressionReader, size: int = 4096, fast_for: FastFor | None = None) -> None:
        self.reader = reader
        self.size = size
        self.fast_for = fast_for
        """What sets ``fast`` on the lines kept (:attr:`Block.fast`): a Block of the fast path's shape
        (:attr:`Block.plain`) and every compiled line get ``fast_for(line)``; None: none does."""
        self._entries: dict[str, object] = {}
        self._compiler: _Compiler | None = None

    @property
    def known(self) -> Callable[[str], object]:
        """``known(raw)``: what the cache holds for a line text (a Block, a :class:`CompiledLine`, a
        marker) or None; the function stays valid as the cache is cleared."""
        return self._entries.get

    @property
    def entries(self) -> dict[str, object]:
        """The lines kept, by their text: the program loop notes there the lines it ran by its pattern
        (``entries[raw] = FAST_SEEN``, after clearing them when they number :attr:`size`), which
        :meth:`parse` reads as lines not read yet. The same dict for the cache's life (cleared, not
        replaced)."""
        return self._entries

    def parse(self, raw: str) -> Block:
        entry = self._entries.get(raw)
        if entry is None or entry is FAST_SEEN:
            block = parse_line(raw, self.reader)  # errors: the reader's, and nothing is kept
            entries = self._entries
            if len(entries) >= self.size:
                entries.clear()
            if block.o_text is not None or "#" not in raw:
                entries[raw] = _with_plain(block)
                if block.plain is not None and self.fast_for is not None:
                    block.fast = self.fast_for(block)
            else:
                entries[raw] = _SEEN
            return block
        if entry.__class__ is Block:
            return entry  # type: ignore[return-value]
        if entry.__class__ is CompiledLine:
            return entry.run()  # type: ignore[attr-defined]
        if entry is _SEEN:
            if self._compiler is None:
                self._compiler = _Compiler(self.reader)
            try:
                entry = CompiledLine(raw, self._compiler)
            except (GCodeError, RecursionError):
                entry = _NOT_COMPILED
            else:
                if self.fast_for is not None:
                    entry.fast = self.fast_for(entry)
            self._entries[raw] = entry
            if entry is not _NOT_COMPILED:
                return entry.run()  # type: ignore[attr-defined]
        return parse_line(raw, self.reader)
