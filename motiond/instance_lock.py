"""One ``canon run`` or ``canon daemon`` per machine.

Two processes driving the same machine would stream setpoints to the same drives, interleave their
LCM status and share one parameter file. Each takes an exclusive ``flock`` on a lock file in the
state directory, named after the machine file (its resolved path; the built-in demo machine has its
own). The kernel drops the lock when the process ends, however it ends, so a crash leaves no stale
lock behind; the file holds the PID of its holder, which a refused second process names.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import re
from pathlib import Path


class MachineInUse(Exception):
    """Another process holds the machine's lock; the message names its PID."""


def lock_path(config_file: str | os.PathLike[str] | None, machine_name: str, directory: Path) -> Path:
    """The lock file for a machine file (``None``: the built-in demo machine)."""
    key = str(Path(config_file).resolve()) if config_file is not None else "<demo>"
    slug = re.sub(r"[^A-Za-z0-9._-]+", "-", machine_name).strip("-") or "machine"
    digest = hashlib.sha1(key.encode()).hexdigest()[:12]
    return directory / f"{slug}-{digest}.lock"


class InstanceLock:
    """Held from :meth:`acquire` until :meth:`release` or the end of the process."""

    def __init__(self, path: Path, what: str) -> None:
        self.path = path
        self.what = what  # "machine file m.toml" / "the demo machine", for the refusal
        self._fd: int | None = None

    def acquire(self) -> InstanceLock:
        """Take the lock or raise :class:`MachineInUse` (or ``OSError`` for an unusable directory)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_pid(fd)
            os.close(fd)
            who = f"process {holder}" if holder else "another process"
            raise MachineInUse(f"{self.what} is in use by {who} (a canon run or daemon; lock {self.path}): "
                               "stop it first") from None
        except OSError:
            os.close(fd)
            raise
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, 0)
            os.close(self._fd)  # closing drops the flock
            self._fd = None

    def __enter__(self) -> InstanceLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def _read_pid(fd: int) -> int:
    try:
        text = os.pread(fd, 64, 0).decode(errors="replace").strip()
        return int(text.split()[0]) if text else 0
    except (OSError, ValueError, IndexError):
        return 0


def lock_machine(config_file: str | None, machine_name: str, state_directory: str | None) -> InstanceLock:
    """Take the machine's lock in the state directory (``motiond.cmd_daemon.state_dir``); a refusal
    or an unusable directory is a :class:`motiond.cli.UserError`."""
    from motiond.cli import UserError
    from motiond.cmd_daemon import state_dir

    directory = state_dir(state_directory)
    what = f"machine file {config_file}" if config_file is not None else "the demo machine"
    lock = InstanceLock(lock_path(config_file, machine_name, directory), what)
    try:
        return lock.acquire()
    except MachineInUse as exc:
        raise UserError(str(exc)) from None
    except OSError as exc:
        raise UserError(f"state directory {directory}: cannot make the machine's lock: "
                        f"{exc.strerror}") from None
