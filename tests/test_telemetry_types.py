"""The LCM types: round trips, the wire layout, and that the committed generated code is lcm-gen's."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import pytest

from telemetry import generate
from telemetry.lcmtypes.canon import command, drive_status, event, reply, status

ROOT = Path(__file__).resolve().parent.parent
TELEMETRY = ROOT / "telemetry"


def full_status() -> status:
    s = status()
    s.utime = 1_790_000_000_123_456
    s.seq = 42
    s.machine = "demo mill"
    s.state = "running"
    s.mode = "auto"
    s.estop = False
    s.enabled = True
    s.program = "examples/pocket.ngc"
    s.line = 17
    s.block = "G1 X10 Y-2.5 F600"
    s.single_block = True
    s.optional_stop = False
    s.block_delete = True
    s.axis_names = ["x", "y", "z"]
    s.num_axes = 3
    s.homed = [True, True, False]
    s.commanded = [10.0, -2.5, 0.125]
    s.actual = [9.998, -2.501, 0.125]
    s.velocity = [8.0, -6.0, 0.0]
    s.following_error = [0.002, 0.001, 0.0]
    s.path_velocity = 10.0
    s.feed_rate = 600.0
    s.feed_override = 1.2
    s.rapid_override = 0.5
    s.spindle_override = 1.0
    drives = []
    for i, axis in enumerate("xyz"):
        d = drive_status()
        d.axis = axis
        d.node_id = i + 1
        d.nmt_state = "OPERATIONAL"
        d.heartbeat_ok = i != 2
        d.statusword = 0xB637 if i == 0 else 0x0237  # above 0x7FFF: the unsigned value must survive
        d.cia402_state = "operation_enabled"
        d.mode_display = 8
        d.position_actual = -2_000_000_000 + i
        d.following_error = 20 - i
        d.emcy_code = 0x8611 if i == 2 else 0
        d.error = "following error" if i == 2 else ""
        drives.append(d)
    s.drives = drives
    s.num_drives = 3
    s.gcodes = ["G1", "G17", "G21", "G40", "G54", "G90", "G94"]
    s.num_gcodes = len(s.gcodes)
    s.mcodes = ["M3", "M8"]
    s.num_mcodes = 2
    s.tool = 3
    s.tool_prepared = 4
    s.tool_length_offset = 12.5
    s.spindle_direction = -1
    s.spindle_speed = 12000.0
    s.mist = False
    s.flood = True
    s.io_ok = True
    s.digital_inputs = [True, False, True, True]
    s.num_digital_inputs = 4
    s.digital_outputs = [False, True]
    s.num_digital_outputs = 2
    s.analog_inputs = [1.25]
    s.num_analog_inputs = 1
    s.analog_outputs = [0.0, 5.5, -3.25]
    s.num_analog_outputs = 3
    s.last_error = "drive z: following error"
    s.last_error_utime = 1_790_000_000_000_001
    s.events_dropped = 7
    return s


def slots(msg: object) -> dict[str, object]:
    out = {}
    for name in msg.__slots__:
        value = getattr(msg, name)
        if isinstance(value, (list, tuple)):
            value = [slots(v) if hasattr(v, "__slots__") else v for v in value]
        out[name] = value
    return out


def test_status_round_trip_keeps_every_field() -> None:
    s = full_status()
    back = status.decode(s.encode())
    assert slots(back) == slots(s)
    assert back.drives[0].statusword == 0xB637
    assert back.drives[1].position_actual == -1_999_999_999


def test_empty_status_round_trip() -> None:
    back = status.decode(status().encode())
    assert back.num_axes == 0 and list(back.commanded) == [] and back.drives == []


def test_status_with_counts_that_do_not_match_arrays_does_not_encode() -> None:
    s = full_status()
    s.num_axes = 4  # one more than the arrays hold
    with pytest.raises((IndexError, struct.error)):
        s.encode()


def test_event_round_trip_and_severity_constants() -> None:
    e = event()
    e.utime, e.seq, e.severity = 5, 9, event.ERROR
    e.kind, e.source, e.file, e.line = "drive_fault", "canopen", "part.ngc", 120
    e.text = "drive 3 (z): EMCY 0x8611 following error"
    assert slots(event.decode(e.encode())) == slots(e)
    assert (event.DEBUG, event.INFO, event.WARNING, event.ERROR, event.FATAL) == (0, 1, 2, 3, 4)


def test_command_round_trip() -> None:
    c = command()
    c.utime, c.request_id, c.sender, c.seq, c.verb = 1, 77, "hmi@pc:12", 12345, "jog"
    c.mac_len, c.mac = 32, bytes(range(32))
    c.strings, c.num_strings = ["x"], 1
    c.values, c.num_values = [-5.0, 2.5], 2
    assert slots(command.decode(c.encode())) == slots(c)


def test_reply_wire_layout_follows_the_lcm_spec() -> None:
    """Big-endian int64s, strings as int32 length (with the NUL) + bytes + NUL, boolean one byte."""
    r = reply()
    r.utime, r.request_id, r.sender, r.verb, r.ok, r.error = 3, -2, "me", "run", False, "no"
    data = r.encode()
    body = (struct.pack(">qq", 3, -2) + struct.pack(">i", 3) + b"me\0" + struct.pack(">i", 4) + b"run\0"
            + b"\0" + struct.pack(">i", 3) + b"no\0")
    assert data[8:] == body
    assert slots(reply.decode(data)) == slots(r)


def _java_fingerprint(java_source: Path) -> int:
    """LCM's fingerprint of a type without nested types: its base hash rotated left by one bit."""
    base = int(re.search(r"LCM_FINGERPRINT_BASE = 0x([0-9a-f]+)L", java_source.read_text()).group(1), 16)
    return ((base << 1) & 0xFFFFFFFFFFFFFFFF) | (base >> 63)


@pytest.mark.parametrize("cls", [event, command, reply, drive_status])
def test_python_and_java_agree_on_the_fingerprint(cls: type) -> None:
    java = TELEMETRY / "java" / "canon" / f"{cls.__name__}.java"
    assert struct.unpack(">Q", cls._get_packed_fingerprint())[0] == _java_fingerprint(java)


def test_decoding_another_type_is_refused() -> None:
    with pytest.raises(ValueError):
        status.decode(reply().encode())


def test_every_lcm_file_declares_package_canon_and_one_struct_named_after_the_file() -> None:
    files = generate.lcm_files()
    assert {f.name for f in files} >= {"canon_status.lcm", "canon_event.lcm", "canon_command.lcm",
                                       "canon_reply.lcm"}
    for f in files:
        text = f.read_text()
        assert re.search(r"^package canon;", text, re.M), f
        structs = re.findall(r"^struct (\w+)", text, re.M)
        assert structs == [f.stem.removeprefix("canon_")], f


def test_committed_generated_code_is_what_lcm_gen_makes_now() -> None:
    """Nobody edits a .lcm file without regenerating, nor the generated code by hand."""
    problems = generate.check(with_jar=False)
    assert problems == [], "\n".join(problems) + "\nrun: python -m telemetry.generate"


def test_shipped_jar_was_built_from_these_lcm_files() -> None:
    assert generate.jar_digest(generate.JAR) == generate.sources_digest(), (
        "telemetry/canon_types.jar is stale: run python -m telemetry.generate")


def test_check_reports_a_hand_edited_generated_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fake = tmp_path / "canon"
    fake.mkdir()
    for f in generate.PY_DIR.glob("*.py"):
        (fake / f.name).write_bytes(f.read_bytes())
    edited = fake / "reply.py"
    edited.write_text(edited.read_text().replace("self.ok = False", "self.ok = True"))
    (fake / "old_type.py").write_text("")
    monkeypatch.setattr(generate, "PY_DIR", fake)
    problems = generate.check(with_jar=False)
    assert any("reply.py" in p and "differs" in p for p in problems)
    assert any("old_type.py" in p and "stale" in p for p in problems)


def test_generated_types_import_by_the_packaged_name() -> None:
    import telemetry.lcmtypes.canon as pkg

    assert pkg.status is status
    assert status.__module__ == "telemetry.lcmtypes.canon.status"
    assert "telemetry.lcmtypes.canon.drive_status" in status.__typenames__
