"""canon's local bus (``canon_local``, fieldbus/canopen/localbus.py): CAN frames between processes of
this computer over AF_UNIX sockets, no network (runs anywhere, no namespace needed).

Frames cross between two processes both ways, every flag kept, each sender's frames in order; a
socket file left by a process that died is removed by the next sender and does not stop it; a peer
that does not read (stopped by SIGSTOP) neither blocks the sender nor keeps the frames from a peer
that reads; the channel directory is private to the user. CANopen over it (boot, SDO, PDO, the whole
machine) runs in tests/test_canopen_multiprocess.py (its ``canon_local`` bus) and
tests/test_motion_process.py.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from fieldbus.canopen.localbus import LocalBus, channel_dir

ROOT = Path(__file__).resolve().parent.parent
pytestmark = [pytest.mark.timeout(120)]


@pytest.fixture
def bus_dir(monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A short private directory for the channels (``CANON_BUS_DIR``: socket paths are short), also
    for the child processes."""
    with tempfile.TemporaryDirectory(prefix="lb") as d:
        root = Path(d) / "bus"
        monkeypatch.setenv("CANON_BUS_DIR", str(root))
        yield root


CHILD = """
import sys, time, can
from fieldbus.canopen.localbus import LocalBus
bus = LocalBus(channel=sys.argv[1])
print("up", bus.name, flush=True)
mode = sys.argv[2]
if mode == "echo":  # frames back, id + 1, until id 0x7FF
    while True:
        m = bus.recv(30.0)
        if m is None or m.arbitration_id == 0x7FF:
            break
        bus.send(can.Message(arbitration_id=m.arbitration_id + 1, data=m.data, dlc=m.dlc,
                             is_extended_id=m.is_extended_id, is_remote_frame=m.is_remote_frame,
                             is_fd=m.is_fd, bitrate_switch=m.bitrate_switch, is_error_frame=m.is_error_frame))
elif mode == "burst":  # numbered frames as fast as it can, a window at a time, then the end mark
    n, window = int(sys.argv[3]), int(sys.argv[4])
    for i in range(n):
        if i and i % window == 0:  # the reader has all the frames before this window
            m = bus.recv(30.0)
            assert m is not None and m.arbitration_id == 0x7FE, m
        bus.send(can.Message(arbitration_id=0x181, data=i.to_bytes(4, "little"), is_extended_id=False))
    bus.send(can.Message(arbitration_id=0x7FF, is_extended_id=False))
    time.sleep(2.0)
elif mode == "sleep":  # a bus that never reads
    time.sleep(60.0)
bus.shutdown()
print("done", flush=True)
"""


def child(channel: str, mode: str, *args: str) -> tuple[subprocess.Popen[str], str]:
    """A process with a bus on ``channel`` (CHILD's ``mode``), up when this returns; and its bus's name."""
    proc = subprocess.Popen([sys.executable, "-c", CHILD, channel, mode, *args], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line.startswith("up"), (line, proc.stderr.read() if proc.stderr else "")
    return proc, line.split()[1]


def test_the_bus_is_a_python_can_interface(bus_dir: Path) -> None:
    with can.Bus(interface="canon_local", channel="iface", bitrate=1_000_000) as a, \
            can.Bus(interface="canon_local", channel="iface", receive_own_messages=True) as b:
        assert isinstance(a, LocalBus) and a.dir == bus_dir / "iface"
        b.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))  # SYNC
        seen = [b.recv(5.0), a.recv(5.0)]
        assert [m.arbitration_id if m else None for m in seen] == [0x80, 0x80]
        assert not seen[0].is_rx and seen[1].is_rx  # type: ignore[union-attr]
        assert a.recv(0.05) is None, "its own frames come back only where asked for"
    assert not (bus_dir / "iface").exists(), "the last bus out removes the channel's directory"


def test_frames_cross_between_processes_both_ways_with_every_flag(bus_dir: Path) -> None:
    proc, _ = child("flags", "echo")
    frames = [
        can.Message(arbitration_id=0x601, data=bytes([0x40, 0x41, 0x60, 0, 0, 0, 0, 0]),
                    is_extended_id=False),
        can.Message(arbitration_id=0x1ABCDE0, data=b"\x01\x02", is_extended_id=True),
        can.Message(arbitration_id=0x700, is_remote_frame=True, dlc=1, is_extended_id=False),
        can.Message(arbitration_id=0x300, data=bytes(range(64)), is_fd=True, bitrate_switch=True,
                    is_extended_id=False),
        can.Message(arbitration_id=0x080, data=b"", is_extended_id=False),
        can.Message(arbitration_id=0x004, data=b"\x00\x10", is_error_frame=True, is_extended_id=False),
    ]
    try:
        with LocalBus("flags") as bus:
            for m in frames:
                bus.send(m)
            bus.send(can.Message(arbitration_id=0x7FF, is_extended_id=False))
            back = [bus.recv(10.0) for _ in frames]
    finally:
        proc.wait(10.0)
    assert all(b is not None for b in back), back
    for sent, got in zip(frames, back, strict=True):
        assert got is not None and got.arbitration_id == sent.arbitration_id + 1
        assert (got.is_extended_id, got.is_remote_frame, got.is_fd, got.bitrate_switch, got.is_error_frame,
                got.dlc, bytes(got.data)) == (sent.is_extended_id, sent.is_remote_frame, sent.is_fd,
                                              sent.bitrate_switch, sent.is_error_frame, sent.dlc,
                                              bytes(sent.data))
        assert got.channel == "flags" and got.is_rx and abs(got.timestamp - time.time()) < 30.0


def test_a_senders_frames_arrive_all_and_in_order(bus_dir: Path) -> None:
    """20,000 frames as fast as the child can send them (10 s of a 2 ms cycle with three drives):
    every one, in order, at a reader that keeps up.

    The child sends 1,000 frames at a time and waits for the reader's word before the next 1,000, so
    the reader keeps up even on a loaded machine: a reader that falls behind by a connection's buffer
    (some 5,000 frames, ``SEND_BUFFER``) loses the frames past it, by design (the next test)."""
    n, window = 20_000, 1_000
    got: list[can.Message] = []
    with LocalBus("order") as bus:
        proc, _ = child("order", "burst", str(n), str(window))
        try:
            deadline = time.monotonic() + 60.0
            while time.monotonic() < deadline:
                m = bus.recv(0.5)
                if m is None:
                    continue
                if m.arbitration_id == 0x7FF:
                    break
                got.append(m)
                if len(got) % window == 0:
                    bus.send(can.Message(arbitration_id=0x7FE, is_extended_id=False))
            else:
                raise AssertionError(f"no end mark in 60 s; got {len(got)} frames")
        finally:
            proc.wait(10.0)
    assert [int.from_bytes(m.data, "little") for m in got] == list(range(n))


def test_a_dead_processes_socket_file_is_removed_and_the_sender_goes_on(bus_dir: Path) -> None:
    proc, name = child("dead", "sleep")
    with LocalBus("dead") as sender, LocalBus("dead") as listener:
        sender.send(can.Message(arbitration_id=0x80, is_extended_id=False))  # connected to both
        assert listener.recv(5.0) is not None
        assert (bus_dir / "dead" / name).exists()
        proc.kill()  # its socket file stays behind
        proc.wait(10.0)
        assert (bus_dir / "dead" / name).exists()
        for i in range(3):
            sender.send(can.Message(arbitration_id=0x181, data=bytes([i]), is_extended_id=False))
        assert not (bus_dir / "dead" / name).exists(), "the dead process's socket file was left"
        assert [bytes(m.data)[0] for m in (listener.recv(5.0), listener.recv(5.0), listener.recv(5.0))
                if m is not None] == [0, 1, 2]
        # a file left where nobody listens (a crash before this bus was up) is found by a listing too
        import socket

        stale = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        stale.bind(str(bus_dir / "dead" / "1-1-000000.sock"))
        stale.close()
        time.sleep(0.01)
        sender.send(can.Message(arbitration_id=0x80, is_extended_id=False))
        assert not (bus_dir / "dead" / "1-1-000000.sock").exists()
        assert listener.recv(5.0) is not None


def test_a_peer_that_does_not_read_blocks_neither_the_sender_nor_the_others(bus_dir: Path) -> None:
    """A process stopped by SIGSTOP (alive, its socket open) on the bus: the sender's sends return at
    once, its frames dropped (counted) once its connection's buffer is full; a peer that reads gets
    every frame."""
    proc, _ = child("stall", "sleep")
    os.kill(proc.pid, signal.SIGSTOP)
    n = 3_000
    try:
        with LocalBus("stall", send_buffer=64 * 1024) as sender, LocalBus("stall") as reader:
            got: list[int] = []
            slowest = 0.0
            for i in range(n):
                t0 = time.perf_counter()
                sender.send(can.Message(arbitration_id=0x181, data=i.to_bytes(2, "little"),
                                        is_extended_id=False))
                slowest = max(slowest, time.perf_counter() - t0)
                while (m := reader.recv(0.0)) is not None:
                    got.append(int.from_bytes(m.data, "little"))
            got += [int.from_bytes(m.data, "little") for m in iter(lambda: reader.recv(0.5), None)]
            dropped = sender.dropped
    finally:
        os.kill(proc.pid, signal.SIGCONT)
        proc.kill()
        proc.wait(10.0)
    assert got == list(range(n)), f"the reading peer lost frames: {len(got)} of {n}"
    assert 0 < dropped < n, dropped  # the stopped peer's, once its 64 KiB were full
    assert slowest < 0.5, f"a send waited {slowest * 1e3:.0f} ms"  # never for the stopped peer


def test_the_channel_directory_is_private(bus_dir: Path) -> None:
    with LocalBus("private"):
        mode = os.stat(bus_dir / "private").st_mode & 0o777
        assert mode == 0o700 and os.stat(bus_dir).st_mode & 0o777 == 0o700
    open_dir = bus_dir / "open"
    open_dir.mkdir(mode=0o700)
    open_dir.chmod(0o777)  # anyone could listen or send there
    with pytest.raises(can.CanInitializationError, match="only it may write"):
        LocalBus("open")
    with pytest.raises(can.CanInitializationError, match="a name of"):
        LocalBus("../elsewhere")


def test_named_channels_live_in_the_runtime_directory(monkeypatch: pytest.MonkeyPatch,
                                                      tmp_path: Path) -> None:
    monkeypatch.delenv("CANON_BUS_DIR", raising=False)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    assert channel_dir("demo") == tmp_path / "canon" / "bus" / "demo"
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    assert channel_dir("demo") == Path(f"/tmp/canon-{os.getuid()}/bus/demo")
    assert channel_dir("/run/mill/bus") == Path("/run/mill/bus")


def test_the_machine_file_checks_a_local_channel_with_its_key(tmp_path: Path) -> None:
    from motiond.config_canopen import canopen_from_file
    from motiond.configkit import ConfigError

    data = {"canopen": {"interface": "canon_local", "channel": "a/b", "axes": {"x": {"node_id": 1}}},
            "axes": {"x": {"max_velocity": 10.0}}}
    with pytest.raises(ConfigError, match=r"canopen\.channel.*canon_local needs a name"):
        canopen_from_file(data, "m.toml")
    data["canopen"]["channel"] = "mill-1"  # type: ignore[index]
    assert canopen_from_file(data, "m.toml").bus.bus_kwargs() == {"interface": "canon_local",
                                                                  "channel": "mill-1"}
