"""``canon drives scan`` and ``canon drives dcf``: the demo machine, a drive lacking optional objects,
a drive that does not fit, the DCF of what boot writes."""

from __future__ import annotations

import json
from pathlib import Path

import canopen
import pytest
from canopen_helpers import unique_channel, wait_for

from fieldbus.canopen.config import CanBusConfig
from fieldbus.canopen.drive_sim import SimDrive
from fieldbus.canopen.sim_process import SimBus
from motiond.cli import main


def test_scan_of_the_demo_machine(capsys):
    rc = main(["drives", "scan"])
    out = capsys.readouterr().out
    assert rc == 0, out
    for node, axis in ((1, "x"), (2, "y"), (3, "z")):
        assert f"node {node} (axis {axis}): fits the configuration" in out
    assert "canon simulated CiA 402 drive" in out and "3000 rpm" in out and "CSP yes" in out


def _machine(tmp_path: Path, channel: str, extra: str = "") -> Path:
    p = tmp_path / "m.toml"
    p.write_text(f"""
[axes.x]
max_velocity = 200.0
max_acceleration = 2000.0
[axes.y]
max_velocity = 300.0
max_acceleration = 2000.0
[canopen]
interface = "virtual"
channel = "{channel}"
[canopen.axes.x]
node_id = 1
[canopen.axes.y]
node_id = 2
{extra}""")
    return p


@pytest.fixture
def bus():
    channel = unique_channel()
    sims = SimBus([SimDrive(1, absent_objects={0x6085, 0x60C2}), SimDrive(2)],
                  CanBusConfig("virtual", channel))
    assert wait_for(lambda: all(d.nmt_state != 0 for d in sims.drives.values()), 2.0)
    yield channel, sims
    sims.close()


def test_scan_names_absent_optional_objects_and_every_mismatch(tmp_path, bus, capsys):
    channel, sims = bus
    path = _machine(tmp_path, channel, "vendor_id = 0x1234\n")  # y's identity from the file
    rc = main(["drives", "scan", "--config", str(path)])
    out = capsys.readouterr().out
    assert rc == 1
    assert "0x60C2, 0x6085" in out  # x lacks them: noted, not a mismatch
    assert "node 1 (axis x): fits the configuration" in out
    assert "note: node 1 (axis x): no 0x6085 (quick stop deceleration)" in out
    assert "mismatch: node 2 (axis y): identity 0x1018:01 vendor id is 0x00000CA0, the configuration " \
           "expects 0x00001234" in out
    assert ("mismatch: node 2 (axis y): axes.y.max_velocity 300 is 3,000,000 counts/s, more than the "
            "motor") in out
    rc = main(["drives", "scan", "--config", str(path), "--json"])
    data = json.loads(capsys.readouterr().out)
    assert rc == 1 and [d["node"] for d in data] == [1, 2]
    assert data[0]["optional_absent"] == ["0x60C2", "0x6085"] and data[0]["mismatches"] == []
    assert len(data[1]["mismatches"]) == 2
    assert sims[1].state.value == "Switch on disabled"  # nothing written: the scan reads only


def test_scan_lists_digital_inputs_and_touch_probes_per_node(tmp_path, capsys):
    channel = unique_channel()
    # x has no 0x60FD; y's negative limit switch is active where it stands, and its touch probe 1
    # lacks the negative edge's position (probe 2 is complete)
    sims = SimBus([SimDrive(1, absent_objects={0x60FD}),
                   SimDrive(2, absent_objects={0x60BB}, negative_limit_counts=10)],
                  CanBusConfig("virtual", channel))
    try:
        assert wait_for(lambda: all(d.nmt_state != 0 for d in sims.drives.values()), 2.0)
        path = _machine(tmp_path, channel, "touch_probe = 1\n")
        rc = main(["drives", "scan", "--config", str(path)])
        out = capsys.readouterr().out
        assert rc == 1
        assert "note: node 1 (axis x): no 0x60FD (digital inputs): canon does not see its limit" in out
        assert "yes: 0x00000001 (negative limit switch)" in out
        assert ("mismatch: node 2 (axis y): canopen.axes.y.touch_probe = 1, but the drive lacks 0x60BB "
                "(touch probe 1 position, negative edge)") in out
        rc = main(["drives", "scan", "--config", str(path), "--json"])
        data = json.loads(capsys.readouterr().out)
        assert [d["digital_inputs"] for d in data] == [None, 1]
        assert [d["touch_probes"] for d in data] == [[1, 2], [2]]
    finally:
        sims.close()


def test_scan_of_a_node_that_does_not_answer(tmp_path, capsys):
    path = _machine(tmp_path, unique_channel())
    rc = main(["drives", "scan", "--config", str(path), "--timeout", "0.1"])
    out = capsys.readouterr().out
    assert rc == 1 and "no answer" in out and "node 1 (axis x): no SDO answer" in out


def test_dcf_per_drive_holds_what_boot_writes(tmp_path, capsys):
    path = _machine(tmp_path, unique_channel(), "[[canopen.axes.y.sdo]]\nindex = 0x6099\nsubindex = 1\n"
                                                "type = \"u32\"\nvalue = 4242\n")
    out_dir = tmp_path / "dcf"
    out_dir.mkdir()
    rc = main(["drives", "dcf", "--config", str(path), "--out", str(out_dir)])
    assert rc == 0, capsys.readouterr().err
    assert sorted(p.name for p in out_dir.iterdir()) == ["x-node1.dcf", "y-node2.dcf"]
    od = canopen.import_od(str(out_dir / "y-node2.dcf"), 2)
    assert od[0x6060].value == 8 and od[0x605A].value == 2  # CSP; standard layout: quick stop option 2
    assert od[0x6085].value == 5000 * 10000  # quick_stop_deceleration in counts/s²
    assert od[0x1017].value == 100 and od[0x6099][1].value == 4242
    assert od[0x1600][1].value == 0x607A0020  # RPDO1 maps the target position
    assert od[0x1006].value == 2000


def test_dcf_errors(tmp_path, capsys):
    rc = main(["drives", "dcf", "--out", str(tmp_path / "none")])
    assert rc == 1 and "no such directory" in capsys.readouterr().err
