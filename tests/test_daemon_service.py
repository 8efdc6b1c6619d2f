"""The daemon's slow operations (enable, home ...) run on its service thread, never on the command thread.

A machine with simulated drives on a private virtual bus and telemetry on a private ``memq://``
instance (no multicast), its command server handling that instance on a thread as in the daemon.
Axis X homes with CiA 402 homing mode 6 towards a simulated home switch, so a homing takes as long
as the test wants (the simulated drive travels at the EDS's 100000 counts/s, 10 mm/s here).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import lcm
import pytest
from keys import TEST_KEY

from fieldbus.canopen.cia402 import State as DriveState
from motiond.cli import main
from motiond.cmd_daemon import start
from motiond.config import load_machine
from motiond.control_client import SERVICE_VERBS, send_command, shared_memq
from motiond.runtime import SERVICE_JOIN_S
from telemetry.commands import CommandServer, make_command
from telemetry.config import TelemetryConfig
from telemetry.lcmtypes.canon import event

MACHINE = """
[machine]
name = "service test"
cycle_ms = 2.0

[axes.x]
max_velocity = 200.0
max_acceleration = 2000.0
max_jerk = 50000.0

[axes.y]
max_velocity = 200.0
max_acceleration = 2000.0
max_jerk = 50000.0

[axes.z]
max_velocity = 100.0
max_acceleration = 1500.0
max_jerk = 40000.0

[canopen]
interface = "virtual"
channel = "service"
simulate = true
homing_timeout_s = {homing_timeout_s}

[canopen.axes.x]
node_id = 1
counts_per_unit = 10000
homing = "cia402"
homing_method = 19

[canopen.axes.y]
node_id = 2
counts_per_unit = 10000

[canopen.axes.z]
node_id = 3
counts_per_unit = 10000
"""

FAST = 0.5
"""A command that does not wait for the drives is answered well within this (seconds)."""
SLOW_HOME_COUNTS = 3_000_000
"""Home switch 300 mm away: 30 s of homing at 10 mm/s, far longer than any test waits."""


def machine_file(tmp: Path, homing_timeout_s: float = 60.0) -> str:
    path = tmp / "machine.toml"
    path.write_text(MACHINE.format(homing_timeout_s=homing_timeout_s))
    return str(path)


def command(verb: str, strings: tuple[str, ...] = (), values: tuple[float, ...] = (),
            request_id: int = 1) -> Any:
    return make_command(verb, strings, values, request_id=request_id, sender="test")


class Rig:
    """The machine and its command server on ``lc``; the events it publishes, as they arrive."""

    def __init__(self, tmp: Path, lc: Any, *, homing_timeout_s: float = 60.0, threaded: bool = True) -> None:
        self.lc = lc
        self.events: list[Any] = []
        self._lock = threading.Lock()
        self.sub = lc.subscribe("CANON_EVENT", self._on_event)
        config = load_machine(machine_file(tmp, homing_timeout_s))
        if threaded:  # as the daemon runs: the server handles lc on its own thread
            self.machine, self.server = start(config, lc, TelemetryConfig(url="memq://"), key=TEST_KEY,
                                              var_file=tmp / "params.var")
        else:  # the server only subscribed: a client's own lc.handle() delivers (canon ctl)
            from motiond.runtime import Machine

            self.machine = Machine(config, lc=lc, telemetry=TelemetryConfig(url="memq://"),
                                   var_file=tmp / "params.var").start()
            self.server = CommandServer(lc, self.machine.handle_command, key=TEST_KEY, url="memq://")
            self.server.subscribe()

    def _on_event(self, _ch: str, data: bytes) -> None:
        with self._lock:
            self.events.append(event.decode(data))

    def ready(self) -> None:
        """estop_reset and enable through the command channel, waiting for their results."""
        for verb in ("estop_reset", "enable"):
            rep = send_command(self.lc, verb, timeout=5.0, handle=False, wait_result=10.0)
            assert rep.ok, f"{verb}: {rep.error}"

    def wait_event(self, pred: Callable[[Any], bool], timeout: float = 10.0, what: str = "") -> Any:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                found = [e for e in self.events if pred(e)]
            if found:
                return found[0]
            time.sleep(0.01)
        with self._lock:
            seen = [(e.kind, e.text) for e in self.events[-10:]]
        raise AssertionError(f"no event {what} within {timeout:g} s; the last ones: {seen}")

    def close(self) -> None:
        self.server.stop()
        self.machine.shutdown()
        self.lc.unsubscribe(self.sub)


def wait_for(pred: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout:g} s: {what}")
        time.sleep(0.005)


def timed(fn: Callable[[], Any]) -> tuple[Any, float]:
    t = time.monotonic()
    result = fn()
    return result, time.monotonic() - t


def result_of(rig: Rig, verb: str, request_id: int, timeout: float = 10.0) -> Any:
    """The event that reports the result of the request (sender 'test')."""
    tag = f"(request {request_id} from test)"
    return rig.wait_event(lambda e: e.kind == "command" and tag in e.text and e.text.startswith(verb),
                          timeout, f"with the result of {verb} {tag}")


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    r = Rig(tmp_path, lcm.LCM("memq://"))
    try:
        yield r
    finally:
        r.close()


def start_slow_homing(rig: Rig, request_id: int = 1) -> None:
    m = rig.machine
    sim_x = m.sim_drives[0]
    sim_x.home_switch_counts = SLOW_HOME_COUNTS
    rep, took = timed(lambda: m.handle_command(command("home", ("x",), request_id=request_id)))
    assert rep is None, rep
    assert took < FAST, f"home was answered after {took:.2f} s: the command thread waited for it"
    # the drive travels towards its home switch on its own (CiA 402 homing mode)
    wait_for(lambda: sim_x.actual > 5000, 5.0, "the X drive homing")
    assert m.busy() == "homing axis x"


def test_estop_during_homing_is_answered_at_once_and_fails_the_homing(rig: Rig) -> None:
    m = rig.machine
    rig.ready()
    start_slow_homing(rig)
    sim_x = m.sim_drives[0]
    status = m.status()
    assert status.state == "homing" and status.enabled

    # the other commands are answered at once: the slow verbs and motion refused, busy
    for verb, strings, values in (("home", ("y",), ()), ("enable", (), ()), ("disable", (), ()),
                                  ("mdi", ("G0 X1",), ()), ("jog", ("y",), (10.0, 1.0))):
        rep, took = timed(lambda verb=verb, strings=strings, values=values: m.handle_command(
            command(verb, strings, values, request_id=50)))
        assert took < FAST, f"{verb} answered after {took:.2f} s"
        assert rep == "busy: homing axis x", f"{verb}: {rep!r}"
    rep, took = timed(lambda: m.handle_command(command("feed_override", values=(0.5,))))
    assert rep is None and took < FAST

    moved = sim_x.actual
    rep, took = timed(lambda: m.handle_command(command("estop")))
    assert rep is None
    assert took < FAST, f"estop answered after {took:.2f} s, behind the homing"
    # motion stops at once: the drive homing leaves Operation enabled (quick stop), nothing streams
    assert not m.master.streaming
    wait_for(lambda: sim_x.state != DriveState.OPERATION_ENABLED, FAST, "the X drive quick-stopped")
    stopped_at = sim_x.actual
    assert stopped_at - moved < 0.5 * 100_000  # under half a second of homing travel
    time.sleep(0.2)
    assert sim_x.actual == stopped_at

    # the homing ends failed, with an ERROR event naming the axis and why
    failed = result_of(rig, "home", 1)
    assert failed.severity == event.ERROR
    assert failed.text.startswith("home failed (request 1 from test): homing axis x interrupted by E-stop")
    assert "axis x" in failed.text.split(":", 1)[1]
    wait_for(lambda: m.busy() == "", 2.0, "the service thread free again")
    s = m.status()
    assert s.state == "estop" and not s.enabled and s.homed == [False, False, False]
    assert m.planner is None
    assert all(sim.state != DriveState.OPERATION_ENABLED for sim in m.sim_drives)
    assert not any(e.kind == "homed" for e in rig.events)


def test_a_second_slow_operation_is_refused_busy_and_the_first_one_goes_on(rig: Rig) -> None:
    m = rig.machine
    rig.ready()
    start_slow_homing(rig, request_id=7)
    for verb in sorted(SERVICE_VERBS):
        rep = send_command(rig.lc, verb, timeout=FAST, handle=False, request_id=8)
        assert not rep.ok and rep.error == "busy: homing axis x", (verb, rep)
    # refusals change nothing: the homing carries on
    before = m.sim_drives[0].actual
    wait_for(lambda: m.sim_drives[0].actual > before + 1000, 2.0, "X still homing")
    assert m.busy() == "homing axis x"
    # 'abort' is answered at once too (the axis being homed is the drive's own motion; E-stop stops it)
    rep, took = timed(lambda: m.handle_command(command("abort")))
    assert rep is None and took < FAST


def test_home_through_the_command_channel_returns_at_once_and_reports_homed(rig: Rig) -> None:
    m = rig.machine
    rig.ready()
    m.sim_drives[0].home_switch_counts = 80_000  # 0.8 s of homing
    rep, took = timed(lambda: m.handle_command(command("home", ("x", "y"), request_id=3)))
    assert rep is None and took < FAST, (rep, took)
    assert not m.status().homed[0]  # not done yet: answered before the drive got there
    done = result_of(rig, "home", 3)
    assert done.severity == event.INFO and done.text == "home done (request 3 from test)"
    homed = [e.text for e in rig.events if e.kind == "homed"]
    assert homed == ["axis x homed", "axis y homed"]
    s = m.status()
    assert s.homed == [True, True, False] and s.state == "idle" and s.enabled
    # and a blocking client (send_command waits for the result) gets the result as the reply
    rep = send_command(rig.lc, "home", ["z"], timeout=5.0, handle=False, wait_result=10.0)
    assert rep.ok and rep.error == "", rep
    assert m.status().homed == [True, True, True]


def test_a_failed_homing_is_an_error_event_and_the_reply_of_a_waiting_client(tmp_path: Path) -> None:
    rig = Rig(tmp_path, lcm.LCM("memq://"), homing_timeout_s=0.3)
    try:
        rig.ready()
        rig.machine.sim_drives[0].home_switch_counts = SLOW_HOME_COUNTS
        rep = send_command(rig.lc, "home", ["x"], timeout=5.0, handle=False, wait_result=10.0)
        assert not rep.ok
        assert rep.error.startswith("homing failed: node 1 (axis x): homing not attained within 0.3 s"), rep
        failed = rig.wait_event(lambda e: e.kind == "command" and e.text.startswith("home failed"))
        assert failed.severity == event.ERROR and "axis x" in failed.text
        assert not rig.machine.status().homed[0]
    finally:
        rig.close()


def test_estop_during_enabling_leaves_no_drive_enabled(rig: Rig, monkeypatch: pytest.MonkeyPatch) -> None:
    """The master walks the drives to Operation enabled one after the other: an E-stop half-way
    quick-stops those enabled so far, and the walk then enables the rest unless the operation stops
    them again when it fails."""
    m = rig.machine
    rep = send_command(rig.lc, "estop_reset", timeout=5.0, handle=False, wait_result=10.0)
    assert rep.ok, rep.error
    walking, go_on = threading.Event(), threading.Event()
    enable_drive = m.master._enable_drive

    def slow_second_drive(d: Any) -> None:
        if d.cfg.node_id == 2:
            walking.set()
            go_on.wait(5.0)
        enable_drive(d)

    monkeypatch.setattr(m.master, "_enable_drive", slow_second_drive)
    rep, took = timed(lambda: m.handle_command(command("enable", request_id=11)))
    assert rep is None and took < FAST
    assert walking.wait(5.0)
    rep = m.handle_command(command("enable", request_id=12))
    assert rep == "busy: enabling the drives"
    rep, took = timed(lambda: m.handle_command(command("estop")))
    assert rep is None and took < FAST
    go_on.set()  # the walk goes on to drives 2 and 3
    failed = result_of(rig, "enable", 11)
    assert failed.severity == event.ERROR
    assert failed.text.startswith("enable failed (request 11 from test): enabling the drives interrupted by "
                                  "E-stop")
    s = m.status()
    assert s.state == "estop" and not s.enabled and not m.master.streaming
    # the quick stop went out before the result; the simulated drives take it on their bus thread
    wait_for(lambda: [sim.controlword for sim in m.sim_drives] == [0x0002] * 3
             and DriveState.OPERATION_ENABLED not in [sim.state for sim in m.sim_drives], 1.0,
             "every drive quick-stopped")
    wait_for(lambda: m.planner is None, 1.0, "no planner")


def test_shutdown_during_homing_ends_the_service_thread(tmp_path: Path) -> None:
    rig = Rig(tmp_path, lcm.LCM("memq://"))
    try:
        rig.ready()
        start_slow_homing(rig, request_id=21)
        service = rig.machine._service_thread
        assert service is not None and service.is_alive()
        rig.server.stop()
        _, took = timed(rig.machine.shutdown)
        assert took < SERVICE_JOIN_S + 5.0
        assert not service.is_alive()
        assert all(sim.state != DriveState.OPERATION_ENABLED for sim in rig.machine.sim_drives)
    finally:
        rig.close()


def test_canon_ctl_home_waits_for_the_result(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``canon ctl`` (its own lc.handle(), as a separate process has) prints the result, not the
    acceptance: ok when homed, the reason and exit 1 when homing failed."""
    lc = shared_memq()
    rig = Rig(tmp_path, lc, homing_timeout_s=0.5, threaded=False)
    try:
        url = ["--url", "memq://"]
        assert main(["ctl", *url, "estop_reset"]) == 0
        assert main(["ctl", *url, "enable"]) == 0
        rig.machine.sim_drives[0].home_switch_counts = 20_000  # 0.2 s
        assert main(["ctl", *url, "home", "x"]) == 0
        assert capsys.readouterr().out.splitlines()[-1] == "home: ok"
        assert rig.machine.status().homed[0]
        rig.machine.sim_drives[0].home_switch_counts = SLOW_HOME_COUNTS  # beyond homing_timeout_s
        assert main(["ctl", *url, "home", "x"]) == 1
        err = capsys.readouterr().err
        assert err.startswith("canon ctl: home: homing failed: node 1 (axis x): homing not attained"), err
        # --wait 0: the acceptance only
        assert main(["ctl", *url, "--wait", "0", "disable"]) == 0
        assert capsys.readouterr().out == "disable: accepted\n"
    finally:
        rig.close()
        for _ in range(10_000):  # leave the shared instance empty for the next test (bounded)
            if not lc.handle_timeout(0):
                break


def test_a_waiting_client_takes_its_own_result_and_gives_up_bounded() -> None:
    """``send_command`` on a service verb: the reply, then the result event of *this* request (others'
    results ignored) as the reply; no result within ``wait_result``: NoResult, in bounded time."""
    from motiond.control_client import NoResult, result_text
    from telemetry.publisher import CANON_EVENT

    lc = lcm.LCM("memq://")
    report = {"on": True}

    def handler(cmd: Any) -> str | None:
        if report["on"]:
            for rid, sender, error in ((cmd.request_id + 1, cmd.sender, None),  # another request's
                                       (cmd.request_id, "someone else", None),  # another client's
                                       (cmd.request_id, cmd.sender, "homing failed: node 1 (axis x): no")):
                ev = event()
                ev.severity, ev.kind = event.ERROR if error else event.INFO, "command"
                ev.text = result_text(cmd.verb, rid, sender, error)
                lc.publish(CANON_EVENT, ev.encode())
        return None

    server = CommandServer(lc, handler, key=TEST_KEY, url="memq://")
    server.subscribe()
    try:
        rep = send_command(lc, "home", ["x"], timeout=2.0, request_id=5, sender="me", wait_result=2.0)
        assert (rep.ok, rep.error, rep.request_id, rep.verb) == (False, "homing failed: node 1 (axis x): no",
                                                                 5, "home")
        report["on"] = False
        t = time.monotonic()
        with pytest.raises(NoResult, match=r"'enable' \(request 6\) was accepted, but no result arrived "
                                           r"within 0.3 s"):
            send_command(lc, "enable", timeout=2.0, request_id=6, sender="me", wait_result=0.3)
        assert 0.29 <= time.monotonic() - t < 3.0
        rep = send_command(lc, "enable", timeout=2.0, request_id=7, sender="me", wait_result=0)
        assert rep.ok  # the acceptance only
    finally:
        server.stop()
