"""The interpreter's settings for ``canon check``, ``canon plan``, ``canon run`` and the daemon.

One place, so the four read a program the same way: the machine file's ``[interpreter]`` table
(:class:`motiond.config.InterpreterConfig`) gives the defaults, and what the command line says wins:

* ``--tool-table FILE`` and ``--var FILE`` replace ``tool_table`` / ``var_file``;
* ``--dialect NAME`` replaces ``dialect``;
* ``--subroutine-path DIR`` (repeatable) replaces the whole ``subroutine_path`` list;
* ``--block-delete`` turns block delete on (the file's ``block_delete = true`` cannot be turned off
  from the command line; it is an operator switch in the daemon).

``max_call_depth``, ``max_loop_iterations``, ``log_dir``, ``tool_change_with_spindle_on`` and
``disable_g92_persistence`` come from the file only. With a machine
file, words for axes the machine does not have are errors (``axes``).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from gcode_canon.settings import InterpreterSettings


def add_arguments(parser: argparse.ArgumentParser, *, block_delete: bool = True) -> None:
    """The interpreter options beside :func:`motiond.cli.add_common`'s ``--tool-table`` / ``--var``."""
    if block_delete:
        parser.add_argument("--block-delete", action="store_true", help="skip lines that start with '/'")
    parser.add_argument("--dialect", default=None,
                        help="G-code dialect: linuxcnc, gcode-canon or grbl (default: [interpreter] "
                             "dialect, else linuxcnc)")
    parser.add_argument("--subroutine-path", action="append", default=None, metavar="DIR",
                        help="directory searched for 'o<name> call' files (repeatable; replaces "
                             "[interpreter] subroutine_path; the program's own directory is searched last)")


def build_settings(config: Any, *, var: str | None = None, tool_table: str | None = None,
                   dialect: str | None = None, subroutine_path: list[str] | None = None,
                   block_delete: bool = False, dry_run: bool = False,
                   check_var: bool = False) -> InterpreterSettings:
    """Settings from ``config`` (a :class:`motiond.config.MachineConfig`) with the overrides given.

    Overrides named on a command line are checked here (:class:`motiond.cli.UserError` naming the
    option); the file's values were checked by :func:`motiond.config.load_machine`. ``check_var``:
    a ``--var`` file must exist (a dry run reads it and never writes it).
    """
    from motiond.cli import UserError

    def not_a_file(option: str, name: str) -> UserError:
        from motiond.configkit import special_file

        p = Path(name)
        kind = special_file(p.stat().st_mode) if p.exists() else None
        what = ("is a directory, not a file" if p.is_dir() else f"is {kind} file, not a regular file" if kind
                else "no such file")
        return UserError(f"{option} {name}: {what}")

    ic = config.interpreter
    if tool_table is not None and not Path(tool_table).is_file():
        raise not_a_file("--tool-table", tool_table)
    if var is not None and not Path(var).is_file() and (check_var or Path(var).exists()):
        raise not_a_file("--var", var)  # a run may create it, but never in place of a directory
    if dialect is not None:
        from gcode_canon.dialect import Dialect

        try:
            Dialect.parse(dialect)
        except ValueError as exc:
            raise UserError(f"--dialect: {exc}") from None
    if subroutine_path is not None:
        for directory in subroutine_path:
            if not Path(directory).is_dir():
                raise UserError(f"--subroutine-path {directory}: no such directory")
    from motiond.mcodes import bound_mcodes

    axes = None
    if config.path is not None:  # words for axes the machine does not have are errors
        axes = "".join(axis.name for axis in config.limits.axes)
    return InterpreterSettings(
        var_file=var if var is not None else ic.var_file,
        tool_table=tool_table if tool_table is not None else ic.tool_table,
        block_delete=block_delete or ic.block_delete,
        dry_run=dry_run,
        log_dir=ic.log_dir,
        subroutine_path=[Path(d) for d in subroutine_path] if subroutine_path is not None
        else list(ic.subroutine_path),
        dialect=dialect if dialect is not None else ic.dialect,
        max_call_depth=ic.max_call_depth,
        max_loop_iterations=ic.max_loop_iterations,
        axes=axes,
        tool_change_with_spindle_on=ic.tool_change_with_spindle_on,
        disable_g92_persistence=ic.disable_g92_persistence,
        user_mcodes=bound_mcodes(config),
        disable_fanuc_style_sub=ic.disable_fanuc_style_sub,
        ini_values=ini_values(config.root.data if config.root is not None else {}),
    )


def ini_values(data: dict[str, Any], section: str = "") -> dict[str, float]:
    """The machine file's numbers as ``#<_ini[section]name>`` reads them: ``[axes.x] max_velocity``
    is ``#<_ini[axes.x]max_velocity>`` (LinuxCNC reads its INI file the same way); booleans read 1 and
    0; names in lower case, as the interpreter folds them. Strings and arrays are not numbers."""
    out: dict[str, float] = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out.update(ini_values(value, f"{section}.{key}" if section else key))
        elif isinstance(value, bool | int | float) and section:
            out[f"{section}]{key}".lower().replace(" ", "")] = float(value)
    return out


def settings_from_args(config: Any, args: argparse.Namespace, *, dry_run: bool) -> InterpreterSettings:
    """:func:`build_settings` with the options of :func:`motiond.cli.add_common` and
    :func:`add_arguments` (those a sub-command lacks count as not given)."""
    return build_settings(
        config, var=getattr(args, "var", None), tool_table=getattr(args, "tool_table", None),
        dialect=getattr(args, "dialect", None), subroutine_path=getattr(args, "subroutine_path", None),
        block_delete=bool(getattr(args, "block_delete", False)), dry_run=dry_run, check_var=dry_run,
    )
