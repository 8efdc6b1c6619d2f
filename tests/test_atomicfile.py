"""gcode_canon.atomicfile: atomic replacement with a backup, and the careful line reader."""

from __future__ import annotations

import errno
import os
import stat

import pytest

from gcode_canon import atomicfile
from gcode_canon.atomicfile import BACKUP_SUFFIX, atomic_write, atomic_write_text, read_lines
from gcode_canon.errors import GCodeError

OLD = b"old contents\n" * 50
NEW = b"new contents, longer than the old ones\n" * 80


class Crash(BaseException):
    """The process 'dies' here: nothing after it runs except finally blocks and fd closes."""


STEPS = ("open", "write", "fsync", "fchmod", "fchown", "link", "replace")


class StepOs:
    """Stands in for ``os`` inside atomicfile: records each file system step and can die at one.

    At the fatal step a ``write`` writes half its buffer first (a torn write). After the crash the
    clean-up a real dead process could not do (unlink of its temporary files) is suppressed.
    """

    def __init__(self, crash_at: int | None = None) -> None:
        self.calls: list[str] = []
        self.crash_at = crash_at
        self.crashed = False

    def __getattr__(self, name: str):
        real = getattr(os, name)
        if name == "unlink":
            return lambda *a, **k: None if self.crashed else real(*a, **k)
        if name not in STEPS:
            return real

        def step(*args, **kwargs):
            index = len(self.calls)
            self.calls.append(name)
            if index == self.crash_at:
                self.crashed = True
                if name == "write":
                    fd, data = args
                    real(fd, bytes(data)[: len(data) // 2])
                raise Crash(f"{name} (step {index})")
            return real(*args, **kwargs)

        return step


def stray_files(directory) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.endswith(".tmp"))


# --- writing ----------------------------------------------------------------------------------------


def test_write_new_file_contents_and_default_mode(tmp_path):
    target = tmp_path / "f.txt"
    atomic_write(target, NEW)
    assert target.read_bytes() == NEW
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~umask
    assert stray_files(tmp_path) == []
    assert not (tmp_path / ("f.txt" + BACKUP_SUFFIX)).exists()


def test_replace_keeps_the_old_permission_bits(tmp_path):
    target = tmp_path / "f.txt"
    target.write_bytes(OLD)
    target.chmod(0o640)
    atomic_write(target, NEW)
    assert target.read_bytes() == NEW
    assert stat.S_IMODE(target.stat().st_mode) == 0o640


def test_replace_makes_a_new_inode_and_never_writes_the_old_one(tmp_path):
    target = tmp_path / "f.txt"
    target.write_bytes(OLD)
    with open(target, "rb") as held:  # a reader that opened the old file keeps seeing it whole
        atomic_write(target, NEW)
        assert held.read() == OLD
    assert target.read_bytes() == NEW


def test_backup_holds_the_previous_contents(tmp_path):
    target = tmp_path / "f.txt"
    bak = tmp_path / ("f.txt" + BACKUP_SUFFIX)
    atomic_write(target, OLD, backup=True)
    assert not bak.exists()  # nothing to back up yet
    atomic_write(target, NEW, backup=True)
    assert bak.read_bytes() == OLD
    atomic_write(target, b"third\n", backup=True)
    assert bak.read_bytes() == NEW
    assert target.read_bytes() == b"third\n"
    assert stray_files(tmp_path) == []


def test_no_backup_unless_asked(tmp_path):
    target = tmp_path / "f.txt"
    target.write_bytes(OLD)
    atomic_write(target, NEW)
    assert not (tmp_path / ("f.txt" + BACKUP_SUFFIX)).exists()


def test_backup_is_copied_when_hard_links_are_refused(tmp_path, monkeypatch):
    target = tmp_path / "f.txt"
    target.write_bytes(OLD)

    def no_link(src, dst, *a, **k):
        raise OSError(errno.EPERM, "Operation not permitted", src)

    monkeypatch.setattr(atomicfile.os, "link", no_link)
    atomic_write(target, NEW, backup=True)
    assert (tmp_path / ("f.txt" + BACKUP_SUFFIX)).read_bytes() == OLD
    assert target.read_bytes() == NEW
    assert stray_files(tmp_path) == []


def test_symlink_is_followed_and_kept(tmp_path):
    real = tmp_path / "real.txt"
    real.write_bytes(OLD)
    link = tmp_path / "link.txt"
    link.symlink_to(real)
    atomic_write(link, NEW, backup=True)
    assert link.is_symlink()
    assert real.read_bytes() == NEW
    assert (tmp_path / ("real.txt" + BACKUP_SUFFIX)).read_bytes() == OLD


def test_text_is_written_as_utf8(tmp_path):
    target = tmp_path / "f.txt"
    atomic_write_text(target, "Ø 6 mm\n")
    assert target.read_bytes() == "Ø 6 mm\n".encode()


def test_directory_is_synced_after_the_rename(tmp_path, monkeypatch):
    target = tmp_path / "f.txt"
    target.write_bytes(OLD)
    fake = StepOs()
    synced: list[str] = []
    real_fsync = os.fsync

    def fsync(fd):
        synced.append("dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file")
        return real_fsync(fd)

    monkeypatch.setattr(atomicfile, "os", fake)
    monkeypatch.setattr(os, "fsync", fsync)
    atomic_write(target, NEW, backup=True)
    assert synced == ["file", "dir"]
    assert fake.calls.index("replace") < len(fake.calls) - 1  # something (the dir fsync) after it
    assert fake.calls[-1] == "fsync"
    assert [c for c in fake.calls if c == "replace"] == ["replace", "replace"]  # backup, then file


def test_crash_at_every_step_leaves_old_or_new_whole(tmp_path, monkeypatch):
    """Die at each file system call of a write in turn: the file is always entirely old or new."""
    probe = StepOs()
    target = tmp_path / "probe.txt"
    target.write_bytes(OLD)
    monkeypatch.setattr(atomicfile, "os", probe)
    atomic_write(target, NEW, backup=True)
    monkeypatch.undo()
    steps = list(probe.calls)
    last_replace = max(i for i, name in enumerate(steps) if name == "replace")
    assert len(steps) >= 6

    for k, name in enumerate(steps):
        d = tmp_path / f"crash{k}"
        d.mkdir()
        target = d / "f.txt"
        bak = d / ("f.txt" + BACKUP_SUFFIX)
        atomic_write(target, b"older\n", backup=True)
        atomic_write(target, OLD, backup=True)
        fake = StepOs(crash_at=k)
        monkeypatch.setattr(atomicfile, "os", fake)
        with pytest.raises(Crash):
            atomic_write(target, NEW, backup=True)
        monkeypatch.undo()
        expected = NEW if k > last_replace else OLD
        assert target.read_bytes() == expected, f"crash at step {k} ({name})"
        assert bak.read_bytes() in (b"older\n", OLD), f"crash at step {k} ({name})"
        # the next write works despite what the dead process left behind
        atomic_write(target, b"after\n", backup=True)
        assert target.read_bytes() == b"after\n"
        assert bak.read_bytes() == expected


def test_disk_full_mid_write_leaves_the_old_file(tmp_path, monkeypatch):
    target = tmp_path / "f.txt"
    target.write_bytes(OLD)
    real_write = os.write

    def short_then_full(fd, data):
        if len(data) > 16:
            return real_write(fd, bytes(data)[:16])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomicfile.os, "write", short_then_full)
    with pytest.raises(OSError) as info:
        atomic_write(target, NEW, backup=True)
    assert info.value.errno == errno.ENOSPC
    monkeypatch.undo()
    assert target.read_bytes() == OLD
    assert stray_files(tmp_path) == []


def test_short_writes_are_completed(tmp_path, monkeypatch):
    real_write = os.write
    monkeypatch.setattr(atomicfile.os, "write", lambda fd, data: real_write(fd, bytes(data)[:7]))
    target = tmp_path / "f.txt"
    atomic_write(target, NEW)
    monkeypatch.undo()
    assert target.read_bytes() == NEW


def test_missing_directory_is_an_oserror(tmp_path):
    with pytest.raises(FileNotFoundError):
        atomic_write(tmp_path / "no" / "such" / "f.txt", NEW)


def test_target_that_is_a_directory_is_refused_and_cleaned_up(tmp_path):
    (tmp_path / "d").mkdir()
    with pytest.raises(OSError):
        atomic_write(tmp_path / "d", NEW, backup=True)
    assert (tmp_path / "d").is_dir()
    assert stray_files(tmp_path) == []


# --- reading ----------------------------------------------------------------------------------------


def test_read_lines_numbers_lines_and_strips_endings(tmp_path):
    f = tmp_path / "f"
    f.write_bytes(b"\xef\xbb\xbffirst\r\nsecond\n\nlast without newline")
    assert list(read_lines(f, "test file")) == [
        (1, "first"),
        (2, "second"),
        (3, ""),
        (4, "last without newline"),
    ]


def test_read_lines_missing_file_is_filenotfound(tmp_path):
    with pytest.raises(FileNotFoundError):
        list(read_lines(tmp_path / "absent", "test file"))


@pytest.mark.parametrize(
    ("data", "line", "words"),
    [
        (b"ok\nbad \xff byte\n", 2, "0xff at column 5"),
        (b"ok\nok\nnul\x00here\n", 3, "NUL byte at column 4"),
        (b"ok\n" + b"x" * 5000 + b"\n", 2, "longer than"),
        (b"x" * 100_000, 1, "longer than"),
    ],
)
def test_read_lines_bad_bytes_name_the_line(tmp_path, data, line, words):
    f = tmp_path / "f"
    f.write_bytes(data)
    with pytest.raises(GCodeError) as info:
        list(read_lines(f, "test file"))
    assert info.value.file == str(f)
    assert info.value.line == line
    assert words in info.value.message


def test_read_lines_directory_is_a_gcode_error(tmp_path):
    with pytest.raises(GCodeError, match="cannot read test file") as info:
        list(read_lines(tmp_path, "test file"))
    assert info.value.file == str(tmp_path)
