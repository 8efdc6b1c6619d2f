"""The machine file: ``[machine]`` and ``[axes.*]`` read into the planner's dataclasses.

``[interpreter]`` is read here too, into :class:`InterpreterConfig` (paths resolved against the
file's directory); :mod:`motiond.interp_settings` turns it, with the command-line overrides, into the
interpreter's settings. The other top-level tables (``[canopen]``, ``[modbus]``, ``[telemetry]``)
belong to later layers; they are kept as :class:`~motiond.configkit.Table` objects for their own
readers (``motiond.config_canopen``, ``motiond.config_modbus`` ...), which validate them. Unknown
top-level tables are rejected here, so a typo such as ``[axis.x]`` is an error rather than a silently
ignored section.

With no file, :data:`planner.machine.DEMO_MACHINE` is the machine and the other sections are empty
(each layer then uses its built-in demo defaults).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from gcode_canon.commands import AXES
from motiond.configkit import ConfigError, Table, in_range, load_toml, positive, special_file
from planner.machine import DEMO_MACHINE, AxisLimits, MachineError, MachineLimits

TOP_LEVEL = ("machine", "axes", "interpreter", "canopen", "modbus", "io", "telemetry", "motion")
DIALECTS = ("linuxcnc", "gcode-canon", "grbl")


@dataclass(frozen=True)
class InterpreterConfig:
    """``[interpreter]``: how programs are read on this machine. Paths are absolute (resolved against
    the machine file's directory); the defaults are :class:`gcode_canon.settings.InterpreterSettings`'s."""

    dialect: str = "linuxcnc"
    subroutine_path: tuple[Path, ...] = ()
    max_call_depth: int = 10
    max_loop_iterations: int = 1_000_000
    log_dir: Path | None = None
    block_delete: bool = False
    tool_table: Path | None = None
    var_file: Path | None = None
    program_path: tuple[Path, ...] = ()  # the daemon runs programs from these directories only
    tool_change_with_spindle_on: bool = False  # LinuxCNC's [EMCIO] TOOL_CHANGE_WITH_SPINDLE_ON
    disable_g92_persistence: bool = False  # LinuxCNC's [RS274NGC] DISABLE_G92_PERSISTENCE
    disable_fanuc_style_sub: bool = False  # LinuxCNC's [RS274NGC] DISABLE_FANUC_STYLE_SUB


@dataclass(frozen=True)
class MachineConfig:
    """Everything the machine file says; ``path`` is None for the built-in demo machine."""

    limits: MachineLimits
    path: str | None
    canopen: Table
    modbus: Table
    telemetry: Table
    root: Table | None = None
    """The whole file, for readers that take it (``read_canopen(root, ...)``); empty for the demo."""
    interpreter: InterpreterConfig = field(default_factory=InterpreterConfig)

    @property
    def name(self) -> str:
        return self.limits.name


AXIS_KEYS = ("max_velocity", "max_acceleration", "max_jerk", "min_position", "max_position",
             "quick_stop_deceleration")


def _axis(name: str, t: Table) -> AxisLimits:
    if name not in AXES:
        raise ConfigError(t.file, t.path, f"not an axis name (one of {' '.join(AXES)})")
    for key in t.data:
        if key not in AXIS_KEYS:  # before the required keys: a misspelt key is the likelier mistake
            raise t.error(key, "unknown key (misspelt?)")
    velocity = t.get("max_velocity", float, check=positive)
    acceleration = t.get("max_acceleration", float, check=positive)
    jerk = t.get("max_jerk", float, check=positive)
    lo = t.get("min_position", float, default=None)
    hi = t.get("max_position", float, default=None)
    quick = t.get("quick_stop_deceleration", float, default=None, check=positive)
    if lo is not None and hi is not None and lo >= hi:
        raise t.error("min_position", f"must be below max_position ({hi:g}), got {lo:g}")
    t.check_unknown()
    return AxisLimits(name, velocity, acceleration, jerk, lo, hi, quick)


def _interpreter(t: Table, base: Path) -> InterpreterConfig:
    """``[interpreter]``; relative paths are taken from ``base`` (the machine file's directory)."""

    def resolve(text: str) -> Path:
        p = Path(text).expanduser()
        return p if p.is_absolute() else base / p

    def path_key(name: str, want_dir: bool | None) -> Path | None:
        text = t.get(name, str, default=None)
        if text is None:
            return None
        if not text:
            raise t.error(name, "must not be empty (leave the key out for none)")
        p = resolve(text)
        if want_dir is True and not p.is_dir():
            raise t.error(name, f"no such directory: {p}")
        if want_dir is False and not p.is_file():
            raise t.error(name, f"no such file: {p}")
        return p

    dialect = t.get("dialect", str, default="linuxcnc", check=lambda v: None if v in DIALECTS else
                    f"must be one of {', '.join(DIALECTS)}")
    def dir_list(name: str) -> tuple[Path, ...]:
        dirs = []
        for i, item in enumerate(t.get(name, list, default=[])):
            key = f"{name}[{i}]"
            if not isinstance(item, str) or not item:
                raise t.error(key, f"must be a directory name (a non-empty string), got {item!r}")
            p = resolve(item)
            if not p.is_dir():
                raise t.error(key, f"no such directory: {p}")
            dirs.append(p)
        return tuple(dirs)

    dirs = dir_list("subroutine_path")
    programs = dir_list("program_path")
    depth = t.get("max_call_depth", int, default=10, check=lambda v: None if v >= 1 else "must be >= 1")
    loops = t.get("max_loop_iterations", int, default=1_000_000,
                  check=lambda v: None if v >= 1 else "must be >= 1")
    log_dir = path_key("log_dir", True)
    block_delete = t.get("block_delete", bool, default=False)
    spindle_on = t.get("tool_change_with_spindle_on", bool, default=False)
    no_g92 = t.get("disable_g92_persistence", bool, default=False)
    no_fanuc = t.get("disable_fanuc_style_sub", bool, default=False)
    tool_table = path_key("tool_table", False)
    var_file = path_key("var_file", None)  # may not exist yet: it is written at program end
    if var_file is not None and var_file.is_dir():
        raise t.error("var_file", f"is a directory: {var_file}")
    kind = special_file(var_file.stat().st_mode) if var_file is not None and var_file.exists() else None
    if kind is not None:  # a pipe: reading it waited for a writer for ever
        raise t.error("var_file", f"is {kind} file, not a parameter file: {var_file}")
    t.check_unknown()
    return InterpreterConfig(dialect, dirs, depth, loops, log_dir, block_delete, tool_table, var_file,
                             programs, spindle_on, no_g92, no_fanuc)


def load_machine(path: str | None) -> MachineConfig:
    """Read and check the machine file (None: the demo machine). Errors name the file and the key."""
    if path is None:
        return MachineConfig(DEMO_MACHINE, None, Table({}, "", "canopen"), Table({}, "", "modbus"),
                             Table({}, "", "telemetry"), Table({}, ""))
    file = str(path)
    root = Table(load_toml(path), file)
    for key in root.data:
        if key not in TOP_LEVEL:
            raise root.error(key, f"unknown table (expected one of {', '.join(TOP_LEVEL)})")
    machine = root.table("machine")
    name = machine.get("name", str, default="machine")
    cycle_ms = machine.get("cycle_ms", float, default=2.0, check=in_range(1.0, 10.0))
    machine.check_unknown()
    if "axes" not in root:
        raise root.error("axes", "missing: the machine needs at least one [axes.NAME] table")
    axes = [_axis(axis_name, t) for axis_name, t in root.tables("axes")]
    if not axes:
        raise root.error("axes", "empty: the machine needs at least one [axes.NAME] table")
    try:
        limits = MachineLimits(tuple(axes), cycle_s=cycle_ms / 1000.0, name=name)
    except MachineError as exc:
        raise root.error("axes", str(exc)) from None
    interpreter = _interpreter(root.table("interpreter"), Path(file).resolve().parent)
    return MachineConfig(limits, file, root.table("canopen"), root.table("modbus"), root.table("telemetry"),
                         Table(root.data, file), interpreter)
