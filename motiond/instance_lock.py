"""One ``canon run`` or ``canon daemon`` per machine.

Two processes driving the same machine would stream setpoints to the same drives, interleave their
LCM status and share one parameter file. Each takes an exclusive ``flock`` on a lock file in the
state directory, named after the machine file (its resolved path; the built-in demo machine has its
own). The kernel drops the lock when the process ends, however it ends, so a crash leaves no stale
lock behind; the file holds the PID of its holder, which a refused second process names.

Two different machine files can name the same hardware: the same CAN interface and channel, the same
Modbus module. So the fieldbus endpoints a machine file reaches beyond this process are locked too
(:func:`bus_keys`), each in its own lock file: a second process on ``socketcan can0`` is refused
whatever machine file it was started with. python-can's ``virtual`` bus and simulated Modbus devices
live inside one process and are not locked, nor is the local bus (``canon_local``) of simulated drives:
the machine gives them a channel of its own.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import re
from pathlib import Path
from typing import Any


class MachineInUse(Exception):
    """Another process holds the machine's lock; the message names its PID."""


def lock_path(config_file: str | os.PathLike[str] | None, machine_name: str, directory: Path) -> Path:
    """The lock file for a machine file (``None``: the built-in demo machine)."""
    key = str(Path(config_file).resolve()) if config_file is not None else "<demo>"
    slug = re.sub(r"[^A-Za-z0-9._-]+", "-", machine_name).strip("-") or "machine"
    digest = hashlib.sha1(key.encode()).hexdigest()[:12]
    return directory / f"{slug}-{digest}.lock"


def bus_keys(canopen: Any, modbus: Any) -> list[tuple[str, str]]:
    """(lock key, what it is) for each fieldbus endpoint outside this process that the machine uses:
    its CAN interface and channel, each real Modbus device (TCP endpoint and unit, or serial port)."""
    keys: list[tuple[str, str]] = []
    from fieldbus.canopen.config import LOCAL_INTERFACE

    private = ("virtual", LOCAL_INTERFACE) if canopen is not None and canopen.simulate else ("virtual",)
    if canopen is not None and canopen.bus.interface not in private:  # a machine's own simulated bus
        bus = f"{canopen.bus.interface} {canopen.bus.channel}"
        keys.append((f"can:{bus}", f"CAN bus {bus}"))
    for dev in getattr(modbus, "devices", ()) or ():
        if dev.simulate:
            continue
        where = f"serial port {dev.serial}" if dev.serial else f"Modbus TCP {dev.host}:{dev.port}"
        keys.append((f"modbus:{dev.serial or f'{dev.host}:{dev.port}'}:{dev.unit}",
                     f"{where} unit {dev.unit}"))
    return keys


def resource_lock_path(key: str, directory: Path) -> Path:
    """The lock file of one fieldbus endpoint (:func:`bus_keys`)."""
    slug = re.sub(r"[^A-Za-z0-9._-]+", "-", key).strip("-")[:40]
    return directory / f"bus-{slug}-{hashlib.sha1(key.encode()).hexdigest()[:12]}.lock"


class InstanceLock:
    """Held from :meth:`acquire` until :meth:`release` or the end of the process."""

    def __init__(self, path: Path, what: str, owner: str = "") -> None:
        self.path = path
        self.what = what  # "machine file m.toml" / "the demo machine", for the refusal
        self.owner = owner  # for a bus lock: the machine it is held for, which a refused process names
        self._fd: int | None = None

    def acquire(self) -> InstanceLock:
        """Take the lock or raise :class:`MachineInUse` (or ``OSError`` for an unusable directory)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder, holder_what = _read_holder(fd)
            os.close(fd)
            who = f"process {holder}" if holder else "another process"
            for_what = f"for {holder_what}; " if holder_what and holder_what != self.what else ""
            raise MachineInUse(f"{self.what} is in use by {who} ({for_what}a canon run or daemon; lock "
                               f"{self.path}): stop it first") from None
        except OSError:
            os.close(fd)
            raise
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n{self.owner or self.what}\n".encode())
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


def _read_holder(fd: int) -> tuple[int, str]:
    """The PID in a lock file and what its holder wrote it for (0 and "" when unreadable)."""
    try:
        lines = os.pread(fd, 4096, 0).decode(errors="replace").splitlines()
        return (int(lines[0].split()[0]) if lines and lines[0].strip() else 0), \
            (lines[1].strip() if len(lines) > 1 else "")
    except (OSError, ValueError, IndexError):
        return 0, ""


class MachineLocks:
    """The machine file's lock and its fieldbus endpoints' locks, released together."""

    def __init__(self, locks: list[InstanceLock]) -> None:
        self.locks = locks

    def release(self) -> None:
        for lock in reversed(self.locks):
            lock.release()


def lock_machine(config_file: str | None, config: Any, state_directory: str | None) -> MachineLocks:
    """Take the machine's lock and its fieldbus endpoints' locks in the state directory
    (``motiond.cmd_daemon.state_dir``); a refusal or an unusable directory is a
    :class:`motiond.cli.UserError`. ``config`` is the loaded :class:`motiond.config.MachineConfig`."""
    from motiond.cli import UserError
    from motiond.cmd_daemon import state_dir

    directory = state_dir(state_directory)
    what = f"machine file {config_file}" if config_file is not None else "the demo machine"
    wanted = [InstanceLock(lock_path(config_file, config.limits.name, directory), what)]
    wanted += [InstanceLock(resource_lock_path(key, directory), name, owner=what)
               for key, name in _machine_bus_keys(config)]
    held: list[InstanceLock] = []
    try:
        for lock in wanted:
            held.append(lock.acquire())
    except MachineInUse as exc:
        MachineLocks(held).release()
        raise UserError(str(exc)) from None
    except OSError as exc:
        MachineLocks(held).release()
        raise UserError(f"state directory {directory}: cannot make the machine's lock: "
                        f"{exc.strerror}") from None
    return MachineLocks(held)


def _machine_bus_keys(config: Any) -> list[tuple[str, str]]:
    """:func:`bus_keys` of a loaded machine; a section that does not read is left to the code that
    reports it (the master or the I/O worker, at start)."""
    from motiond.config_canopen import canopen_for_machine
    from motiond.config_modbus import modbus_for
    from motiond.configkit import ConfigError

    try:
        canopen = canopen_for_machine(config)
    except ConfigError:
        canopen = None
    try:
        modbus = modbus_for(config)
    except ConfigError:
        modbus = None
    return bus_keys(canopen, modbus)
