"""The simulated drive's simulation-only fault object 0x2F00, written over SDO by a separate client
(its own bus object on the channel, as a test bench on a real bus), and ``canon sim inject``."""

from __future__ import annotations

import time
from collections.abc import Iterator

import canopen
import pytest
from canopen_helpers import Rig, make_config, unique_channel, wait_for

from fieldbus.canopen import SHIPPED_EDS, cia402
from fieldbus.canopen.cia402 import State
from fieldbus.canopen.config import CanBusConfig
from fieldbus.canopen.drive_sim import SIM_INJECT, SimDrive
from fieldbus.canopen.sim_process import SimBus
from motiond.cli import main


class Bench:
    """A CANopen client on its own bus object: SDO to the drives, their EMCYs; never NMT."""

    def __init__(self, channel: str) -> None:
        self.channel = channel
        self.network = canopen.Network()
        self.network.connect(**CanBusConfig("virtual", channel).bus_kwargs())

    def node(self, node_id: int) -> canopen.RemoteNode:
        if node_id not in self.network:
            self.network.add_node(node_id, str(SHIPPED_EDS))
        return self.network[node_id]

    def inject(self, node_id: int, code: int, delay_ms: int = 0) -> None:
        node = self.node(node_id)
        node.sdo[SIM_INJECT][2].raw = delay_ms
        node.sdo[SIM_INJECT][1].raw = code

    def close(self) -> None:
        self.network.disconnect()


@pytest.fixture
def drives() -> Iterator[tuple[SimBus, Bench]]:
    channel = unique_channel()
    sims = SimBus([SimDrive(1), SimDrive(2)], CanBusConfig("virtual", channel))
    assert wait_for(lambda: all(d.nmt_state != 0 for d in sims.drives.values()), 2.0)  # booted
    bench = Bench(channel)
    try:
        yield sims, bench
    finally:
        bench.close()
        sims.close()


def test_the_object_is_in_the_shipped_eds() -> None:
    od = canopen.import_od(str(SHIPPED_EDS), 1)
    record = od[SIM_INJECT]
    assert record.name.startswith("Simulation")
    assert record[1].data_type == canopen.objectdictionary.UNSIGNED16 and record[1].writable
    assert record[2].data_type == canopen.objectdictionary.UNSIGNED32 and record[2].writable


def test_sdo_write_faults_the_drive_with_that_emcy(drives) -> None:
    sims, bench = drives
    node = bench.node(2)
    assert cia402.decode(node.sdo[0x6041].raw) == State.SWITCH_ON_DISABLED
    bench.inject(2, 0x7300)
    assert sims[2].state == State.FAULT
    assert sims[2].emcys == [0x7300]
    assert sims[1].state != State.FAULT and sims[1].emcys == []  # only the addressed drive
    # the EMCY frame on the bus, and the fault in the statusword and 0x603F, read back over SDO
    assert wait_for(lambda: [e.code for e in node.emcy.log] == [0x7300], 1.0)
    assert cia402.decode(node.sdo[0x6041].raw) == State.FAULT  # bit 3, as a real drive shows it
    assert node.sdo[0x603F].raw == 0x7300
    assert node.sdo[SIM_INJECT][1].raw == 0x7300
    # fault reset works as after any fault: the reset EMCY (code 0), Switch on disabled
    node.sdo[0x6040].raw = 0x0000
    node.sdo[0x6040].raw = 0x0080
    assert sims[2].state == State.SWITCH_ON_DISABLED
    assert node.sdo[0x603F].raw == 0
    assert wait_for(lambda: [e.code for e in node.emcy.log] == [0x7300, 0], 1.0)


def test_delay_then_fault_and_cancel(drives) -> None:
    sims, bench = drives
    t0 = time.monotonic()
    bench.inject(1, 0x5000, delay_ms=300)
    assert sims[1].state != State.FAULT  # not yet
    assert wait_for(lambda: sims[1].state == State.FAULT, 2.0)
    assert time.monotonic() - t0 >= 0.3 and sims[1].emcys == [0x5000]
    bench.inject(2, 0x5000, delay_ms=300)
    bench.node(2).sdo[SIM_INJECT][1].raw = 0  # cancels it
    time.sleep(0.5)
    assert sims[2].state != State.FAULT and sims[2].emcys == []


def test_a_drive_without_the_object_aborts() -> None:
    channel = unique_channel()
    sims = SimBus([SimDrive(1)], CanBusConfig("virtual", channel))
    bench = Bench(channel)
    try:
        assert wait_for(lambda: sims[1].nmt_state != 0, 2.0)
        sims[1].abort_sdo(SIM_INJECT, 1, 0x06020000)  # as a drive whose EDS lacks it answers
        with pytest.raises(canopen.SdoAbortedError):
            bench.inject(1, 0x7300)
        assert sims[1].emcys == []
    finally:
        bench.close()
        sims.close()


def test_injected_by_sdo_mid_move_the_master_stops_everything() -> None:
    r = Rig(make_config(3)).up()
    bench = Bench(r.config.bus.channel)
    try:
        r.run(20, lambda k: [0.002 * k, 0.001 * k, 0.0])
        # the master does no SDO while streaming: the bench's SDO does not clash with it
        bench.inject(2, 0x7300, delay_ms=100)
        deadline = time.monotonic() + 3.0
        k = 20
        while r.master.fault is None and time.monotonic() < deadline:
            r.run(5, lambda i, k=k: [0.002 * (k + i), 0.001 * (k + i), 0.0])
            k += 5
        f = r.master.fault
        assert f is not None and (f.node, f.axis) == (2, "y") and "EMCY 0x7300" in f.reason
        held = r.master.positions()
        r.run(50, lambda i: [1.0, 1.0, 1.0])  # ignored: the master holds; its quick stop went out
        assert r.master.positions() == held
        assert wait_for(lambda: r.sim(2).state == State.FAULT, 2.0)
        assert wait_for(lambda: all(r.sim(n).velocity == 0.0 for n in (1, 2, 3)), 2.0)  # stopped
        # standard layout: quick stop option 2 ends in Switch on disabled
        assert r.sim(1).state == State.SWITCH_ON_DISABLED and r.sim(3).state == State.SWITCH_ON_DISABLED
        r.master.reset_faults()
        r.master.enable()
        assert r.master.fault is None
        assert [s.state for s in r.master.state] == [State.OPERATION_ENABLED] * 3
    finally:
        bench.close()
        r.close()


def test_cli_injects_by_axis(drives, capsys) -> None:
    sims, bench = drives
    rc = main(["sim", "inject", "--interface", "virtual", "--channel", bench.channel,
               "--axis", "y", "--emcy", "0x7300"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "node 2 (axis y): EMCY 0x7300 injected; the drive sent it" in out.out
    assert sims[2].state == State.FAULT and sims[2].emcys == [0x7300]


def test_cli_works_the_local_quick_stop_input(drives, capsys) -> None:
    sims, bench = drives
    rc = main(["sim", "inject", "--interface", "virtual", "--channel", bench.channel,
               "--axis", "x", "--quick-stop", "on"])
    assert rc == 0 and "node 1 (axis x): local quick-stop input on" in capsys.readouterr().out
    assert sims[1].quick_stop_input and not sims[2].quick_stop_input
    rc = main(["sim", "inject", "--interface", "virtual", "--channel", bench.channel,
               "--axis", "x", "--quick-stop", "off"])
    assert rc == 0 and not sims[1].quick_stop_input


def test_cli_errors(drives, capsys) -> None:
    sims, bench = drives
    rc = main(["sim", "inject", "--interface", "virtual", "--channel", bench.channel,
               "--axis", "q", "--emcy", "0x7300"])
    assert rc == 1 and "no drive for axis 'q'" in capsys.readouterr().err
    rc = main(["sim", "inject", "--interface", "virtual", "--channel", bench.channel,
               "--node", "9", "--emcy", "0x7300", "--timeout", "0.2"])
    assert rc == 1 and "node 9: no SDO answer" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["sim", "inject", "--axis", "x", "--emcy", "0x1FFFF"])
    assert exc.value.code == 2 and "16 bits" in capsys.readouterr().err
    assert all(d.emcys == [] for d in sims.drives.values())
