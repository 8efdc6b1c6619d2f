"""An E-stop takes effect at once while another process floods the daemon with commands.

The machine (simulated drives) runs a long move in this process with its command server on udpm; a
second process sends 1,000 valid, signed commands per second (``feed_override``, which goes the
urgent way, and ``single_block``, rate-limited per client). The E-stop published meanwhile must put
the machine in ESTOP with every drive quick-stopping within 50 ms: a safety bound, measured with a
bounded loop. Every flood command is answered (accepted, or refused with a reason), none silently lost
before the end. Joins a multicast group: ``multicast`` (tests/run's namespace).
"""

from __future__ import annotations

import random
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import lcm
import pytest
from keys import TEST_KEY

from motiond.cmd_daemon import start
from motiond.config import load_machine
from motiond.states import State
from telemetry.commands import make_command
from telemetry.config import TelemetryConfig
from telemetry.url import with_receive_buffer

ROOT = Path(__file__).resolve().parent.parent
ESTOP_BOUND_S = 0.050

FLOOD = r"""
import sys, time, lcm
from telemetry.commands import make_command
key = bytes.fromhex(sys.argv[2]); rate = 1000.0; seconds = float(sys.argv[3])
lc = lcm.LCM(sys.argv[1])
sent = 0
t0 = time.monotonic()
print("flooding", flush=True)
while True:
    now = time.monotonic()
    if now - t0 > seconds:
        break
    due = int((now - t0) * rate) + 1
    while sent < due:
        if sent % 2:
            cmd = make_command("single_block", values=[0], request_id=sent + 1, sender="flood", key=key)
        else:
            cmd = make_command("feed_override", values=[1.0], request_id=sent + 1, sender="flood", key=key)
        lc.publish("CANON_COMMAND", cmd.encode())
        sent += 1
    time.sleep(0.0005)
print(f"sent {sent} in {time.monotonic() - t0:.2f} s", flush=True)
"""

PROGRAM = "G21 G90 G94\nG1 X150 F6000\nM2\n"


@pytest.mark.multicast
def test_estop_during_a_flood_of_commands_takes_effect_within_50_ms(tmp_path: Path) -> None:
    group = f"239.78.{random.randint(1, 250)}.{random.randint(1, 250)}"
    # as the daemon opens it: with a receive buffer for bursts (telemetry.url.with_receive_buffer)
    url = with_receive_buffer(f"udpm://{group}:{random.randint(20000, 60000)}?ttl=0")
    lc = lcm.LCM(url)
    replies: list[Any] = []
    from telemetry.lcmtypes.canon import reply

    def on_reply(_ch: str, data: bytes) -> None:
        r = reply.decode(data)
        if r.sender == "flood":
            replies.append((r.request_id, r.ok, r.error))

    machine, server = start(load_machine(None), lc, TelemetryConfig(url=url), key=TEST_KEY,
                            var_file=tmp_path / "p.var", late_fault_s=2.0)
    listener = lcm.LCM(url)
    listener.subscribe("CANON_REPLY", on_reply).set_queue_capacity(100_000)  # LCM's default: 30
    stop_listening = threading.Event()

    def listen() -> None:
        while not stop_listening.is_set():
            listener.handle_timeout(50)

    lt = threading.Thread(target=listen, daemon=True)
    lt.start()
    flood: subprocess.Popen[str] | None = None
    try:
        machine.bring_up()
        prog = tmp_path / "long.ngc"
        prog.write_text(PROGRAM)
        job = machine.run(prog)
        flood = subprocess.Popen([sys.executable, "-c", FLOOD, url, TEST_KEY.hex(), "2.5"], cwd=ROOT,
                                 text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        assert flood.stdout is not None
        assert flood.stdout.readline().startswith("flooding")
        r0 = server.replies
        time.sleep(1.0)  # the flood in full swing, the machine moving
        assert machine.states.state is State.RUNNING
        flood_answered = server.replies - r0
        estop = make_command("estop", request_id=1, sender="operator", key=TEST_KEY)
        t0 = time.monotonic()
        lc.publish("CANON_COMMAND", estop.encode())
        took = None
        for _ in range(2000):  # bounded: at most 2000 polls of ~1 ms
            if machine.states.state is State.ESTOP and all(
                    d.state.name != "OPERATION_ENABLED" for d in machine.sim_drives):
                took = time.monotonic() - t0
                break
            time.sleep(0.001)
        still_flooding = flood.poll() is None
        out, _ = flood.communicate(timeout=30)
        flood = None
        assert job.done.wait(10)
        time.sleep(0.5)  # the last replies
    finally:
        if flood is not None:
            flood.kill()
            flood.wait(5)
        stop_listening.set()
        lt.join(2)
        server.stop()
        machine.shutdown()
    assert took is not None, "the E-stop never took effect"
    print(f"E-stop took effect after {took * 1e3:.1f} ms during the flood")
    assert took < ESTOP_BOUND_S, f"E-stop took {took * 1e3:.1f} ms during the flood"
    assert flood_answered > 500 and still_flooding  # the E-stop came in the middle of the flood
    sent = int(out.split("sent ")[1].split()[0])
    assert sent >= 2000, out
    # none silently dropped: each flood command got a reply (accepted, or refused with the reason)
    ids = {rid for rid, _, _ in replies}
    missing = sorted(set(range(1, sent + 1)) - ids)
    assert len(ids) == sent, (f"{sent - len(ids)} of {sent} flood commands got no reply: {missing[:50]}; "
                              f"server replies {server.replies} refused {server.refused} "
                              f"limited {server.rate_limited} errors {server.errors}")
    refused = [e for _, ok, e in replies if not ok]
    assert any(e.startswith("refused: rate limit") for e in refused)
