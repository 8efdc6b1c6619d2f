"""The daemon in this process on ``memq://``: commands through ``send_command``, status through LCM.

Each test starts the demo machine (simulated drives on a private bus, the simulated I/O module on a
free loopback port) with its :class:`CommandServer`, and drives it as an HMI would: commands and their
replies, the ``canon.status`` stream, events. Faults are injected in the simulated drives (by SDO on
their bus, as a test bench does) and the I/O module.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from keys import TEST_KEY

from motiond.cmd_daemon import start
from motiond.config import load_machine
from motiond.control_client import send_command, shared_memq
from telemetry.commands import make_command
from telemetry.config import TelemetryConfig
from telemetry.lcmtypes.canon import event, status

SHORT = """%
G21 G90 G94 G64 P0.01
G0 Z5
G0 X10 Y5
M62 P0
G1 Z-1 F600
G1 X20 Y15 F1200
G2 X30 Y5 I5 J-5
M63 P0
G0 Z5
G0 X12.5 Y7.25 Z3
M2
%
"""
SHORT_FINAL = (12.5, 7.25, 3.0)  # the program's last G0

LONG = """%
G21 G90 G94
G1 X120 F3000
G0 X0
M2
%
"""


def demo_with_motion(process: str) -> Any:
    """The built-in demo machine with ``[motion] process`` set (the demo has no file to write it in)."""
    import dataclasses

    from motiond.configkit import Table

    return dataclasses.replace(load_machine(None), root=Table({"motion": {"process": process}}, ""))


def inject_emcy(machine: Any, node_id: int, code: int) -> None:
    """Make simulated drive ``node_id`` fault with EMCY ``code`` as ``canon sim inject`` does: an SDO
    write to its simulation-only 0x2F00 from a CANopen client of this test's own on the machine's bus
    (the drives run in a process of their own, or beside a thread-mode motion)."""
    import struct

    import canopen

    from fieldbus.canopen.drive_sim import SIM_INJECT, SIM_INJECT_CODE, SIM_INJECT_DELAY_MS

    network = canopen.Network()
    network.connect(**machine.canopen.bus.bus_kwargs())
    try:
        node = network.add_node(canopen.RemoteNode(node_id, canopen.ObjectDictionary()))
        node.sdo.MAX_RETRIES = 3
        node.sdo.RESPONSE_TIMEOUT = 1.0  # the drives' process may wait for a CPU on the loaded test PC
        node.sdo.download(SIM_INJECT, SIM_INJECT_DELAY_MS, struct.pack("<I", 0))
        node.sdo.download(SIM_INJECT, SIM_INJECT_CODE, struct.pack("<H", code))
    finally:
        network.disconnect()


class Daemon:
    """A machine with its command server on the process's shared memq, and what it publishes."""

    def __init__(self, tmp: Path, tele: TelemetryConfig | None = None, late_fault_s: float = 2.0,
                 config: Any = None, feedback_timeout_s: float | None = None) -> None:
        self.lc = shared_memq()
        self.tele = tele or TelemetryConfig(url="memq://")
        self.statuses: list[Any] = []
        self.events: list[Any] = []
        self._lock = threading.Lock()
        self.var = tmp / "params.var"
        self.tmp = tmp
        for _ in range(100_000):  # bounded: what an earlier test's machine published is still queued in
            if self.lc.handle_timeout(0) <= 0:  # the shared memq, and its first status (IDLE) reached
                break  # the next test's subscription as this machine's first
        self.subs = [self.lc.subscribe("CANON_STATUS", self._on_status),
                     self.lc.subscribe("CANON_EVENT", self._on_event)]
        config = load_machine(None) if config is None else config
        self.machine, self.server = start(config, self.lc, self.tele, key=TEST_KEY, var_file=self.var,
                                          programs=[tmp], late_fault_s=late_fault_s,
                                          feedback_timeout_s=feedback_timeout_s)

    def _on_status(self, _ch: str, data: bytes) -> None:
        s = status.decode(data)
        with self._lock:
            self.statuses.append(s)

    def _on_event(self, _ch: str, data: bytes) -> None:
        with self._lock:
            self.events.append(event.decode(data))

    def cmd(self, verb: str, strings: tuple[str, ...] | list[str] = (), values: tuple[float, ...] = (),
            key: bytes = TEST_KEY) -> Any:
        return send_command(self.lc, verb, strings, values, key, timeout=10.0, handle=False)

    def ok(self, verb: str, *args: Any, **kw: Any) -> None:
        reply = self.cmd(verb, *args, **kw)
        assert reply.ok, f"{verb}: {reply.error}"

    def latest(self) -> Any:
        with self._lock:
            return self.statuses[-1] if self.statuses else None

    def wait_status(self, pred: Callable[[Any], bool], timeout: float = 10.0, what: str = "") -> Any:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            s = self.latest()
            if s is not None and pred(s):
                return s
            time.sleep(0.01)
        s = self.latest()
        raise AssertionError(f"status never showed {what}: last state {s.state if s else None!r}, "
                             f"error {s.last_error if s else ''!r}")

    def wait_event(self, pred: Callable[[Any], bool], timeout: float = 10.0, what: str = "") -> Any:
        """The first event ``pred`` accepts: events and status travel on separate channels, so an
        event may arrive after the status that shows its effect."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for e in list(self.events):
                if pred(e):
                    return e
            time.sleep(0.01)
        raise AssertionError(f"no event {what}: saw {[e.kind for e in list(self.events)]}")

    def states_seen(self) -> list[str]:
        out: list[str] = []
        with self._lock:
            for s in self.statuses:
                if not out or out[-1] != s.state:
                    out.append(s.state)
        return out

    def program(self, text: str, name: str = "prog.ngc") -> str:
        p = self.tmp / name
        p.write_text(text)
        return str(p)

    def ready(self) -> None:
        self.ok("estop_reset")
        self.ok("enable")
        self.wait_status(lambda s: s.state == "idle" and s.enabled, what="idle and enabled")

    def close(self) -> None:
        self.server.stop()
        self.machine.shutdown()
        for sub in self.subs:
            self.lc.unsubscribe(sub)


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[Daemon]:
    d = Daemon(tmp_path)
    try:
        yield d
    finally:
        d.close()


def test_run_from_idle_to_running_to_idle(daemon: Daemon) -> None:
    prog = daemon.program(SHORT)
    first = daemon.wait_status(lambda s: True, what="any status")
    assert first.state == "estop" and not first.enabled  # power-up never moves a machine
    refused = daemon.cmd("run", [prog])
    assert not refused.ok and "estop" in refused.error
    assert not daemon.cmd("enable").ok  # not from estop
    daemon.ready()
    daemon.machine.trace = []
    daemon.ok("run", [prog])
    daemon.wait_status(lambda s: s.state == "running", what="running")
    s = daemon.wait_status(lambda s: s.state == "idle" and s.seq > 0 and s.commanded[0] == SHORT_FINAL[0],
                           what="idle at the end")
    seq = daemon.states_seen()
    assert seq[-3:] == ["idle", "running", "idle"]
    assert tuple(s.commanded) == SHORT_FINAL
    for actual, want in zip(daemon.wait_status(
            lambda s: all(abs(a - w) < 1e-3 for a, w in zip(s.actual, SHORT_FINAL, strict=True)),
            what="drives at the end").actual, SHORT_FINAL, strict=True):
        assert actual == pytest.approx(want, abs=1e-3)
    # the synchronized outputs: M62 P0 rides on the first setpoint of the Z plunge, M63 P0 on that of
    # the retract: Z at rest on the start point the cycle before, moving by the cycle after (the first
    # setpoint of a motion from rest is its start point, or its first sample 1e-8 mm away)
    trace = daemon.machine.trace
    switched = [(k, ev) for k, (_c, _t, _p, evs) in enumerate(trace) for ev in evs
                if type(ev).__name__ == "DigitalOutput"]
    assert [(ev.index, ev.on, ev.line) for _k, ev in switched] == [(0, True, 5), (0, False, 9)]
    # In G64 P the retract after the arc starts inside a transition that eases the corner, so Z leaves
    # its rest during the output's cycle rather than exactly at it: at most one cycle of a jerk-limited
    # start (Z velocity and acceleration both 0 there), j T^3 / 6.
    one_cycle = daemon.machine.limits.axes[2].max_jerk * daemon.machine.T ** 3 / 6
    for (k, ev), z_rest in zip(switched, (5.0, -1.0), strict=True):
        z = [trace[i][2][2] for i in range(k - 2, k + 2)]
        assert z[0] == z[1] == z_rest, f"line {ev.line}: Z moved before the output's cycle"
        assert abs(z[2] - z_rest) <= one_cycle, f"line {ev.line}: the output came late"
        assert z[3] != z_rest, f"line {ev.line}: Z does not start moving with its output"
    module = daemon.machine.sim_io["io"]
    writes = module.writes_to("coil", 0)
    on = [w for w in writes if w.values == (1,)]
    off = [w for w in writes if w.values == (0,) and on and w.t > on[0].t]
    assert on and off
    t_on, t_off = trace[switched[0][0]][1], trace[switched[1][0]][1]
    assert 0 <= on[0].t - t_on < 0.5 and 0 <= off[0].t - t_off < 0.5  # written after its cycle, soon
    daemon.wait_event(lambda e: e.kind == "program_start", what="program_start")
    daemon.wait_event(lambda e: e.kind == "program_end", what="program_end")
    assert daemon.var.exists()  # the parameter file is written at program end


def test_pause_resume_and_abort(daemon: Daemon) -> None:
    daemon.ready()
    prog = daemon.program(LONG)
    daemon.ok("run", [prog])
    daemon.wait_status(lambda s: s.commanded[0] > 10, what="X moving")
    daemon.ok("pause")
    held = daemon.wait_status(lambda s: s.state == "paused" and s.velocity[0] == 0.0, what="held")
    time.sleep(0.3)
    assert daemon.latest().commanded[0] == held.commanded[0]  # stays put while paused
    assert 10 < held.commanded[0] < 120
    assert held.program.endswith("prog.ngc") and held.line == 3 and held.block == "G1 X120 F3000"
    assert not daemon.cmd("run", [prog]).ok  # one program at a time
    daemon.ok("resume")
    daemon.wait_status(lambda s: s.state == "running" and s.commanded[0] > held.commanded[0] + 1,
                       what="moving again")
    daemon.ok("abort")
    stopped = daemon.wait_status(lambda s: s.state == "idle" and s.velocity[0] == 0.0,
                                 what="idle after abort")
    assert stopped.commanded[0] < 120  # never reached the end
    time.sleep(0.2)
    assert daemon.latest().commanded[0] == stopped.commanded[0]
    daemon.ok("mdi", ["G0 X0"])  # and the machine takes the next command from where it stopped
    daemon.wait_status(lambda s: s.state == "idle" and s.commanded[0] == 0.0, what="back at X0")


def test_feed_override_single_block_switches_and_refusals(daemon: Daemon) -> None:
    assert not daemon.cmd("feed_override", values=(3.0,)).ok
    daemon.ok("single_block", values=(1.0,))
    daemon.ok("optional_stop", values=(1.0,))
    daemon.ok("block_delete", values=(1.0,))
    s = daemon.wait_status(lambda s: s.single_block and s.optional_stop and s.block_delete, what="switches")
    assert s.state == "estop"
    assert not daemon.cmd("jog", ["x"], (10.0,)).ok
    assert not daemon.cmd("home").ok
    assert not daemon.cmd("run", ["/nonexistent.ngc"]).ok
    daemon.ready()
    assert "outside the program directories" in daemon.cmd("run", ["/nonexistent.ngc"]).error
    assert "no program 'missing.ngc' in the program directories" in daemon.cmd("run", ["missing.ngc"]).error
    daemon.ok("feed_override", values=(0.5,))
    daemon.wait_status(lambda s: s.feed_override == 0.5, what="override 50 %")


def test_m0_pauses_and_resume_continues_m1_needs_optional_stop(daemon: Daemon) -> None:
    daemon.ready()
    prog = daemon.program("%\nG0 X5\nM1\nG0 X6\nM0\nG0 X7\nM2\n%\n")
    daemon.ok("run", [prog])
    s = daemon.wait_status(lambda s: s.state == "paused", what="paused at M0")
    assert s.commanded[0] == 6.0  # M1 passed (optional stop off), M0 stopped
    daemon.ok("resume")
    daemon.wait_status(lambda s: s.state == "idle" and s.commanded[0] == 7.0, what="end of program")


def test_m66_waits_for_the_input(daemon: Daemon) -> None:
    daemon.ready()
    module = daemon.machine.sim_io["io"]
    prog = daemon.program("%\nG0 X2\nM66 P3 L3 Q5\n#100 = #5399\nG0 X[3 + #100]\nM2\n%\n")
    daemon.ok("run", [prog])
    time.sleep(0.5)
    assert daemon.latest().commanded[0] == 2.0  # waiting for discrete input 3
    module.set("discrete_input", 3, 1)
    daemon.wait_status(lambda s: s.state == "idle" and s.commanded[0] == 4.0, what="after M66")
    assert daemon.machine.interp.parameter(5399) == 1.0


def test_jog_and_home(daemon: Daemon) -> None:
    daemon.ready()
    daemon.ok("jog", ["y"], (20.0, 5.0))
    daemon.wait_status(lambda s: s.commanded[1] == 5.0 and s.state == "idle", what="jogged 5 mm")
    daemon.ok("mdi", ["G91 G0 Y1"])  # incremental from where the jog left the machine
    daemon.wait_status(lambda s: s.commanded[1] == 6.0 and s.state == "idle", what="Y6 after G91 Y1")
    daemon.ok("mdi", ["G90"])
    daemon.wait_status(lambda s: s.state == "idle" and daemon.machine.job is None, what="G90 done")
    daemon.ok("jog", ["x"], (-30.0,))  # continuous, until velocity 0
    daemon.wait_status(lambda s: s.state == "jogging" and s.commanded[0] < -1.0, what="jogging")
    daemon.ok("jog", ["x"], (0.0,))
    stopped = daemon.wait_status(lambda s: s.state == "idle", what="jog stopped")
    assert stopped.commanded[0] < -1.0
    daemon.ok("home", ["x"])
    s = daemon.wait_status(lambda s: s.homed[0], what="x homed")
    assert s.commanded[0] == 0.0 and not s.homed[1]  # "set" homing: here is X0
    daemon.ok("mdi", ["G0 X2 Y0"])  # the interpreter continues from the homed position
    daemon.wait_status(lambda s: s.state == "idle" and s.commanded[0] == 2.0 and s.commanded[1] == 0.0,
                       what="moved after homing")


def test_estop_and_recovery(daemon: Daemon) -> None:
    daemon.ready()
    daemon.ok("run", [daemon.program(LONG)])
    daemon.wait_status(lambda s: s.commanded[0] > 5, what="moving")
    daemon.ok("estop")
    s = daemon.wait_status(lambda s: s.state == "estop", what="estop")
    assert s.estop and not s.enabled
    daemon.wait_event(lambda e: e.kind == "estop", what="estop")
    assert not daemon.cmd("mdi", ["G0 X0"]).ok
    daemon.ready()
    daemon.ok("mdi", ["G0 X1"])
    daemon.wait_status(lambda s: s.state == "idle" and s.commanded[0] == 1.0, what="moving after reset")


def test_drive_emcy_faults_and_reset_recovers(daemon: Daemon) -> None:
    daemon.ready()
    daemon.ok("run", [daemon.program(LONG)])
    daemon.wait_status(lambda s: s.commanded[0] > 5, what="moving")
    inject_emcy(daemon.machine, node_id=2, code=0x2310)  # axis y
    s = daemon.wait_status(lambda s: s.state == "fault", what="fault")
    assert "EMCY 0x2310" in s.last_error and "axis y" in s.last_error
    assert not s.enabled
    daemon.wait_event(lambda e: e.kind == "drive_fault" and "0x2310" in e.text, what="drive_fault 0x2310")
    assert not daemon.cmd("mdi", ["G0 X0"]).ok
    refused = daemon.cmd("enable")
    assert not refused.ok and "fault" in refused.error
    daemon.ok("reset")
    s = daemon.wait_status(lambda s: s.state == "idle", what="idle after reset")
    assert not s.enabled and s.last_error == ""
    daemon.ok("enable")
    daemon.ok("run", [daemon.program(SHORT, "short.ngc")])
    daemon.wait_status(lambda s: s.state == "idle" and tuple(s.commanded) == SHORT_FINAL, what="run again")


def test_io_server_stopped_faults_and_reset_waits_for_the_link(daemon: Daemon) -> None:
    daemon.ready()
    module = daemon.machine.sim_io["io"]
    module.stop()
    # the demo machine's E-stop input is on that module (docs/wiring.md): unreadable is an E-stop
    # (a machine without an E-stop input faults instead: tests/test_end_to_end.py)
    daemon.wait_status(lambda s: s.state == "estop" and not s.io_ok, what="E-stop")
    refused = daemon.cmd("estop_reset")
    assert not refused.ok and "Modbus" in refused.error
    module.start()
    deadline = time.monotonic() + 10
    while True:
        reply = daemon.cmd("estop_reset")
        if reply.ok or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    assert reply.ok, reply.error
    daemon.ok("enable")
    daemon.ok("mdi", ["M64 P2"])
    daemon.wait_status(lambda s: s.io_ok and len(s.digital_outputs) > 2 and s.digital_outputs[2],
                       what="output 2 on")


def test_gcode_error_mid_program_faults_with_file_and_line(daemon: Daemon) -> None:
    daemon.ready()
    prog = daemon.program("%\nG0 X5\nG1 X10\nM2\n%\n", "bad.ngc")
    daemon.ok("run", [prog])
    s = daemon.wait_status(lambda s: s.state == "fault", what="fault")
    assert s.last_error.endswith("bad.ngc:3: Cannot do G1 with zero feed rate")
    daemon.ok("reset")
    daemon.wait_status(lambda s: s.state == "idle", what="idle")


def test_late_cycle_is_a_fault(tmp_path: Path) -> None:
    # the cycle thread is stalled from within its process (_on_cycle): the demo machine's motion in a
    # thread of this process, where the test can reach it, whatever "auto" picks (a motion process of
    # its own is hung by SIGSTOP in tests/test_motion_process_watch.py)
    d = Daemon(tmp_path, late_fault_s=0.1, config=demo_with_motion("thread"))
    try:
        d.ready()
        d.machine._on_cycle(lambda: time.sleep(0.3), wait=False)  # a stalled cycle thread
        s = d.wait_status(lambda s: s.state == "fault", what="fault")
        assert "late" in s.last_error
        d.ok("reset")
        d.ok("enable")
        d.ok("mdi", ["G0 X1"])
        d.wait_status(lambda s: s.state == "idle" and s.commanded[0] == 1.0, what="moving after reset")
    finally:
        d.close()


def test_malformed_message_is_counted_and_ignored(daemon: Daemon) -> None:
    daemon.wait_status(lambda s: True, what="any status")
    daemon.lc.publish("CANON_COMMAND", b"\x00not a canon.command at all")
    deadline = time.monotonic() + 5
    while daemon.server.bad_messages == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert daemon.server.bad_messages == 1
    daemon.ok("estop_reset")  # still answering
    seq = daemon.latest().seq
    daemon.wait_status(lambda s: s.seq > seq + 5, what="status still flowing")


def test_unsigned_and_wrongly_signed_commands_are_refused_with_a_security_event(tmp_path: Path) -> None:
    d = Daemon(tmp_path)
    try:
        d.wait_status(lambda s: True, what="any status")  # status stays readable without the key
        wrong = d.cmd("estop_reset", key=bytes(32))
        assert not wrong.ok and wrong.error.startswith("refused: bad MAC")
        d.lc.publish("CANON_COMMAND", make_command("estop_reset", request_id=9, sender="lan").encode())
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and not [e for e in list(d.events) if e.kind == "security"
                                                    and "'lan'" in e.text and "unsigned" in e.text]:
            time.sleep(0.01)
        assert [e.severity for e in list(d.events) if e.kind == "security"] == [event.WARNING] * 2
        assert d.latest().state == "estop"
        d.ok("estop_reset")
        d.wait_status(lambda s: s.state == "idle", what="idle")
    finally:
        d.close()


def test_parameters_saved_on_shutdown(tmp_path: Path) -> None:
    d = Daemon(tmp_path)
    try:
        d.ready()
        d.ok("mdi", ["G10 L2 P1 X7.5"])  # G54 X offset: a persistent parameter (#5221)
        d.wait_status(lambda s: s.state == "idle" and d.machine.job is None, what="mdi done")
    finally:
        d.close()
    values = dict(line.split() for line in d.var.read_text().splitlines() if line.strip())
    assert float(values["5221"]) == 7.5


def test_single_block_stops_after_each_block(daemon: Daemon) -> None:
    daemon.ready()
    daemon.ok("single_block", values=(1.0,))
    prog = daemon.program("%\nG0 X1\nG0 X2\nG0 X3\nM2\n%\n")
    daemon.ok("run", [prog])
    for x in (1.0, 2.0):
        s = daemon.wait_status(lambda s, x=x: s.state == "paused" and s.commanded[0] == x,
                               what=f"stop at X{x}")
        time.sleep(0.2)
        assert daemon.latest().commanded[0] == x and daemon.latest().state == "paused"
        daemon.ok("resume")
    daemon.ok("single_block", values=(0.0,))
    daemon.wait_status(lambda s: s.state in ("paused", "idle") and s.commanded[0] == 3.0, what="X3")
    if daemon.latest().state == "paused":
        daemon.ok("resume")
    daemon.wait_status(lambda s: s.state == "idle", what="end")
    assert s.single_block


def test_disable_then_nothing_moves_until_enabled(daemon: Daemon) -> None:
    daemon.ready()
    daemon.ok("disable")
    s = daemon.wait_status(lambda s: not s.enabled, what="disabled")
    assert all(d.cia402_state == "switch_on_disabled" for d in s.drives)
    refused = daemon.cmd("mdi", ["G0 X1"])
    assert not refused.ok and "disabled" in refused.error
    assert not daemon.cmd("jog", ["x"], (10.0, 1.0)).ok
    daemon.ok("enable")
    daemon.wait_status(lambda s: s.enabled and all(d.cia402_state == "operation_enabled" for d in s.drives),
                       what="enabled again")
    daemon.ok("mdi", ["G0 X1"])
    daemon.wait_status(lambda s: s.state == "idle" and s.commanded[0] == 1.0, what="moved")


def test_run_takes_programs_only_from_the_program_directories(daemon: Daemon, tmp_path: Path) -> None:
    """Outside files are refused in one sentence, whatever is there: nothing read, nothing revealed."""
    daemon.ready()
    outside = tmp_path.parent / f"{tmp_path.name}-outside"
    outside.mkdir()
    secret = outside / "secret.ngc"
    secret.write_text("root:*:20228:0:99999:7:::\n")
    (tmp_path / "link.ngc").symlink_to(secret)
    (tmp_path / "sub").mkdir()
    answers = {}
    for name in (str(secret), str(outside / "absent.ngc"), "/etc/shadow", "/etc/nothing-here",
                 f"../{outside.name}/secret.ngc", f"../{outside.name}/absent.ngc", "link.ngc",
                 "sub/../../x.ngc", "sub"):
        rep = daemon.cmd("run", [name])
        assert not rep.ok, name
        answers[name] = rep.error
    for name, error in answers.items():
        if name == "sub":
            assert error.startswith("no program 'sub' in the program directories"), error
            continue
        assert error == f"{name!r} is outside the program directories ({tmp_path.resolve()}): refused"
    with daemon._lock:
        texts = [e.text for e in daemon.events] + [s.last_error for s in daemon.statuses]
    assert not [t for t in texts if "root:" in t or "20228" in t]  # the content never echoed
    assert daemon.latest().state == "idle"
    (tmp_path / "sub" / "ok.ngc").write_text(SHORT)
    daemon.ok("run", ["sub/ok.ngc"])  # a relative name inside works
    daemon.wait_status(lambda s: s.state == "idle" and tuple(s.commanded) == SHORT_FINAL, what="program ran")


def test_an_mdi_line_over_the_line_limit_is_refused_without_a_fault(daemon: Daemon) -> None:
    daemon.ready()
    rep = daemon.cmd("mdi", ["G0 X1" + " " * 100_011])
    assert not rep.ok and rep.error == "<mdi>:1: Line too long (more than 256 characters)"
    assert daemon.machine.states.state.name == "IDLE"
    daemon.ok("mdi", ["G0 X1"])
