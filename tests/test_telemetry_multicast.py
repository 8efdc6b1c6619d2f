"""LCM on the real udpm provider: publish, receive, command, record with ``canon log``, replay.

Everything here joins the multicast group of the default URL, so it is marked ``multicast`` and runs
only inside the private network namespace that tests/run (or tests/netns-run) makes. The last test
makes a namespace of its own *without* a multicast route to see the clear message.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import lcm
import pytest
from keys import TEST_KEY

from telemetry.commands import CommandServer, make_command
from telemetry.generate import lcm_tool
from telemetry.lcmtypes.canon import event, reply, status
from telemetry.publisher import (
    CANON_COMMAND,
    CANON_EVENT,
    CANON_REPLY,
    CANON_STATUS,
    EventPublisher,
    StatusPublisher,
)
from telemetry.url import DEFAULT_URL

ROOT = Path(__file__).resolve().parent.parent
# the console script, as users run it (`python -m motiond.cli` would load cli.py twice)
CANON = str(Path(sys.executable).parent / "canon")


class Listener:
    """A second LCM instance on the URL (as another process would be), collecting decoded messages."""

    def __init__(self, url: str, channels: dict[str, Any]) -> None:
        self.lc = lcm.LCM(url)
        self.got: dict[str, list[Any]] = {ch: [] for ch in channels}
        for ch, cls in channels.items():
            self.lc.subscribe(ch, lambda c, data, cls=cls: self.got[c].append(cls.decode(data)))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.is_set():
            self.lc.handle_timeout(20)

    def wait(self, channel: str, n: int, timeout: float = 5.0) -> list[Any]:
        end = time.monotonic() + timeout
        while len(self.got[channel]) < n and time.monotonic() < end:
            time.sleep(0.01)
        return self.got[channel]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)


def make_status(seq: int) -> status:
    s = status()
    s.utime = seq
    s.seq = seq
    s.machine = "demo mill"
    s.state = "running"
    s.axis_names, s.num_axes = ["x", "y", "z"], 3
    s.homed = [True] * 3
    s.commanded = [seq * 0.1, 0.0, -1.0]
    s.actual = [seq * 0.1, 0.0, -1.0]
    s.velocity = [5.0, 0.0, 0.0]
    s.following_error = [0.0] * 3
    return s


@pytest.mark.multicast
def test_status_and_events_on_the_default_url() -> None:
    listener = Listener(DEFAULT_URL, {CANON_STATUS: status, CANON_EVENT: event})
    lc = lcm.LCM(DEFAULT_URL)
    try:
        with StatusPublisher(lc, 50) as sp, EventPublisher(lc) as ep:
            sp.update(make_status(7))
            ep.emit(event.ERROR, "drive 3: following error", kind="drive_fault", source="canopen",
                    file="part.ngc", line=12)
            statuses = listener.wait(CANON_STATUS, 10)
            events = listener.wait(CANON_EVENT, 1)
    finally:
        listener.close()
    assert len(statuses) >= 10
    assert statuses[-1].seq == 7 and list(statuses[-1].commanded) == pytest.approx([0.7, 0.0, -1.0])
    assert list(statuses[-1].axis_names) == ["x", "y", "z"]
    first = events[0]
    assert (first.severity, first.text, first.line) == (event.ERROR, "drive 3: following error", 12)


@pytest.mark.multicast
def test_command_and_reply_between_two_lcm_instances() -> None:
    server_lc = lcm.LCM(DEFAULT_URL)
    server = CommandServer(server_lc, lambda cmd: None, key=TEST_KEY, url=DEFAULT_URL).start()
    client = Listener(DEFAULT_URL, {CANON_REPLY: reply})
    try:
        cmd = make_command("feed_override", values=[0.8], request_id=31, sender="test-client", key=TEST_KEY)
        deadline = time.monotonic() + 5
        # the server's subscription may still be settling: resend until answered (bounded)
        while not client.got[CANON_REPLY] and time.monotonic() < deadline:
            client.lc.publish(CANON_COMMAND, cmd.encode())
            client.wait(CANON_REPLY, 1, 0.2)
    finally:
        client.close()
        server.stop()
    first = client.got[CANON_REPLY][0]
    assert (first.request_id, first.sender, first.verb, first.ok, first.error) == (
        31, "test-client", "feed_override", True, "")


@pytest.mark.multicast
def test_canon_log_records_a_file_that_replays(tmp_path: Path) -> None:
    path = tmp_path / "run.lcmlog"
    proc = subprocess.Popen([CANON, "log", str(path), "--duration", "3",
                             "--channels", "CANON_.*"], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    lc = lcm.LCM(DEFAULT_URL)
    seq = 0
    try:
        deadline = time.monotonic() + 20
        while proc.poll() is None and time.monotonic() < deadline:
            seq += 1
            lc.publish(CANON_STATUS, make_status(seq).encode())
            lc.publish("OTHER_CHANNEL", b"not recorded")
            time.sleep(0.02)
        _, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    assert proc.returncode == 0, err
    assert f"{path}:" in err and "CANON_STATUS" in err and "lcm-logplayer" in err

    log = lcm.EventLog(str(path), "r")
    recorded = [(e.channel, status.decode(e.data).seq) for e in log]
    log.close()
    assert {ch for ch, _ in recorded} == {CANON_STATUS}
    seqs = [s for _, s in recorded]
    assert len(seqs) >= 50 and seqs == sorted(seqs) and seqs[-1] <= seq

    # lcm-logplayer publishes the same messages again (5x speed), as lcm-spy would see them
    listener = Listener(DEFAULT_URL, {CANON_STATUS: status})
    try:
        player = subprocess.run([str(lcm_tool("lcm-logplayer")), "--speed=5", f"--lcm-url={DEFAULT_URL}",
                                 str(path)], capture_output=True, text=True, timeout=30)
        replayed = listener.wait(CANON_STATUS, len(seqs), 5)
    finally:
        listener.close()
    assert player.returncode == 0, player.stderr
    assert [m.seq for m in replayed] == seqs


def _netns_available() -> str | None:
    if os.geteuid() != 0:
        return "needs root to make a network namespace"
    if shutil.which("ip") is None:
        return "needs iproute2 (ip)"
    return None


@pytest.mark.skipif(_netns_available() is not None, reason=str(_netns_available()))
def test_no_multicast_route_gives_the_clear_message_and_canon_run_can_carry_on() -> None:
    """In a namespace with loopback up but no multicast route, as on an offline PC or in a container.

    Nothing can leave such a namespace, and no group is joined (LCM fails before that).
    """
    ns = f"canon-noroute-{uuid.uuid4().hex[:8]}"
    subprocess.run(["ip", "netns", "add", ns], check=True, timeout=30)
    try:
        subprocess.run(["ip", "netns", "exec", ns, "ip", "link", "set", "lo", "up"], check=True, timeout=30)
        script = (
            "import lcm\n"
            "from telemetry.publisher import open_lcm, TelemetryUnavailable\n"
            "try:\n"
            "    lcm.LCM('udpm://239.255.76.67:7667?ttl=0')\n"
            "    print('RAW: opened')\n"
            "except RuntimeError as exc:\n"
            "    print('RAW:', exc)\n"
            "try:\n"
            "    open_lcm()\n"
            "except TelemetryUnavailable as exc:\n"
            "    print('CLEAR:', exc)\n"
            "lc = open_lcm(fallback='memq')\n"
            "print('FALLBACK:', type(lc).__name__, lc is not None)\n"
        )
        proc = subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-c", script], cwd=ROOT,
                              capture_output=True, text=True, timeout=60)
        cli = subprocess.run(["ip", "netns", "exec", ns, CANON, "log",
                              "/nonexistent-dir/x.log"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    finally:
        subprocess.run(["ip", "netns", "del", ns], timeout=30)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert "RAW: Couldn't create LCM" in out  # what LCM itself gives: the reason we wrap it
    clear = next(line for line in out.splitlines() if line.startswith("CLEAR:"))
    assert "no route to the multicast group 239.255.76.67" in clear
    assert "ip link set lo multicast on" in clear and "ip route add 224.0.0.0/4 dev lo" in clear
    assert "FALLBACK: LCM True" in out
    assert "ip route add 224.0.0.0/4 dev lo" in proc.stderr  # the warning logged by the fallback
    assert cli.returncode == 1 and "Traceback" not in cli.stderr
    assert "ip route add 224.0.0.0/4 dev lo" in cli.stderr
