"""Numbered and named parameters: storage, scopes, read-only checks, predefined names.

* Numbered #1-#5601 live in one flat list (index 0 unused): LinuxCNC's range (its array has
  RS274NGC_MAX_PARAMETERS = 5602 entries from 0). #1-#30 will become per-call locals with the o-word
  issue (:meth:`Parameters.push_scope`); everything else is global.
* Named ``#<name>`` is local to the current scope, ``#<_name>`` global. Names arrive folded (lower
  case, no spaces) from the lexer.
* Predefined names (``#<_x>``, ``#<_abs_x>``, ``#<_metric>`` ...) and a few numbered ones (#5021-#5029,
  the machine position; #5420-#5428, the current position) are computed on read by getters the
  interpreter registers; they and the tool parameters #5400-#5413 are read-only to programs. The
  interpreter writes system values with :meth:`set_system`.
* ``#<_ini[section]name>`` reads a number of the machine's configuration (LinuxCNC reads its INI file;
  canon the machine file's TOML tables, :attr:`Parameters.ini`); read-only.
"""

from __future__ import annotations

from collections.abc import Callable

from gcode_canon.errors import GCodeError
from gcode_canon.expressions import MAX_PARAMETER

READ_ONLY_NUMBERED = frozenset([*range(5021, 5030), *range(5400, 5414), *range(5420, 5429)])
"""Numbered parameters a program may read but not assign (LinuxCNC's ``Interp::readonly_parameters``,
``interp_array.cc``: machine position #5021-5029, tool #5400-5413, current position #5420-5428)."""

Getter = Callable[[], float]

INI_PREFIX = "_ini["
"""``#<_ini[section]name>``: a value of the machine's configuration file (LinuxCNC's INI variables)."""


class Parameters:
    __slots__ = ("_globals", "_locals", "dynamic_numbered", "ini", "numbered", "predefined")

    def __init__(self) -> None:
        self.numbered: list[float] = [0.0] * (MAX_PARAMETER + 1)
        self._globals: dict[str, float] = {}
        self._locals: list[dict[str, float]] = [{}]
        self.predefined: dict[str, Getter] = {}
        self.dynamic_numbered: dict[int, Getter] = {}
        #: ``#<_ini[section]name>`` values, keyed "section]name" (InterpreterSettings.ini_values)
        self.ini: dict[str, float] = {}
        self.numbered[5599] = 1.0  # (DEBUG,...) output enabled

    # --- reading ----------------------------------------------------------------------------------

    def get_numbered(self, index: int) -> float:
        getter = self.dynamic_numbered.get(index)
        if getter is not None:
            return getter()
        return self.numbered[index]

    def get_named(self, name: str) -> float:
        if name.startswith("_"):
            getter = self.predefined.get(name)
            if getter is not None:
                return getter()
            value = self.ini.get(name[5:]) if name.startswith(INI_PREFIX) else self._globals.get(name)
        else:
            value = self._locals[-1].get(name)
        if value is None:
            raise GCodeError(f"Named parameter #<{name}> not defined")
        return value

    def exists(self, name: str) -> bool:
        if name.startswith("_"):
            if name.startswith(INI_PREFIX):
                return name[5:] in self.ini
            return name in self.predefined or name in self._globals
        return name in self._locals[-1]

    # --- writing ----------------------------------------------------------------------------------

    def check_assignable(self, key: int | str) -> None:
        """Refuse an assignment a program may not make (before any assignment of the line lands)."""
        if isinstance(key, str):
            if key in self.predefined or key.startswith(INI_PREFIX):
                raise GCodeError(f"Cannot assign to read-only parameter #<{key}>")
        elif key in READ_ONLY_NUMBERED:
            raise GCodeError(f"Cannot assign to read-only parameter #{key}")

    def assign(self, key: int | str, value: float) -> None:
        if isinstance(key, str):
            if key.startswith("_"):
                self._globals[key] = value
            else:
                self._locals[-1][key] = value
        else:
            self.numbered[key] = value

    def set_system(self, index: int, value: float) -> None:
        """The interpreter's own writes (tool, probe, offsets), read-only ones included."""
        self.numbered[index] = value

    # --- scopes (o-word calls, a later issue) ----------------------------------------------------

    def push_scope(self) -> None:
        self._locals.append({})

    def pop_scope(self) -> None:
        if len(self._locals) > 1:
            self._locals.pop()

    @property
    def call_level(self) -> int:
        return len(self._locals) - 1

    # --- persistence ------------------------------------------------------------------------------

    def load(self, values: dict[int, float]) -> None:
        for index, value in values.items():
            if 1 <= index <= MAX_PARAMETER:
                self.numbered[index] = float(value)

    def snapshot(self, indexes) -> dict[int, float]:
        return {i: self.numbered[i] for i in sorted(set(indexes)) if 1 <= i <= MAX_PARAMETER}
