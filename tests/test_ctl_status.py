"""``canon ctl`` and ``canon status``: the command client, the status view, and both commands.

Most tests run on the process's shared memq:// instance (``control_client.shared_memq()``, which the
commands use for ``--url memq://``), with a ``CommandServer`` as the fake daemon in this process. The
last tests run the real console script against a responder on udpm, inside the network namespace.
"""

from __future__ import annotations

import json
import math
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import lcm
import pytest
from keys import TEST_KEY, write_key_file
from rich.console import Console

from motiond import control_client
from motiond.cli import main
from motiond.control_client import (
    SERVICE_VERBS,
    CommandError,
    NoReply,
    Reply,
    result_text,
    send_command,
    shared_memq,
)
from motiond.status_view import StatusWatcher, decode_event, decode_status, render_status, to_json
from telemetry.commands import CommandServer
from telemetry.lcmtypes.canon import drive_status, event, reply, status
from telemetry.publisher import CANON_COMMAND, CANON_EVENT, CANON_REPLY, EventPublisher, StatusPublisher
from telemetry.url import DEFAULT_URL

CANON = str(Path(sys.executable).parent / "canon")
ROOT = Path(__file__).resolve().parent.parent


class FakeDaemon:
    """The daemon's command side: a CommandServer whose handler records commands and refuses ``run``.

    Like the daemon, it reports the result of a slow verb (``control_client.SERVICE_VERBS``) as an
    event after accepting it: done at once here.
    """

    def __init__(self, lc: Any, *, url: str = "memq://", key: bytes = TEST_KEY,
                 threaded: bool = False) -> None:
        self.commands: list[Any] = []
        self.server = CommandServer(lc, self.handler, key=key, url=url)
        if threaded:
            self.server.start()
        else:
            self.server.subscribe()  # the client's own lc.handle() dispatches to it

    def handler(self, cmd: Any) -> str | None:
        self.commands.append(cmd)
        if cmd.verb in SERVICE_VERBS:
            ev = event()
            ev.severity, ev.kind = event.INFO, "command"
            ev.text = result_text(cmd.verb, cmd.request_id, cmd.sender, None)
            self.server.lc.publish(CANON_EVENT, ev.encode())
        return "not homed: home the machine first" if cmd.verb == "run" else None

    def stop(self) -> None:
        self.server.stop()


def _drain(lc: Any) -> None:
    """Dispatch what earlier tests left queued on the shared instance (bounded)."""
    for _ in range(10_000):
        if not lc.handle_timeout(0):
            return


@pytest.fixture
def memq() -> Any:
    lc = shared_memq()
    _drain(lc)
    yield lc
    _drain(lc)


@pytest.fixture
def daemon(memq: Any) -> Any:
    d = FakeDaemon(memq)
    yield d
    d.stop()


# ---- send_command ------------------------------------------------------------------------------

def test_send_command_ok_and_error_replies_from_a_responder_thread(memq: Any) -> None:
    d = FakeDaemon(memq, threaded=True)
    try:
        ok = send_command(memq, "feed_override", values=[0.5], timeout=5, handle=False)
        refused = send_command(memq, "run", ["part.ngc"], [12], timeout=5, handle=False)
    finally:
        d.stop()
    assert isinstance(ok, Reply) and ok.ok and ok.error == "" and ok.verb == "feed_override"
    assert not refused.ok and refused.error == "not homed: home the machine first"
    assert [(c.verb, list(c.strings), list(c.values)) for c in d.commands] == [
        ("feed_override", [], [0.5]), ("run", ["part.ngc"], [12.0])]
    assert refused.request_id == d.commands[1].request_id and refused.sender == d.commands[1].sender
    assert refused.sender.startswith("canon-ctl@") and refused.sender.endswith(f":{os.getpid()}")


def test_send_command_handles_the_instance_itself(memq: Any, daemon: FakeDaemon) -> None:
    rep = send_command(memq, "home", ["x", "z"], timeout=5, request_id=77, sender="hmi")
    assert (rep.ok, rep.request_id, rep.sender, rep.verb) == (True, 77, "hmi", "home")
    assert list(daemon.commands[0].strings) == ["x", "z"]


def test_send_command_picks_its_own_reply(memq: Any) -> None:
    """Other clients' replies on CANON_REPLY (another request id or sender) are not ours."""
    def answer(_channel: str, data: bytes) -> None:
        from telemetry.lcmtypes.canon import command

        cmd = command.decode(data)
        for rid, sender, error in ((cmd.request_id + 1, cmd.sender, "other request"),
                                   (cmd.request_id, "someone else", "other sender"),
                                   (cmd.request_id, cmd.sender, "")):
            r = reply()
            r.request_id, r.sender, r.verb, r.ok, r.error = rid, sender, cmd.verb, not error, error
            memq.publish(CANON_REPLY, r.encode())
        memq.publish(CANON_REPLY, b"not a canon.reply")

    sub = memq.subscribe(CANON_COMMAND, answer)
    try:
        rep = send_command(memq, "pause", timeout=5, request_id=5, sender="me")
    finally:
        memq.unsubscribe(sub)
    assert (rep.ok, rep.error, rep.request_id, rep.sender) == (True, "", 5, "me")


@pytest.mark.parametrize(("key", "ok", "error"), [
    (TEST_KEY, True, ""),
    (bytes(32), False, "refused: bad MAC"),
])
def test_the_server_checks_the_signature(memq: Any, key: bytes, ok: bool, error: str) -> None:
    d = FakeDaemon(memq)
    try:
        rep = send_command(memq, "estop", key=key, timeout=5)
    finally:
        d.stop()
    assert rep.ok is ok and error in rep.error
    assert len(d.commands) == (1 if ok else 0)  # a refused command never reaches the daemon


@pytest.mark.parametrize(("verb", "strings", "values", "complaint"), [
    ("fly", [], [], "unknown verb 'fly'"),
    ("jog", ["x"], [], "jog takes 1 to 2 numeric argument(s), got 0"),
    ("feed_override", [], [math.nan], "must be finite"),
])
def test_a_malformed_command_is_not_sent(memq: Any, daemon: FakeDaemon, verb: str, strings: list[str],
                                         values: list[float], complaint: str) -> None:
    with pytest.raises(CommandError, match=complaint.replace("(", r"\(").replace(")", r"\)")):
        send_command(memq, verb, strings, values, timeout=0.5)
    memq.handle_timeout(50)
    assert daemon.commands == []


def test_no_reply_within_the_timeout(memq: Any) -> None:
    start = time.monotonic()
    with pytest.raises(NoReply, match=r"no reply to 'pause' .* within 0.3 s"):
        send_command(memq, "pause", timeout=0.3)
    assert 0.29 <= time.monotonic() - start < 3


def test_the_no_answer_message_names_the_url() -> None:
    text = control_client.no_answer_message("reply to 'pause'", DEFAULT_URL, 5)
    assert text.startswith(f"no reply to 'pause' within 5 s on {DEFAULT_URL}: the daemon may not be running")
    assert "memq://" not in text
    assert "reaches only this process" in control_client.no_answer_message("status", "memq://", 1)


# ---- canon ctl ---------------------------------------------------------------------------------

def test_ctl_ok(daemon: FakeDaemon, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ctl", "--url", "memq://", "jog", "x", "-10", "2.5"]) == 0
    assert capsys.readouterr().out == "jog: ok\n"
    cmd = daemon.commands[0]
    assert (cmd.verb, list(cmd.strings), list(cmd.values), cmd.mac_len) == ("jog", ["x"], [-10.0, 2.5], 32)


def test_ctl_refused_exits_1_with_the_reason(daemon: FakeDaemon, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ctl", "--url", "memq://", "run", "part.ngc", "12"]) == 1
    out, err = capsys.readouterr()
    assert out == "" and err == "canon ctl: run: not homed: home the machine first\n"
    assert (list(daemon.commands[0].strings), list(daemon.commands[0].values)) == (["part.ngc"], [12.0])


def test_ctl_json(daemon: FakeDaemon, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ctl", "--url", "memq://", "--json", "run", "part.ngc"]) == 1
    got = json.loads(capsys.readouterr().out)
    assert got["ok"] is False and got["verb"] == "run" and got["error"].startswith("not homed")
    assert got["request_id"] == daemon.commands[0].request_id and got["sender"] == daemon.commands[0].sender


@pytest.mark.parametrize(("argv", "strings", "values"), [
    (["mdi", "G0", "X10", "Y-2"], ["G0 X10 Y-2"], []),
    (["mdi", "G1 X1 F100"], ["G1 X1 F100"], []),
    (["home"], [], []),
    (["home", "x", "y"], ["x", "y"], []),
    (["single_block", "on"], [], [1.0]),
    (["block_delete", "0"], [], [0.0]),
    (["feed_override", "1.2"], [], [1.2]),
])
def test_ctl_splits_the_arguments_as_the_verb_takes_them(daemon: FakeDaemon, argv: list[str],
                                                        strings: list[str], values: list[float]) -> None:
    assert main(["ctl", "--url", "memq://", *argv]) == 0
    cmd = daemon.commands[0]
    assert (cmd.verb, list(cmd.strings), list(cmd.values)) == (argv[0], strings, values)


@pytest.mark.parametrize(("argv", "message", "usage"), [
    ([], "which verb?", "jog AXIS VELOCITY [DISTANCE]"),
    (["fly"], "unknown verb 'fly'", "feed_override FACTOR"),
    (["feed_override"], "feed_override: wrong number of arguments (0 given)",
     "canon ctl feed_override FACTOR"),
    (["jog", "x", "fast"], "jog: 'fast' is not a number", "canon ctl jog AXIS VELOCITY [DISTANCE]"),
    (["pause", "now"], "pause: 'now' is not a number", "canon ctl pause"),
    (["jog", "x", "1", "2", "3"], "jog: wrong number of arguments (4 given)", "canon ctl jog"),
    (["feed_override", "inf"], "feed_override: 'inf' is not a finite number", "canon ctl feed_override"),
    (["pause", "--timeout", "0"], "--timeout must be a number of seconds > 0", ""),
])
def test_ctl_usage_errors(daemon: FakeDaemon, argv: list[str], message: str, usage: str,
                          capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ctl", "--url", "memq://", *argv]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"canon ctl: {message}") and usage in err and "Traceback" not in err
    assert daemon.commands == []


def test_ctl_no_reply_exits_3_and_says_why(memq: Any, capsys: pytest.CaptureFixture[str]) -> None:
    start = time.monotonic()
    assert main(["ctl", "--url", "memq://", "--timeout", "0.3", "pause"]) == 3
    assert time.monotonic() - start < 3
    err = capsys.readouterr().err
    assert err.startswith("canon ctl: no reply to 'pause' within 0.3 s on memq://: the daemon may not be "
                          "running")


MACHINE = """
[machine]
name = "t"
[axes.x]
max_velocity = 100.0
max_acceleration = 1000.0
max_jerk = 10000.0
[telemetry]
url = "memq://"
key_file = "operator.key"
"""


def test_ctl_takes_url_and_key_file_from_the_machine_file(memq: Any, tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    machine = tmp_path / "machine.toml"
    machine.write_text(MACHINE)
    other = bytes(range(100, 132))
    write_key_file(tmp_path / "operator.key", other)
    monkeypatch.delenv("CANON_KEY")
    d = FakeDaemon(memq, key=other)
    try:
        rc = main(["ctl", "--config", str(machine), "estop"])
        assert rc == 0 and len(d.commands) == 1
        # --key-file names another file: its key is used, and the daemon refuses it
        write_key_file(tmp_path / "wrong.key", TEST_KEY)
        rc = main(["ctl", "--config", str(machine), "--key-file", str(tmp_path / "wrong.key"), "estop"])
    finally:
        d.stop()
    assert rc == 1 and capsys.readouterr().err.startswith("canon ctl: estop: refused: bad MAC")


def test_ctl_refuses_a_token_on_the_command_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ctl", "--url", "memq://", "--token", "s3cret", "estop"]) == 1
    err = capsys.readouterr().err
    assert "--token is no longer accepted" in err and "--key-file" in err and "Traceback" not in err


def test_ctl_without_a_key_says_where_to_put_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.delenv("CANON_KEY")
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    monkeypatch.setattr("telemetry.auth.SYSTEM_KEY_FILE", tmp_path / "none")
    assert main(["ctl", "--url", "memq://", "estop"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("canon ctl: no command key") and "CANON_KEY_FILE" in err


def test_ctl_bad_url(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ctl", "--url", "udpm://10.0.0.1:7667", "pause"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("canon ctl: ") and "not a multicast address" in err and "Traceback" not in err


# ---- the status view ---------------------------------------------------------------------------

def sample_status(seq: int = 42) -> Any:
    s = status()
    s.utime, s.seq, s.machine, s.state, s.mode, s.enabled = 1_700_000_000_000_000, seq, "demo mill", \
        "running", "auto", True
    s.program, s.line, s.block = "pocket.ngc", 17, "G1 X10.5 F600"
    s.num_axes, s.axis_names, s.homed = 2, ["x", "y"], [True, False]
    s.commanded, s.actual = [10.5, -2.25], [10.4987, -2.25]
    s.velocity, s.following_error = [12.5, 0.0], [0.0013, 0.0]
    s.feed_rate, s.feed_override, s.rapid_override, s.spindle_override = 600.0, 0.75, 1.0, 1.1
    drives = []
    for axis, node, word, state in (("x", 1, 0x1237, "operation_enabled"), ("y", 2, 0x0218, "fault")):
        d = drive_status()
        d.axis, d.node_id, d.nmt_state, d.heartbeat_ok = axis, node, "OPERATIONAL", axis == "x"
        d.statusword, d.cia402_state, d.mode_display = word, state, 8
        d.emcy_code, d.error = (0, "") if axis == "x" else (0x8611, "following error too large")
        drives.append(d)
    s.num_drives, s.drives = 2, drives
    s.num_gcodes, s.gcodes, s.num_mcodes, s.mcodes = 2, ["G1", "G90"], 2, ["M3", "M8"]
    s.tool, s.tool_prepared, s.tool_length_offset = 3, 4, 25.4
    s.spindle_direction, s.spindle_speed, s.mist, s.flood = 1, 12000.0, False, True
    s.io_ok = True
    s.num_digital_inputs, s.digital_inputs = 2, [False, True]
    s.num_digital_outputs, s.digital_outputs = 3, [True, False, True]
    s.num_analog_inputs, s.analog_inputs = 1, [2.5]
    s.num_analog_outputs, s.analog_outputs = 1, [math.nan]
    s.last_error, s.last_error_utime, s.events_dropped = "drive y: following error", 0, 3
    return s


def sample_event(severity: int = event.WARNING, text: str = "check the clamp", seq: int = 1) -> Any:
    e = event()
    e.utime, e.seq, e.severity, e.kind, e.source = 1_700_000_000_000_000, seq, severity, "message", "gcode"
    e.file, e.line, e.text = "pocket.ngc", 12, text
    return e


def test_decode_status_groups_axes_and_names_the_drive_state() -> None:
    d = decode_status(sample_status().encode())
    assert d["axes"][0] == {"name": "x", "homed": True, "commanded": 10.5, "actual": 10.4987,
                            "following_error": 0.0013, "velocity": 12.5}
    assert d["axes"][1]["name"] == "y" and d["axes"][1]["homed"] is False
    assert [(x["axis"], x["statusword"], x["statusword_hex"], x["cia402_state"]) for x in d["drives"]] == [
        ("x", 0x1237, "0x1237", "operation_enabled"), ("y", 0x0218, "0x0218", "fault")]
    assert (d["state"], d["program"], d["line"], d["tool"], d["feed_override"]) == \
        ("running", "pocket.ngc", 17, 3, 0.75)
    assert d["digital_outputs"] == [True, False, True] and d["mcodes"] == ["M3", "M8"]
    assert to_json(decode_status(sample_status())) == to_json(d)  # the message object decodes the same


def test_to_json_is_strict() -> None:
    text = to_json(decode_status(sample_status()))
    assert "NaN" not in text
    assert json.loads(text)["analog_outputs"] == [None]


def test_decode_event_names_the_severity() -> None:
    e = decode_event(sample_event(event.ERROR).encode())
    assert (e["severity"], e["file"], e["line"], e["text"]) == ("ERROR", "pocket.ngc", 12, "check the clamp")


def render(*args: Any, **kwargs: Any) -> str:
    console = Console(record=True, width=160, color_system=None)
    console.print(render_status(*args, **kwargs))
    return console.export_text()


def test_render_shows_the_snapshot_and_the_events() -> None:
    text = render(decode_status(sample_status()), [decode_event(sample_event())])
    lines = text.splitlines()
    for expected in ("demo mill", "running", "auto", "pocket.ngc:17", "G1 X10.5 F600", "75 %", "110 %",
                     "M3 cw", "S12000", "flood on", "mist off", "T3 (prepared T4)", "25.4", "G1 G90",
                     "M3 M8", "0:0 1:1", "0:1 1:0 2:1", "0:2.5", "drive y: following error",
                     "3 events dropped", "check the clamp", "WARNING", "pocket.ngc:12"):
        assert expected in text, expected
    x_row = next(line for line in lines if line.split()[:2] == ["x", "yes"])
    assert x_row.split()[2:] == ["10.5000", "10.4987", "0.0013", "12.500"]
    assert next(line for line in lines if line.split()[:2] == ["y", "no"]).split()[2:] == \
        ["-2.2500", "-2.2500", "0.0000", "0.000"]
    x_drive = next(line for line in lines if "0x1237" in line)
    assert x_drive.split() == ["x", "1", "OP", "ok", "operation_enabled", "0x1237", "8", "-"]
    y_drive = next(line for line in lines if "0x0218" in line)
    assert y_drive.split() == ["y", "2", "OP", "LOST", "fault", "0x0218", "8", "0x8611"]
    assert "drive y (node 2): following error too large" in lines
    assert "may have stopped" not in text


def test_render_waiting_and_stale() -> None:
    assert "waiting for CANON_STATUS on memq://" in render(None, url="memq://")
    stale = render(decode_status(sample_status()), age=2.5, url="memq://")
    assert "no status for 2.5 s: the daemon may have stopped (listening on memq://)" in stale


def test_watcher_keeps_the_latest_snapshot_and_the_last_events(memq: Any) -> None:
    with StatusWatcher(memq, max_events=3) as w:
        assert w.snapshot() is None and w.age() is None
        with EventPublisher(memq) as ep:
            for i in range(5):
                ep.emit(event.INFO, f"event {i}", kind="message", source="motiond")
        for seq in (1, 2):
            memq.publish("CANON_STATUS", sample_status(seq).encode())
        memq.publish("CANON_STATUS", b"junk")
        end = time.monotonic() + 5
        while (w.received < 2 or len(w.events) < 3 or w.bad_messages < 1) and time.monotonic() < end:
            w.poll(0.05)
        snap = w.snapshot()
        assert snap is not None and snap["seq"] == 2 and w.bad_messages == 1
        assert [e["text"] for e in w.events] == ["event 2", "event 3", "event 4"]
        assert w.age() is not None and w.age() < 5


# ---- canon status ------------------------------------------------------------------------------

@pytest.fixture
def publishing(memq: Any) -> Any:
    """The daemon's status side: a StatusPublisher at 50 Hz on the shared memq:// instance."""
    with StatusPublisher(memq, 50) as pub:
        pub.update(sample_status())
        yield pub


def test_status_once_json(publishing: StatusPublisher, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["status", "--url", "memq://", "--once", "--json"]) == 0
    out = capsys.readouterr().out
    assert out.count("\n") == 1
    got = json.loads(out)
    assert (got["state"], got["machine"], got["line"]) == ("running", "demo mill", 17)
    assert [a["name"] for a in got["axes"]] == ["x", "y"] and got["drives"][1]["statusword_hex"] == "0x0218"


def test_status_once_table(publishing: StatusPublisher, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["status", "--url", "memq://", "--once"]) == 0
    out = capsys.readouterr().out
    assert "pocket.ngc:17" in out and "0x1237" in out and "operation_enabled" in out


def test_status_once_without_a_daemon_exits_3(memq: Any, capsys: pytest.CaptureFixture[str]) -> None:
    start = time.monotonic()
    assert main(["status", "--url", "memq://", "--once", "--timeout", "0.3"]) == 3
    assert time.monotonic() - start < 3
    err = capsys.readouterr().err
    assert err.startswith("canon status: no status within 0.3 s on memq://: the daemon may not be running")


def test_status_bad_options(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["status", "--url", "memq://", "--once", "--timeout", "-1"]) == 1
    assert "--timeout must be a number of seconds > 0" in capsys.readouterr().err


def _read_until(proc: subprocess.Popen[bytes], marker: bytes, timeout: float) -> bytes:
    assert proc.stdout is not None
    seen = b""
    end = time.monotonic() + timeout
    while marker not in seen and time.monotonic() < end:
        ready, _, _ = select.select([proc.stdout], [], [], 0.1)
        if ready:
            chunk = os.read(proc.stdout.fileno(), 65536)
            if not chunk:
                break
            seen += chunk
    return seen


def test_status_live_ends_cleanly_on_ctrl_c() -> None:
    env = dict(os.environ, TTY_COMPATIBLE="1", COLUMNS="120")
    proc = subprocess.Popen([CANON, "status", "--url", "memq://"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=env, cwd=ROOT)
    try:
        seen = _read_until(proc, b"Ctrl-C to quit", 20)
        assert b"waiting for status on memq://" in seen
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    assert proc.stderr is not None
    err = proc.stderr.read().decode()
    assert rc == 0 and "Traceback" not in err and "interrupted" not in err


# ---- on udpm, through the console script (network namespace) -----------------------------------

@pytest.mark.multicast
def test_ctl_and_status_against_a_responder_on_udpm() -> None:
    lc = lcm.LCM(DEFAULT_URL)
    d = FakeDaemon(lc, url=DEFAULT_URL, threaded=True)
    try:
        with StatusPublisher(lc, 50) as pub:
            pub.update(sample_status())
            ok = subprocess.run([CANON, "ctl", "--url", DEFAULT_URL, "feed_override", "0.8"],
                                capture_output=True, text=True, timeout=30)
            refused = subprocess.run([CANON, "ctl", "--json", "run", "part.ngc"],
                                     capture_output=True, text=True, timeout=30)
            snap = subprocess.run([CANON, "status", "--once", "--json"],
                                  capture_output=True, text=True, timeout=30)
    finally:
        d.stop()
    assert (ok.returncode, ok.stdout) == (0, "feed_override: ok\n"), ok.stderr
    assert refused.returncode == 1 and json.loads(refused.stdout)["error"].startswith("not homed")
    assert snap.returncode == 0, snap.stderr
    assert json.loads(snap.stdout)["drives"][0]["cia402_state"] == "operation_enabled"
    assert [(c.verb, list(c.values)) for c in d.commands] == [("feed_override", [0.8]), ("run", [])]


@pytest.mark.multicast
def test_ctl_on_udpm_without_a_daemon() -> None:
    res = subprocess.run([CANON, "ctl", "--timeout", "0.5", "pause"], capture_output=True, text=True,
                         timeout=30)
    assert res.returncode == 3
    assert f"no reply to 'pause' within 0.5 s on {DEFAULT_URL}: the daemon may not be running" in res.stderr
