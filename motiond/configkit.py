"""Small helpers to read a TOML machine file with errors that name the file and the key.

Each layer keeps its own typed configuration dataclasses; the ``motiond.config*`` modules read the
TOML tables into them with these helpers, so that every mistake reads like
``machine.toml: axes.x.max_velocity: must be > 0, got -5``.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")

_MISSING = object()


class ConfigError(ValueError):
    """A problem in a configuration file: which file, which key, what is wrong."""

    def __init__(self, file: str, key: str, message: str) -> None:
        self.file = file
        self.key = key
        self.message = message
        where = f"{file}: " if file else ""
        super().__init__(f"{where}{key + ': ' if key else ''}{message}")


class ConfigErrors(ConfigError):
    """Several problems in one file (``canon config check`` reports them all): one line each."""

    def __init__(self, errors: list[ConfigError]) -> None:
        self.errors = errors
        first = errors[0]
        super().__init__(first.file, first.key, first.message)

    def __str__(self) -> str:
        return "\n".join(str(e) for e in self.errors)


# While a reader runs under collect_errors(), a bad value of an optional key is recorded here and its
# default used, so that the reader goes on to the section's other keys: ``canon config check`` then
# names every bad key of a section at once. Required keys still raise (there is nothing to go on with).
_collected: contextvars.ContextVar[list[ConfigError] | None] = contextvars.ContextVar("_collected",
                                                                                        default=None)


@contextlib.contextmanager
def collect_errors() -> Iterator[list[ConfigError]]:
    """Within the block, :meth:`Table.get` records a bad optional value and returns its default, and
    :meth:`Table.check_unknown` records every unknown key; the list holds what was recorded."""
    errors: list[ConfigError] = []
    token = _collected.set(errors)
    try:
        yield errors
    finally:
        _collected.reset(token)


def special_file(mode: int) -> str | None:
    """What a file of ``os.stat`` mode ``mode`` is when it is neither a regular file nor a directory
    ("a device", "a pipe" ...: reading one may never end), else None."""
    import stat

    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return None
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    return "a pipe" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode) else "special"


def load_toml(path: str | Path) -> dict[str, Any]:
    """Read a TOML file; syntax errors become :class:`ConfigError` with the line TOML reports."""
    import tomllib  # here, not at the top: canon check without a machine file reads no TOML

    p = Path(path)
    try:
        kind = special_file(p.stat().st_mode)  # /dev/zero or a pipe: read() would never end
        if kind is not None:
            raise ConfigError(str(p), "", f"is {kind} file, not a machine file (a regular file is needed)")
        with p.open("rb") as fh:
            data = fh.read()
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as exc:  # TOML is UTF-8; tomllib would raise this bare
            line = data.count(b"\n", 0, exc.start) + 1
            raise ConfigError(str(p), "", f"line {line}: byte 0x{data[exc.start]:02x} is not UTF-8 text "
                                          "(a TOML file is UTF-8)") from None
        return tomllib.loads(text)
    except FileNotFoundError:
        raise ConfigError(str(p), "", "no such file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(p), "", f"not valid TOML: {exc}") from None
    except OSError as exc:
        raise ConfigError(str(p), "", f"cannot read: {exc.strerror}") from None


class Table:
    """A TOML table with its dotted path, for reading values with precise errors.

    Keys that are read are remembered; :meth:`check_unknown` then reports any key nobody read, which
    catches typos such as ``max_velocty`` instead of silently using a default.
    """

    def __init__(self, data: dict[str, Any], file: str = "", path: str = "") -> None:
        if not isinstance(data, dict):
            raise ConfigError(file, path, f"must be a table, got {type(data).__name__}")
        self.data = data
        self.file = file
        self.path = path
        self._seen: set[str] = set()

    def key(self, name: str) -> str:
        return f"{self.path}.{name}" if self.path else name

    def error(self, name: str, message: str) -> ConfigError:
        return ConfigError(self.file, self.key(name), message)

    def __contains__(self, name: str) -> bool:
        return name in self.data

    def get(self, name: str, kind: type[T], default: Any = _MISSING,
            check: Callable[[T], str | None] | None = None) -> T:
        """Value of ``name`` as ``kind`` (int accepted for float); ``check`` returns a complaint.

        Under :func:`collect_errors` a bad value of a key with a default is recorded and the default
        returned."""
        self._seen.add(name)
        if name not in self.data:
            if default is _MISSING:
                raise self.error(name, "missing (required)")
            return default
        complaint = self._complaint(name, kind, check)
        if complaint is None:
            value = self.data[name]
            return float(value) if kind is float else value  # type: ignore[return-value]
        errors = _collected.get()
        if errors is None or default is _MISSING:
            raise self.error(name, complaint)
        errors.append(self.error(name, complaint))
        return default

    def _complaint(self, name: str, kind: type, check: Callable[[Any], str | None] | None) -> str | None:
        value = self.data[name]
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or (kind is not bool and isinstance(value, bool)):
            return f"must be {kind.__name__}, got {type(value).__name__} {value!r}"
        if kind is float and not math.isfinite(value):
            return f"must be a finite number, got {value!r}"
        if check is not None:
            complaint = check(value)
            if complaint:
                return f"{complaint}, got {value!r}"
        return None

    def table(self, name: str, required: bool = False) -> Table:
        self._seen.add(name)
        if name not in self.data:
            if required:
                raise self.error(name, "missing table (required)")
            return Table({}, self.file, self.key(name))
        return Table(self.data[name], self.file, self.key(name))

    def tables(self, name: str) -> Iterator[tuple[str, Table]]:
        """Sub-tables of table ``name`` (``[axes.x]``, ``[axes.y]`` ...) in file order."""
        outer = self.table(name)
        for sub in list(outer.data):
            yield sub, outer.table(sub)

    def array_of_tables(self, name: str) -> list[Table]:
        self._seen.add(name)
        items = self.data.get(name, [])
        if not isinstance(items, list):
            raise self.error(name, "must be an array of tables ([[...]])")
        return [Table(item, self.file, f"{self.key(name)}[{i}]") for i, item in enumerate(items)]

    def check_unknown(self) -> None:
        """Any key nobody read is a mistake (under :func:`collect_errors`, each one is recorded)."""
        unknown = sorted(set(self.data) - self._seen)
        if not unknown:
            return
        errors = _collected.get()
        if errors is None:
            raise self.error(unknown[0], "unknown key (misspelt?)")
        errors.extend(self.error(k, "unknown key (misspelt?)") for k in unknown)


def positive(v: float) -> str | None:
    return None if v > 0 else "must be > 0"


def non_negative(v: float) -> str | None:
    return None if v >= 0 else "must be >= 0"


def one_of(*choices: Any) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        return None if v in choices else f"must be one of {', '.join(map(str, choices))}"

    return check


def in_range(lo: float, hi: float) -> Callable[[float], str | None]:
    def check(v: float) -> str | None:
        return None if lo <= v <= hi else f"must be between {lo} and {hi}"

    return check
