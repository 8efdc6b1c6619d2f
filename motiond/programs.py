"""Which part programs the daemon may run: only files inside its program directories.

A ``run`` command names a program as a path relative to one of the directories (``pocket.ngc``,
``jobs/a/part.ngc``) or as an absolute path inside one. The name is resolved with every symbolic
link followed (``os.path.realpath``) and must land inside a directory's own real path: ``..``, an
absolute path elsewhere, or a link that leads out are refused (LinuxCNC's ``PROGRAM_PREFIX`` serves
the same purpose). The refusal for a path outside is one sentence, whatever is there: it never says
whether the file exists, how long it is or what it holds, and nothing outside is ever opened.

The directories are ``[interpreter] program_path`` of the machine file, ``canon daemon
--program-dir`` (repeatable), or else ``programs`` in the daemon's state directory.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from motiond.states import CommandRefused

__all__ = ["resolve_program"]

_NAME_SHOWN = 200  # characters of the requested name repeated in a refusal


def _inside(real: Path, root: Path) -> bool:
    return real == root or root in real.parents


def resolve_program(name: str, directories: Sequence[str | os.PathLike[str]]) -> Path:
    """The real path of the program ``name`` inside ``directories``; :class:`CommandRefused` otherwise."""
    shown = name if len(name) <= _NAME_SHOWN else name[:_NAME_SHOWN] + "..."
    if not directories:
        raise CommandRefused("no program directories are configured ([interpreter] program_path, or canon "
                             "daemon --program-dir): no program can be run")
    roots = [Path(os.path.realpath(d)) for d in directories]
    where = ", ".join(str(r) for r in roots)
    if not name.strip() or "\0" in name:
        raise CommandRefused(f"{shown!r} is not a program name")
    given = Path(name)
    candidates = [given] if given.is_absolute() else [root / given for root in roots]
    inside_any = False
    for candidate in candidates:
        real = Path(os.path.realpath(candidate))
        if not any(_inside(real, root) for root in roots):
            continue
        inside_any = True
        if real.is_file():
            return real
    if not inside_any:
        raise CommandRefused(f"{shown!r} is outside the program directories ({where}): refused")
    raise CommandRefused(f"no program {shown!r} in the program directories ({where})")
