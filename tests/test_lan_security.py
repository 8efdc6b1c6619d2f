"""Commands from another host on the LAN: only signed, fresh, never-seen ones are obeyed.

A daemon (``canon daemon``, ``ttl=0`` as shipped) runs in namespace lan-a; from lan-b, joined to it by
a veth pair with the multicast route on it (tests/lan.py), commands are sent with TTL 1, which reach
the daemon: ttl limits what a process sends, not what it accepts. Unsigned, forged (another key),
stale (a 1970 time, right key) and replayed (captured bytes sent again) commands are refused and each
refusal is published as a ``security`` event; a command signed by a key holder is obeyed. An observer
in lan-a records replies, events and status (the daemon's own traffic stays in lan-a: ttl=0).
"""

from __future__ import annotations

import json
import random
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from lan import in_netns, lan, lan_skip_reason

ROOT = Path(__file__).resolve().parent.parent

OBSERVER = r"""
import json, sys, time, lcm
from telemetry.lcmtypes.canon import event, reply, status
lc = lcm.LCM(sys.argv[1])
def out(**kw):
    print(json.dumps(kw), flush=True)
def on_reply(_c, d):
    r = reply.decode(d)
    out(what="reply", sender=r.sender, verb=r.verb, ok=r.ok, error=r.error)
def on_event(_c, d):
    e = event.decode(d)
    if e.kind == "security":
        out(what="security", severity=e.severity, text=e.text)
seen = []
def on_status(_c, d):
    s = status.decode(d)
    if not seen:
        out(what="ready")
    if not seen or seen[-1] != (s.state, s.single_block):
        seen.append((s.state, s.single_block))
        out(what="status", state=s.state, single_block=s.single_block)
lc.subscribe("CANON_REPLY", on_reply); lc.subscribe("CANON_EVENT", on_event)
lc.subscribe("CANON_STATUS", on_status)
end = time.monotonic() + 90
while time.monotonic() < end:
    lc.handle_timeout(100)
"""

LAN_HOST = r"""
import os, sys, time, lcm
from telemetry.auth import sign
from telemetry.commands import make_command
lc = lcm.LCM(sys.argv[1])
key = bytes.fromhex(os.environ["CANON_KEY"])
captured = []
lc.subscribe("CANON_COMMAND", lambda _c, d: captured.append(d))  # a listener on the LAN
def send(cmd):
    lc.publish("CANON_COMMAND", cmd.encode())
    time.sleep(0.3)
    while lc.handle_timeout(0) > 0:
        pass
send(make_command("estop_reset", request_id=1, sender="unsigned"))
send(sign(make_command("estop_reset", request_id=2, sender="forged"), os.urandom(32)))
stale = make_command("estop_reset", request_id=3, sender="stale")
stale.utime = 1_000_000
send(sign(stale, key))
send(sign(make_command("single_block", values=[1], request_id=4, sender="holder"), key))
mine = [d for d in captured if b"holder" in d]
assert mine, "the listener saw the key holder's command"
lc.publish("CANON_COMMAND", mine[0])  # replayed at once: the same bytes
time.sleep(0.3)
send(sign(make_command("estop_reset", request_id=5, sender="holder"), key))
print("done", flush=True)
"""


class Proc:
    def __init__(self, argv: list[str], env: dict[str, str] | None = None) -> None:
        self.lines: list[str] = []
        self.p = subprocess.Popen(argv, cwd=ROOT, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                  bufsize=1, env=env)
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        assert self.p.stdout is not None
        for line in self.p.stdout:
            self.lines.append(line)

    def wait_line(self, pred: Any, timeout: float, what: str) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            found = [line for line in list(self.lines) if pred(line)]
            if found:
                return found[0]
            if self.p.poll() is not None:
                break
            time.sleep(0.05)
        raise AssertionError(f"no {what} within {timeout:g} s:\n" + "".join(self.lines[-40:]))

    def records(self) -> list[dict[str, Any]]:
        return [json.loads(line) for line in list(self.lines) if line.startswith("{")]

    def stop(self) -> int:
        if self.p.poll() is None:
            self.p.terminate()
            try:
                self.p.wait(20)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait(5)
        self._t.join(2)
        return self.p.returncode


def test_lan_host_needs_the_key_and_cannot_replay(tmp_path: Path) -> None:
    reason = lan_skip_reason()
    if reason:
        print(f"skipped: {reason}")
        pytest.skip(reason)
    group = f"239.77.{random.randint(1, 250)}.{random.randint(1, 250)}"
    port = random.randint(20000, 60000)
    daemon_url, lan_url = f"udpm://{group}:{port}?ttl=0", f"udpm://{group}:{port}?ttl=1"
    py = sys.executable
    procs: list[Proc] = []
    with lan() as (ns_a, ns_b):
        try:
            daemon = Proc(in_netns(ns_a, [py, "-m", "motiond.cli", "daemon", "--url", daemon_url,
                                          "--state-dir", str(tmp_path)]))
            procs.append(daemon)
            daemon.wait_line(lambda line: "canon daemon: machine" in line, 60, "daemon start")
            key_file = tmp_path / "command.key"
            assert oct(key_file.stat().st_mode & 0o777) == "0o640"  # created at first start
            observer = Proc(in_netns(ns_a, [py, "-c", OBSERVER, daemon_url]))
            procs.append(observer)
            observer.wait_line(lambda line: '"ready"' in line, 30, "status in lan-a")
            env = {"PATH": "/usr/bin:/bin", "CANON_KEY": key_file.read_text().strip()}
            host = Proc(in_netns(ns_b, [py, "-c", LAN_HOST, lan_url]), env=env)
            procs.append(host)
            host.wait_line(lambda line: line.startswith("done"), 60, "the LAN host's commands")
            assert host.p.wait(30) == 0, "".join(host.lines)  # it ends by itself after "done"
            observer.wait_line(lambda line: '"idle"' in line, 20, "idle after the key holder's estop_reset")
            time.sleep(0.5)  # the last events
            records = observer.records()
        finally:
            codes = [p.stop() for p in reversed(procs)]
    assert codes[-1] == 0, "".join(procs[0].lines)  # the daemon shut down cleanly
    replies = [(r["sender"], r["ok"], r["error"]) for r in records if r["what"] == "reply"]
    assert replies[0][:2] == ("unsigned", False) and replies[0][2].startswith("refused: unsigned command")
    assert replies[1][:2] == ("forged", False) and replies[1][2].startswith("refused: bad MAC")
    assert replies[2][:2] == ("stale", False) and replies[2][2].startswith("refused: stale command")
    assert replies[3] == ("holder", True, "")
    assert replies[4][:2] == ("holder", False) and replies[4][2].startswith("refused: replayed command")
    assert replies[5] == ("holder", True, "")
    assert len(replies) == 6
    security = [r["text"] for r in records if r["what"] == "security"]
    assert [t.split(" refused: ")[0] for t in security] == [
        "command 'estop_reset' from 'unsigned'", "command 'estop_reset' from 'forged'",
        "command 'estop_reset' from 'stale'", "command 'single_block' from 'holder'"]
    states = [(r["state"], r["single_block"]) for r in records if r["what"] == "status"]
    assert states[0] == ("estop", False) and states[-1] == ("idle", True)
    assert ("idle", False) not in states  # nothing the refused commands asked for happened
