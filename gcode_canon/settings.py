"""Interpreter settings: what the machine side decides before a program runs.

Kept apart from the interpreter so the daemon can build them from the machine configuration and
``canon check`` from its command line, without importing the interpreter.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path


@dataclass(slots=True)
class InterpreterSettings:
    var_file: Path | str | None = None
    """LinuxCNC parameter file: read at start, written at program end / shutdown (unless dry_run)."""
    tool_table: Path | str | None = None
    """LinuxCNC-format tool table; None means an empty table (any tool number, zero offsets)."""
    block_delete: bool = False
    """When True, lines starting with ``/`` are skipped."""
    dry_run: bool = False
    """Never write the parameter file (``canon check``)."""
    log_dir: Path | str | None = None
    """Directory for (LOGOPEN,...) files; None refuses LOG files."""
    subroutine_path: list[Path] = field(default_factory=list)
    """Directories searched, in order, for ``NAME.ngc`` when ``o<NAME> call`` names a subroutine not
    defined earlier in the program; the main program's own directory is searched last."""
    dialect: str = "linuxcnc"
    """"linuxcnc" (default), "gcode-canon" or "grbl" (:mod:`gcode_canon.dialect`): the meaning of the
    codes the dialects disagree on (so far: bare O numbers, M98, M99)."""
    max_line_length: int = 256
    max_call_depth: int = 10
    """Nested o-word / M98 calls (recursion included) beyond this are an error."""
    max_loop_iterations: int = 1_000_000
    """Passes of one while / do / repeat loop (or an M98 L count) beyond this are an error (a runaway
    loop)."""
    max_expression_depth: int = 64
    """Bracket / function / indirection nesting refused beyond this (protects the recursion limit)."""
    axes: str | None = None
    """The machine's axis letters (e.g. "xyz"); None accepts all nine. A word for an axis the machine
    does not have is an error."""
    require_program_end: bool = True
    """A program (file or string) must end with M2/M30 or a closing ``%`` (LinuxCNC's rule)."""
    tool_change_with_spindle_on: bool = False
    """M6 leaves the spindle turning (LinuxCNC's ``[EMCIO] TOOL_CHANGE_WITH_SPINDLE_ON``); by default
    M6 stops it first, as LinuxCNC does."""
    disable_g92_persistence: bool = False
    """G92/G52 offsets (#5210-#5219) are not kept from one program to the next: cleared when the
    parameter file is read and at M2/M30 (LinuxCNC's ``[RS274NGC] DISABLE_G92_PERSISTENCE``)."""
    user_mcodes: frozenset[int] = frozenset()
    """The user M codes (100-199) the machine binds (``[io.mcodes]``); any other M100-M199 is an error."""
    disable_fanuc_style_sub: bool = False
    """M98, M99 and bare ``O<n>`` program numbers are refused (LinuxCNC's ``[RS274NGC]
    DISABLE_FANUC_STYLE_SUB``): only o-word subroutines."""
    ini_values: dict[str, float] = field(default_factory=dict)
    """What ``#<_ini[section]name>`` reads (LinuxCNC's INI variables), keyed ``"section]name"`` in
    lower case: the daemon fills it with the machine file's numbers. Read-only to programs."""
