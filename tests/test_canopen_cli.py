"""``canon can-dump`` and ``canon sim drives``: decoding, and errors as one line without traceback."""

from __future__ import annotations

import argparse
import os
import signal
import threading
import time

import can.interfaces.virtual as virtual
import pytest
from canopen_helpers import Rig, make_config
from motion_process_helpers import fifo_allowed

from fieldbus.canopen.dump import describe, name_of
from motiond import cmd_can_dump
from motiond.cli import main

pytestmark = pytest.mark.timeout(60)


def test_frames_are_named_by_cob_id():
    assert name_of(0x000) == "NMT"
    assert name_of(0x080) == "SYNC"
    assert name_of(0x083) == "EMCY node 3"
    assert name_of(0x182) == "TPDO1 node 2"
    assert name_of(0x201) == "RPDO1 node 1"
    assert name_of(0x285) == "TPDO2 node 5"
    assert name_of(0x605) == "SDO request node 5"
    assert name_of(0x585) == "SDO response node 5"
    assert name_of(0x77F) == "heartbeat node 127"


def test_payloads_are_decoded():
    assert describe(0x000, bytes([0x82, 2])).endswith("reset communication -> node 2")
    assert describe(0x702, bytes([0])).endswith("boot-up")
    assert describe(0x702, bytes([5])).endswith("operational")
    assert describe(0x201, bytes.fromhex("10270000 0f00")).endswith("target 10000, controlword 0x000F")
    assert describe(0x181, bytes.fromhex("3706 f0d8ffff")).endswith(
        "statusword 0x0637 (Operation enabled), position -10000")
    assert describe(0x281, (-5).to_bytes(4, "little", signed=True)).endswith("following error -5")
    assert describe(0x081, bytes.fromhex("1023 01 0000000000")).endswith("error 0x2310, register 0x01")
    assert describe(0x601, bytes.fromhex("2b 4060 00 0600 0000")).endswith("write 0x6040:00")
    assert describe(0x581, bytes.fromhex("80 6060 00 3000 0906")).endswith("abort 0x6060:00 code 0x06090030")


def test_can_dump_watches_a_running_bus(capsys):
    r = Rig(make_config(1))
    try:
        args = argparse.Namespace(config=None, interface="virtual", channel=r.config.bus.channel, count=40,
                                  seconds=10.0, no_sync=False)
        listeners = len(virtual.channels.get(args.channel, ()))
        t = threading.Thread(target=cmd_can_dump.run, args=(args,), daemon=True)
        t.start()
        # The dump must be listening before the boot starts, or it misses the NMT reset: wait (bounded)
        # until its bus has joined the virtual channel.
        deadline = time.monotonic() + 10.0
        while len(virtual.channels.get(args.channel, ())) <= listeners and time.monotonic() < deadline:
            time.sleep(0.005)
        r.up()
        r.run(20, lambda k: [0.001 * k])
        t.join(10.0)
        assert not t.is_alive()
    finally:
        r.close()
    out = capsys.readouterr().out
    assert "NMT" in out and "reset communication -> node 1" in out
    assert "heartbeat node 1" in out and "boot-up" in out
    assert "SDO request node 1" in out


def test_unknown_interface_is_one_line_error(capsys):
    assert main(["can-dump", "--interface", "nosuchbus", "--seconds", "0.1"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("canon can-dump: cannot open nosuchbus bus") and "Traceback" not in err


def test_sim_drives_rejects_a_bad_config_file(tmp_path, capsys):
    bad = tmp_path / "m.toml"
    bad.write_text('[machine]\ncycle_ms = 2.0\n[axes.x]\n[canopen]\ninterface = "virtual"\n'
                   '[canopen.axes.x]\nnode_id = 300\n')
    assert main(["sim", "drives", "--config", str(bad)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"{bad}: canopen.axes.x.node_id: must be between 1 and 127, got 300"


def test_sim_drives_runs_the_drives_clock_at_tick_ms(tmp_path, capsys, monkeypatch):
    from fieldbus.canopen import sim_process

    ticks: list[float] = []

    policies: list[tuple[int, int]] = []

    class Counted(sim_process.SimBus):
        def __init__(self, *args, **kw):
            super().__init__(*args, **kw)
            ticks.append(self.tick_s)
            policies.append((os.sched_getscheduler(0), os.sched_getparam(0).sched_priority))

    monkeypatch.setattr(sim_process, "SimBus", Counted)
    path = tmp_path / "m.toml"
    path.write_text('[machine]\ncycle_ms = 2.0\n[axes.x]\n[canopen]\ninterface = "virtual"\n'
                    f'channel = "tick-{tmp_path.name}"\nrealtime_priority = 20\n'
                    '[canopen.axes.x]\nnode_id = 1\n')
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    policy = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
    assert main(["sim", "drives", "--config", str(path), "--tick-ms", "20", "--seconds", "0.05"]) == 0
    assert ticks == [0.02]
    # run in-process, it gives the signal handlers back: one left behind swallowed later Ctrl-Cs
    assert {sig: signal.getsignal(sig) for sig in before} == before
    # with a SCHED_FIFO cycle in the file the drives ran just below it (they stand in for hardware),
    # and the calling thread has its own policy back
    if fifo_allowed():
        assert policies == [(os.SCHED_FIFO, 19)], policies
    assert (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority) == policy
    assert main(["sim", "drives", "--config", str(path), "--tick-ms", "0", "--seconds", "0.05"]) == 1
    assert "--tick-ms 0: must be between 0.5 and 100" in capsys.readouterr().err
