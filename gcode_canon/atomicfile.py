"""Small persistent text files: read them line by line with clear errors, replace them atomically.

Why this exists: the parameter (.var) file and the tool table hold a machine's state (work offsets,
tool lengths). A crash or a power cut while saving must leave a readable file holding either the old
or the new contents, never half of each; and a damaged or foreign file must give a clear error
naming the file and the line, never a traceback of some other type.

Writing follows the POSIX recipe: write a new file under a unique name in the same directory, fsync
it, keep the current file as ``FILE.bak`` (a hard link to it, put in place with one rename, so the
backup too is always whole), rename the new file over the old one (``os.replace``, atomic within a
file system), then fsync the directory so the renames themselves survive a power cut. The old file
is never opened for writing, so until the final rename it is untouched. A process killed mid-way may
leave a stray ``.NAME.*.tmp`` file next to the target; it is never read, and
:func:`remove_stray_temps` (the daemon calls it at start) removes it.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import secrets
import stat
from collections.abc import Iterator

from gcode_canon.errors import GCodeError

log = logging.getLogger(__name__)

BACKUP_SUFFIX = ".bak"
"""Suffix of the backup of the previous contents (LinuxCNC keeps its var file's backup so too)."""

MAX_LINE_BYTES = 4096
"""Longest line (line ending included) the readers accept; anything longer is not one of our files."""

# Errors of os.link that mean "this file system has no hard links": fall back to copying.
_NO_LINK = {errno.EPERM, errno.EMLINK, errno.EXDEV, errno.ENOTSUP, errno.EOPNOTSUPP, errno.ENOSYS}


def atomic_write(path: str | os.PathLike[str], data: bytes, *, backup: bool = False) -> None:
    """Replace the file at ``path`` with ``data`` so that a crash leaves either old or new contents.

    With ``backup``, the previous contents (if there was a file) are kept as ``path + ".bak"``.
    A symbolic link at ``path`` is followed: its target is replaced and the link kept. The new file
    gets the old file's permission bits (and owner, where allowed); a new file gets ``0o666`` less
    the umask. Raises ``OSError`` (with the failing file's name) on any failure, after removing its
    temporary file; the old file is then unchanged, except when the error comes from the final
    directory fsync, when the new contents are in place but may not yet be on disk.
    """
    target = os.path.realpath(os.fspath(path))
    directory, name = os.path.split(target)
    old = _stat_or_none(target)
    tmp = _write_temp(directory, name, data, old)
    try:
        if backup and old is not None and stat.S_ISREG(old.st_mode):
            _keep_backup(target, directory, name, old)
        os.replace(tmp, target)
    except BaseException:
        _unlink_quietly(tmp)
        raise
    _fsync_directory(directory)


def atomic_write_text(
    path: str | os.PathLike[str], text: str, *, backup: bool = False, encoding: str = "utf-8"
) -> None:
    """:func:`atomic_write` for text (``\\n`` line endings, written as is)."""
    atomic_write(path, text.encode(encoding), backup=backup)


def read_lines(
    path: str | os.PathLike[str], what: str, *, max_line: int = MAX_LINE_BYTES
) -> Iterator[tuple[int, str]]:
    """Yield ``(line_number, text)`` for each line of a UTF-8 text file, line ending removed.

    ``what`` names the file in messages ("parameter file"). A missing file raises
    ``FileNotFoundError`` (callers decide whether that is an error); every other problem raises
    :class:`GCodeError` naming the file and, where there is one, the line: unreadable file, a line
    longer than ``max_line`` bytes, a NUL byte, bytes that are not UTF-8. A UTF-8 byte order mark at
    the start is ignored; ``\\r\\n`` endings are accepted.
    """
    name = os.fspath(path)
    try:
        f = open(name, "rb")  # noqa: SIM115 - closed by the with below; open errors handled here
    except FileNotFoundError:
        raise
    except OSError as e:
        raise GCodeError(f"cannot read {what}: {e.strerror or e}", name) from e
    with f:
        lineno = 0
        while True:
            try:
                raw = f.readline(max_line + 1)
            except OSError as e:
                raise GCodeError(f"cannot read {what}: {e.strerror or e}", name, lineno + 1) from e
            if not raw:
                return
            lineno += 1
            if len(raw) > max_line:
                raise GCodeError(f"line longer than {max_line} bytes: not a {what}", name, lineno)
            nul = raw.find(b"\0")
            if nul >= 0:
                raise GCodeError(f"NUL byte at column {nul + 1}: not a text {what}", name, lineno)
            try:
                text = raw.decode("utf-8")
            except UnicodeDecodeError as e:
                raise GCodeError(
                    f"byte 0x{raw[e.start]:02x} at column {e.start + 1} is not UTF-8 text", name, lineno
                ) from None
            if lineno == 1:
                text = text.removeprefix("\ufeff")
            yield lineno, text.removesuffix("\n").removesuffix("\r")


def remove_stray_temps(path: str | os.PathLike[str], min_age_s: float = 10.0) -> list[str]:
    """Remove the temporary files that interrupted saves of ``path`` left next to it (``.NAME.*.tmp``,
    ``.NAME.*.bak.tmp``); returns their names. Only files older than ``min_age_s`` are touched, so a
    save in progress in another process keeps its file. Errors are logged, never raised."""
    import time

    target = os.path.realpath(os.fspath(path))
    directory, name = os.path.split(target)
    prefix = f".{name}."
    removed: list[str] = []
    try:
        entries = os.listdir(directory)
    except OSError as e:
        log.warning("cannot look for stray temporary files in %s: %s", directory, e.strerror or e)
        return removed
    now = time.time()
    for entry in entries:
        if not (entry.startswith(prefix) and entry.endswith(".tmp")):
            continue
        middle = entry[len(prefix):-len(".tmp")].removesuffix(".bak")
        if len(middle) != 12 or any(c not in "0123456789abcdef" for c in middle):
            continue  # not one of ours (secrets.token_hex(6))
        full = os.path.join(directory, entry)
        try:
            st = os.lstat(full)
            if not stat.S_ISREG(st.st_mode) or now - st.st_mtime < min_age_s:
                continue
            os.unlink(full)
            removed.append(full)
        except OSError as e:
            log.warning("cannot remove the stray temporary file %s: %s", full, e.strerror or e)
    if removed:
        log.info("removed %d temporary file(s) of interrupted saves of %s", len(removed), target)
    return removed


# --- helpers ----------------------------------------------------------------------------------------


def _stat_or_none(path: str) -> os.stat_result | None:
    try:
        return os.stat(path)
    except FileNotFoundError:
        return None


def _write_temp(directory: str, name: str, data: bytes, like: os.stat_result | None) -> str:
    """Write ``data`` to a new uniquely named file in ``directory``, fsynced; return its path."""
    tmp = os.path.join(directory, f".{name}.{secrets.token_hex(6)}.tmp")
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
    fd = os.open(tmp, flags, 0o666)
    try:
        try:
            view = memoryview(data)
            while view:
                written = os.write(fd, view)
                view = view[written:]
            if like is not None and stat.S_ISREG(like.st_mode):
                _copy_owner_and_mode(fd, like)
            os.fsync(fd)
        finally:
            os.close(fd)
    except BaseException:
        _unlink_quietly(tmp)
        raise
    return tmp


def _copy_owner_and_mode(fd: int, like: os.stat_result) -> None:
    if hasattr(os, "fchown") and (like.st_uid, like.st_gid) != (os.getuid(), os.getgid()):
        try:
            os.fchown(fd, like.st_uid, like.st_gid)
        except PermissionError:
            log.debug("cannot give the new file its old owner %d:%d", like.st_uid, like.st_gid)
    os.fchmod(fd, stat.S_IMODE(like.st_mode))


def _keep_backup(target: str, directory: str, name: str, old: os.stat_result) -> None:
    """Make ``target + BACKUP_SUFFIX`` the current contents of ``target``, replacing it in one step."""
    link = os.path.join(directory, f".{name}.{secrets.token_hex(6)}.bak.tmp")
    try:
        os.link(target, link)
    except OSError as e:
        if e.errno not in _NO_LINK:
            raise
        with open(target, "rb") as f:
            link = _write_temp(directory, name, f.read(), old)
    try:
        os.replace(link, target + BACKUP_SUFFIX)
    except BaseException:
        _unlink_quietly(link)
        raise


def _fsync_directory(directory: str) -> None:
    if not hasattr(os, "O_DIRECTORY"):  # not POSIX: renames are as durable as the platform makes them
        return
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    except OSError as e:
        if e.errno != errno.EINVAL:  # some file systems cannot sync a directory; nothing more to do
            raise
    finally:
        os.close(fd)


def _unlink_quietly(path: str) -> None:
    with contextlib.suppress(OSError):
        os.unlink(path)
