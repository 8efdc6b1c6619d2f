"""gcode_canon.paramfile: LinuxCNC's parameter (.var) file, read strictly and saved atomically."""

from __future__ import annotations

import errno
import logging
import math
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gcode_canon import atomicfile
from gcode_canon.errors import GCodeError
from gcode_canon.paramfile import (
    MAX_PARAMETER,
    PERSISTENT,
    READ_ONLY,
    USER,
    read_parameter_file,
    write_parameter_file,
)

ROOT = Path(__file__).resolve().parent.parent

# What LinuxCNC's reader, sscanf("%d %lf"), takes as the first two fields of a line.
C_LINE = re.compile(r"[+-]?[0-9]+[ \t]+[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


def write_text(path: Path, text: str) -> Path:
    path.write_text(textwrap.dedent(text))
    return path


def raises_at(path: Path, line: int, match: str) -> GCodeError:
    with pytest.raises(GCodeError) as info:
        read_parameter_file(path)
    assert re.search(match, info.value.message), info.value.message
    assert info.value.file == str(path)
    assert info.value.line == line
    assert str(info.value).startswith(f"{path}:{line}: ")
    return info.value


def stray_files(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.endswith(".tmp"))


# --- reading ----------------------------------------------------------------------------------------


def test_reads_linuxcnc_style_file(tmp_path):
    f = write_text(
        tmp_path / "sim.var",
        """\
        31	12.500000
        5161	0.000000
        5220	1.000000
        5221	-10.250000
        5222	3
        """,
    )
    assert read_parameter_file(f) == {31: 12.5, 5161: 0.0, 5220: 1.0, 5221: -10.25, 5222: 3.0}


def test_missing_file_is_filenotfound(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_parameter_file(tmp_path / "never-written.var")


def test_junk_lines_are_skipped(tmp_path, caplog):
    f = write_text(
        tmp_path / "p.var",
        """\
        Parameter file written by hand

        # a comment
           5161   1.5   (G28 X: text after the two numbers is ignored)
        5162
        abc 5
        5163 x
        5220 1,5
        5221 2
        """,
    )
    with caplog.at_level(logging.WARNING, logger="gcode_canon.paramfile"):
        assert read_parameter_file(f) == {5161: 1.5, 5221: 2.0}
    warned = {r.getMessage().split(":")[1] for r in caplog.records}
    assert warned == {"5", "7", "8"}  # the skipped lines that begin with a number look like mistakes


def test_accepts_bom_crlf_exponents_and_signs(tmp_path):
    f = tmp_path / "p.var"
    f.write_bytes(b"\xef\xbb\xbf5161 1e-3\r\n5162 +2.\r\n5163 -.5\r\n5164 -0\r\n")
    values = read_parameter_file(f)
    assert values == {5161: 0.001, 5162: 2.0, 5163: -0.5, 5164: 0.0}


def test_out_of_order_names_the_line(tmp_path):
    f = write_text(tmp_path / "p.var", "header\n5220 1\n5221 0\n5161 0\n")
    err = raises_at(f, 4, "^Parameter file out of order")
    assert "#5161" in err.message and "#5221" in err.message


def test_repeated_number_is_out_of_order(tmp_path):
    f = write_text(tmp_path / "p.var", "5161 0\n5161 1\n")
    raises_at(f, 2, "^Parameter file out of order")


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("0 1", "out of range"),
        ("-3 1", "out of range"),
        (f"{MAX_PARAMETER + 1} 1", "out of range"),
        ("99999999999999999999 1", "out of range"),
        ("5400 3", "read-only"),
        ("5021 0.5", "read-only"),
        ("5428 0.5", "read-only"),
        ("5161.5 1", "not an integer"),
        ("5161 nan", "not a finite number"),
        ("5161 -inf", "not a finite number"),
        ("5161 1e999", "not a finite number"),
        ("5161 1 2", "third number"),
    ],
)
def test_bad_parameter_lines_name_the_line(tmp_path, text, match):
    f = write_text(tmp_path / "p.var", f"31 0\n\n{text}\n")
    raises_at(f, 3, match)


def test_every_number_in_range_that_is_not_read_only_is_accepted(tmp_path):
    numbers = [n for n in range(1, MAX_PARAMETER + 1) if n not in READ_ONLY]
    f = write_text(tmp_path / "p.var", "".join(f"{n} {n / 7!r}\n" for n in numbers))
    values = read_parameter_file(f)
    assert list(values) == numbers
    assert values[MAX_PARAMETER] == MAX_PARAMETER / 7


@pytest.mark.parametrize(
    ("data", "line", "match"),
    [
        (b"5161 0\n5162 \xe9\n", 2, "not UTF-8"),
        (b"5161 0\n5162 0\x00\n", 2, "NUL byte"),
        (b"5161 0\n" + b"5" * 10_000_000, 2, "longer than"),
    ],
)
def test_binary_junk_is_a_clear_error(tmp_path, data, line, match):
    f = tmp_path / "p.var"
    f.write_bytes(data)
    raises_at(f, line, match)


def test_unreadable_path_is_a_gcode_error(tmp_path):
    with pytest.raises(GCodeError, match="cannot read parameter file"):
        read_parameter_file(tmp_path)


# --- writing ----------------------------------------------------------------------------------------

AWKWARD = [0.1, 1 / 3, -2.5e-300, 5e-324, 1.7976931348623157e308, 123456789.12345679, -0.0, 1e16, 42.0]


def test_round_trip_is_exact(tmp_path):
    f = tmp_path / "p.var"
    values = {n: AWKWARD[i % len(AWKWARD)] / (1 + i // len(AWKWARD)) for i, n in enumerate(PERSISTENT)}
    values[31] = 0.1
    values[5000] = -7.0
    write_parameter_file(f, values)
    back = read_parameter_file(f)
    assert back == values
    assert all(math.copysign(1, back[n]) == math.copysign(1, v) for n, v in values.items())


def test_written_lines_are_what_linuxcnc_reads(tmp_path):
    f = tmp_path / "p.var"
    write_parameter_file(f, {5161: 1e-7, 5221: -3.25, 100: 1e22})
    lines = f.read_text().splitlines()
    assert lines, "nothing written"
    for line in lines:
        assert C_LINE.fullmatch(line), line
    numbers = [int(line.split()[0]) for line in lines]
    assert numbers == sorted(numbers)


def test_what_is_written(tmp_path):
    f = tmp_path / "p.var"
    write_parameter_file(f, {5221: 2.0, 100: 3.5, 200: 0.0, 5: 9.0, 5061: 1.0, 5400: 4.0, 5602: 1.0})
    values = read_parameter_file(f)
    # every persistent parameter, zero when not given; non-zero user parameters; nothing else
    assert set(values) == set(PERSISTENT) | {100}
    assert values[5221] == 2.0
    assert values[5161] == 0.0
    assert values[100] == 3.5


def test_parameters_in_the_old_file_are_kept(tmp_path):
    f = write_text(tmp_path / "p.var", "5 1\n200 4\n4000 0\n5161 0\n5500 2\n")
    write_parameter_file(f, {5: 6.0, 200: 0.0, 4000: 0.0, 5500: 8.0, 5221: 1.0})
    values = read_parameter_file(f)
    # user parameters that were in the file stay, even at zero (LinuxCNC keeps them too)
    assert {5: 6.0, 200: 0.0, 4000: 0.0, 5500: 8.0, 5221: 1.0}.items() <= values.items()
    assert set(values) == set(PERSISTENT) | {5, 200, 4000, 5500}


def test_first_save_creates_the_file_without_backup(tmp_path):
    f = tmp_path / "p.var"
    write_parameter_file(f, {})
    assert read_parameter_file(f) == dict.fromkeys(PERSISTENT, 0.0)
    assert not (tmp_path / "p.var.bak").exists()
    assert stray_files(tmp_path) == []


def test_backup_holds_the_previous_values(tmp_path):
    f = tmp_path / "p.var"
    write_parameter_file(f, {5221: 1.0, 77: 7.0})
    write_parameter_file(f, {5221: 2.0})
    assert read_parameter_file(tmp_path / "p.var.bak")[5221] == 1.0
    assert read_parameter_file(tmp_path / "p.var.bak")[77] == 7.0
    assert read_parameter_file(f)[5221] == 2.0
    assert read_parameter_file(f)[77] == 0.0  # was in the file: kept, with its new value


def test_non_finite_value_is_refused_and_nothing_written(tmp_path):
    f = tmp_path / "p.var"
    write_parameter_file(f, {5221: 1.0})
    before = f.read_bytes()
    for bad in (math.nan, math.inf):
        with pytest.raises(GCodeError, match="not a finite number") as info:
            write_parameter_file(f, {5221: bad})
        assert info.value.file == str(f)
        with pytest.raises(GCodeError, match="#100"):
            write_parameter_file(f, {100: bad})
    assert f.read_bytes() == before
    assert stray_files(tmp_path) == []


def test_bad_existing_file_is_left_alone(tmp_path):
    f = write_text(tmp_path / "p.var", "5221 1\n5161 0\n")
    before = f.read_bytes()
    with pytest.raises(GCodeError, match=r"not saved.*out of order") as info:
        write_parameter_file(f, {5221: 2.0})
    assert info.value.line == 2
    assert f.read_bytes() == before


# --- atomicity --------------------------------------------------------------------------------------


class Crash(BaseException):
    """The process dies at this point."""


class StepOs:
    """``os`` as atomicfile sees it: the ``crash_at``-th file system call dies (a write half done);
    after that, the dead process's clean-up (unlink) does not happen."""

    STEPS = ("open", "write", "fsync", "fchmod", "fchown", "link", "replace")

    def __init__(self, crash_at: int | None = None) -> None:
        self.calls: list[str] = []
        self.crash_at = crash_at
        self.crashed = False

    def __getattr__(self, name: str):
        real = getattr(os, name)
        if name == "unlink":
            return lambda *a, **k: None if self.crashed else real(*a, **k)
        if name not in self.STEPS:
            return real

        def step(*args, **kwargs):
            index = len(self.calls)
            self.calls.append(name)
            if index == self.crash_at:
                self.crashed = True
                if name == "write":
                    real(args[0], bytes(args[1])[: len(args[1]) // 2])
                raise Crash(name)
            return real(*args, **kwargs)

        return step


OLD = {n: float(n) for n in PERSISTENT} | {100: 1.0}
NEW = {n: -n / 3 for n in PERSISTENT} | {100: 2.0, 200: 3.0}


def test_crash_at_every_step_leaves_old_or_new_values(tmp_path, monkeypatch):
    probe = StepOs()
    f = tmp_path / "probe.var"
    write_parameter_file(f, OLD)
    monkeypatch.setattr(atomicfile, "os", probe)
    write_parameter_file(f, NEW)
    monkeypatch.undo()
    steps = list(probe.calls)
    assert {"write", "fsync", "replace"} <= set(steps)
    committed = max(i for i, s in enumerate(steps) if s == "replace")

    for k, step in enumerate(steps):
        d = tmp_path / f"crash{k}"
        d.mkdir()
        f = d / "p.var"
        write_parameter_file(f, OLD)
        monkeypatch.setattr(atomicfile, "os", StepOs(crash_at=k))
        with pytest.raises(Crash):
            write_parameter_file(f, NEW)
        monkeypatch.undo()
        expected = NEW if k > committed else OLD
        assert read_parameter_file(f) == expected, f"crash at step {k} ({step})"
        write_parameter_file(f, NEW)  # and the next save works
        assert read_parameter_file(f) == NEW
        assert read_parameter_file(d / "p.var.bak") == expected


@pytest.mark.parametrize("where", ["write", "fsync", "replace"])
def test_os_error_at_each_step_is_a_gcode_error_naming_the_file(tmp_path, monkeypatch, where):
    f = tmp_path / "p.var"
    write_parameter_file(f, OLD)
    before = f.read_bytes()
    real = getattr(os, where)
    count = 0

    def failing(*args, **kwargs):
        nonlocal count
        count += 1
        if where == "write" and count == 1:  # part of the data, then the disk is full
            return real(args[0], bytes(args[1])[:100])
        raise OSError(errno.ENOSPC if where == "write" else errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(atomicfile.os, where, failing)
    with pytest.raises(GCodeError, match="cannot save the parameter file") as info:
        write_parameter_file(f, NEW)
    monkeypatch.undo()
    assert info.value.file == str(f)
    assert f.read_bytes() == before
    assert stray_files(tmp_path) == []


def test_permission_denied_is_a_gcode_error_and_old_file_stays(tmp_path, monkeypatch):
    f = tmp_path / "p.var"
    write_parameter_file(f, OLD)
    before = f.read_bytes()
    real_open = os.open

    def deny(path, flags, *args):
        if flags & os.O_CREAT:
            raise PermissionError(errno.EACCES, "Permission denied", path)
        return real_open(path, flags, *args)

    monkeypatch.setattr(atomicfile.os, "open", deny)
    with pytest.raises(GCodeError, match="Permission denied") as info:
        write_parameter_file(f, NEW)
    monkeypatch.undo()
    assert info.value.file == str(f)
    assert f.read_bytes() == before


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_read_only_directory_for_real(tmp_path):
    """A directory the writer may not write to: as root, a forked child drops to 'nobody' first."""
    d = Path(tempfile.mkdtemp(prefix="canon-ro-", dir="/tmp" if os.path.isdir("/tmp") else None))
    try:
        f = d / "p.var"
        write_parameter_file(f, OLD)
        before = f.read_bytes()
        d.chmod(0o555)
        f.chmod(0o644)
        read_end, write_end = os.pipe()
        pid = os.fork()
        if pid == 0:  # child: report the error text through the pipe and leave at once
            code = 3
            try:
                os.close(read_end)
                if os.geteuid() == 0:
                    os.setgid(65534)
                    os.setuid(65534)
                try:
                    write_parameter_file(f, NEW)
                    os.write(write_end, b"no error")
                    code = 1
                except GCodeError as e:
                    os.write(write_end, str(e).encode())
                    code = 0
            finally:
                os._exit(code)
        os.close(write_end)
        with os.fdopen(read_end, "rb") as pipe:
            message = pipe.read().decode()
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0, message
        assert message.startswith(f"{f}:0: cannot save the parameter file: Permission denied"), message
        assert f.read_bytes() == before
        assert [p.name for p in d.iterdir()] == ["p.var"]
    finally:
        d.chmod(0o755)
        shutil.rmtree(d)


KILL_CHILD = """
import sys, time
from gcode_canon.paramfile import PERSISTENT, write_parameter_file
OLD = {n: float(n) for n in PERSISTENT} | {100: 1.0}
NEW = {n: -n / 3 for n in PERSISTENT} | {100: 2.0, 200: 3.0}
path = sys.argv[1]
write_parameter_file(path, OLD)
print("ready", flush=True)
deadline = time.monotonic() + 30
i = 0
while time.monotonic() < deadline:
    write_parameter_file(path, NEW if i % 2 == 0 else OLD)
    i += 1
"""


def matches_one_of(values: dict[int, float]) -> bool:
    return any(all(values.get(n) == v for n, v in want.items()) for want in (OLD, NEW))


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
def test_sigkill_while_saving_in_a_loop(tmp_path):
    """A real process killed at a random moment while saving: the file always parses, old or new."""
    rng = random.Random(2026)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    for round_ in range(8):
        f = tmp_path / f"kill{round_}.var"
        child = subprocess.Popen(
            [sys.executable, "-c", KILL_CHILD, str(f)], stdout=subprocess.PIPE, env=env, text=True
        )
        try:
            assert child.stdout is not None
            assert child.stdout.readline().strip() == "ready"
            time.sleep(rng.uniform(0.02, 0.3))
        finally:
            child.kill()
            child.wait(timeout=30)
            if child.stdout is not None:
                child.stdout.close()
        assert child.returncode == -signal.SIGKILL  # it was still saving when killed
        assert matches_one_of(read_parameter_file(f)), f"round {round_}"
        bak = tmp_path / f"kill{round_}.var.bak"
        if bak.exists():
            assert matches_one_of(read_parameter_file(bak)), f"round {round_} backup"


# --- properties -------------------------------------------------------------------------------------

JUNK_TOKENS = st.sampled_from(
    ["5161", "5220", "31", "0", "-1", "5603", "1.5", "nan", "inf", "1e999", "#", ";", "x", "\t", " ", "\n",
     "\r", "\x00", "\xe9", "5400", "99999999999999999999", ".", "-", "+", "e5", "1,5", "\ufeff"]
)  # fmt: skip


def joined(tokens: list[str]) -> bytes:
    return "".join(tokens).encode()


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.one_of(st.binary(max_size=400), st.lists(JUNK_TOKENS, max_size=60).map(joined)))
def test_junk_never_raises_anything_but_gcode_error(tmp_path, data):
    f = tmp_path / "junk.var"
    f.write_bytes(data)
    try:
        values = read_parameter_file(f)
    except GCodeError as e:
        assert e.file == str(f) and e.line >= 1
        return
    for n, v in values.items():
        assert 1 <= n <= MAX_PARAMETER and n not in READ_ONLY and math.isfinite(v)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    values=st.dictionaries(
        st.one_of(st.sampled_from(list(PERSISTENT)), st.sampled_from(list(USER))),
        st.floats(allow_nan=False, allow_infinity=False),
        max_size=40,
    )
)
def test_any_finite_values_round_trip(tmp_path, values):
    f = tmp_path / "prop.var"
    if f.exists():
        f.unlink()
    write_parameter_file(f, values)
    back = read_parameter_file(f)
    for n, v in values.items():
        if n in PERSISTENT or v != 0:
            assert back[n] == v and math.copysign(1, back[n]) == math.copysign(1, v)
