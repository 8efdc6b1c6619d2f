"""Setpoints sent ahead by the SYNC process (``[canopen] setpoint_lead`` with ``sync = "process"``):
the buffer's rules, a late cycle costing no setpoint within the lead (and costing some without it),
stops passing the buffer so no setpoint computed before a stop reaches a drive after it, a drive
enabled while the SYNC runs never left without a setpoint, and the key checked with its name."""

from __future__ import annotations

import itertools
import struct
import threading
import time

import pytest

from fieldbus.canopen import cia402
from fieldbus.canopen import setpoint_buffer as sb
from fieldbus.canopen.clock import PeriodicRunner
from fieldbus.canopen.master import CanopenMaster
from motiond.config_canopen import read_canopen
from motiond.configkit import ConfigError, Table

SYNC, RPDO1 = 0x80, 0x200


# ------------------------------------------------------------------------------- the buffer's rules
class Wire:
    """A SetpointBuffer fed through the encoder and decoder, as in the SYNC process."""

    def __init__(self) -> None:
        self.sent: list[tuple[int, bytes]] = []
        self.buffer = sb.SetpointBuffer(lambda cob, data: self.sent.append((cob, bytes(data))))
        self.decoder = sb.Decoder()

    def feed(self, *messages: list[bytes], split: int = 0) -> None:
        data = b"".join(b"".join(m) for m in messages)
        chunks = [data] if not split else [data[i:i + split] for i in range(0, len(data), split)]
        for chunk in chunks:
            for m in self.decoder.feed(chunk):
                self.buffer.on_message(*m)

    def sync(self) -> bool:
        fed = self.buffer.synced()
        self.buffer.send_next()
        return fed

    def take(self) -> list[tuple[int, bytes]]:
        sent, self.sent = self.sent, []
        return sent


def test_a_set_goes_out_right_after_the_sync_before_its_own_and_a_late_one_is_dropped():
    w = Wire()
    w.feed(sb.encode(sb.START), sb.encode(sb.PUSH, [(0x201, b"a")], tag=1), split=7)
    assert w.take() == [(0x201, b"a")]  # for the next SYNC (number 1): at once
    w.feed(sb.encode(sb.PUSH, [(0x201, b"b")], tag=2), sb.encode(sb.PUSH, [(0x201, b"c")], tag=3))
    assert w.take() == [] and w.buffer.pending == [2, 3]
    assert w.sync() is True and w.take() == [(0x201, b"b")]  # SYNC 1 had its set; then the one for 2
    assert w.sync() is True and w.take() == [(0x201, b"c")]
    assert w.sync() is True and w.take() == []  # SYNC 3 had its set; none for 4
    assert w.sync() is False  # SYNC 4 found none: reported unfed
    w.feed(sb.encode(sb.PUSH, [(0x201, b"d")], tag=4))
    assert w.take() == [] and w.buffer.late == 1  # after its SYNC: dropped, never latched a SYNC late


def test_a_stop_drops_every_buffered_set_and_voids_sets_pushed_before_it():
    w = Wire()
    w.feed(sb.encode(sb.START), *(sb.encode(sb.PUSH, [(0x201, bytes([t]))], tag=t) for t in (2, 3, 4)))
    w.feed(sb.encode(sb.NOW_FLUSH, [(0x201, b"QS")], generation=1))
    assert w.take() == [(0x201, b"QS")] and w.buffer.pending == []
    w.feed(sb.encode(sb.PUSH, [(0x201, b"old")], tag=5, generation=0))  # computed before the stop
    assert w.buffer.pending == [] and w.buffer.void == 1
    for _ in range(5):
        w.sync()
    assert w.take() == []  # nothing computed before the stop ever went out after it
    w.feed(sb.encode(sb.PUSH, [(0x201, b"new")], tag=7, generation=1))
    assert w.buffer.pending == [7]


def test_a_drive_enabled_joins_every_buffered_set_and_one_homing_leaves_them():
    w = Wire()
    w.feed(sb.encode(sb.START), *(sb.encode(sb.PUSH, [(0x201, bytes([t]))], tag=t) for t in (2, 3)))
    w.feed(sb.encode(sb.NOW_MERGE, [(0x202, b"hold")]))
    assert w.take() == [(0x202, b"hold")]
    w.sync()
    assert sorted(w.take()) == [(0x201, b"\x02"), (0x202, b"hold")]
    w.feed(sb.encode(sb.DROP, [(0x201, b"")]))
    w.sync()
    assert w.take() == [(0x202, b"hold")]


def test_a_set_larger_than_one_atomic_write_is_split_and_a_broken_stream_is_refused():
    frames = [(0x200 + i % 100, struct.pack("<iH", i, 15)) for i in range(sb.MAX_FRAMES + 5)]
    parts = sb.encode(sb.NOW_FLUSH, frames, generation=2)
    assert len(parts) == 2 and all(len(p) <= sb.PIPE_BUF for p in parts)
    w = Wire()
    w.feed(parts)
    assert w.take() == frames and w.buffer.generation == 2
    with pytest.raises(ValueError, match="broken"):
        list(sb.Decoder().feed(sb.HEADER.pack(99, 0, 0, 0)))


# ------------------------------------------------------------------------------- on the bus
def lead_rig(local_rig, n: int, lead: int, **kw: object):
    """Drives on canon's local bus, the SYNC process sending their setpoints ``lead`` SYNCs ahead."""
    return local_rig(n, setpoint_lead=lead, **kw)


def stream(master: CanopenMaster, steps: int, stall_every: int = 0, stall_s: float = 0.0,
           on_step=None) -> tuple[PeriodicRunner, list[float]]:
    """Run ``steps`` steps paced by the SYNC process, each running as many cycles as the buffer wants
    (as the daemon's cycle does), the setpoints a slow ramp; every ``stall_every``-th step first
    stalls ``stall_s`` (a late cycle). ``on_step(i)`` before the ``i``-th step's cycles."""
    n = len(master.drives)
    sent: list[float] = []
    steps_run = [0]  # counted here: the runner's k skips the ticks a late step missed

    def step(k: int, t: float) -> bool:
        i = steps_run[0]
        steps_run[0] += 1
        if stall_every and i and i % stall_every == 0:
            time.sleep(stall_s)
        if on_step is not None:
            on_step(i)
        for _ in range(max(1, master.setpoints_wanted())):
            p = 0.0005 * len(sent)
            master.cycle([p] * n)
            sent.append(p)
        return master.fault is None or on_step is not None

    runner = PeriodicRunner(master.config.cycle_s, step, cycles=steps, tick=master.sync_tick).start()
    assert runner.join(120.0), "the cycle did not end"
    assert runner.error is None
    return runner, sent


def test_a_late_cycle_within_the_lead_costs_no_setpoint_and_without_the_lead_it_does(local_rig):
    """Every 8th step stalls 15 ms at a 10 ms period: with a lead of 4 (30 ms and more of slack) the
    drives get a setpoint at every SYNC; with a lead of 1 the same stalls cost setpoints."""
    missed = {}
    for lead in (4, 1):
        rig, _listener = lead_rig(local_rig, 2, lead, cycle_s=0.010, feedback_timeout_s=2.0)
        rig.up()
        sims = [rig.sim(node) for node in (1, 2)]
        for sim in sims:
            sim.record_targets = True
        # counted from the 4th step on, before the first stall: the first step, right after the first
        # SYNC, fills the buffer only then (on a loaded PC it can itself be late past the second SYNC)
        warm: dict[str, list[int]] = {}

        def warmed(k: int, warm=warm, sims=sims) -> None:
            if k == 4:
                warm["missed"] = [s.missed_setpoints for s in sims]
                warm["sync"] = [sims[0].syncs]

        stream(rig.master, 64, stall_every=8, stall_s=0.015, on_step=warmed)
        assert rig.master.fault is None, rig.master.fault
        missed[lead] = [s.missed_setpoints - m for s, m in zip(sims, warm["missed"], strict=True)]
        if lead == 4:
            # the drives latched one new target at every SYNC, in order, none skipped
            latched = [(s, t) for s, t in sims[0].latched if s > warm["sync"][0]]
            syncs = [s for s, _ in latched]
            assert syncs == list(range(syncs[0], syncs[0] + len(syncs))), syncs
            targets = [t for _, t in latched]
            assert all(b >= a for a, b in itertools.pairwise(targets))
        else:  # the SYNC process's reports tell the master of the SYNCs that found no set
            assert rig.master.missed_setpoints >= 3
        rig.close()
    assert missed[4] == [0, 0], missed
    assert min(missed[1]) >= 3, missed  # 7 stalls of 1.5 periods each


def test_a_quick_stop_passes_the_buffer_so_no_earlier_setpoint_follows_it(local_rig):
    """The stop goes out at once, and every set buffered before it is dropped: after the first quick
    stop frame, the last RPDO each drive gets before every SYNC is the quick stop."""
    rig, listener = lead_rig(local_rig, 2, 4, cycle_s=0.004, feedback_timeout_s=2.0)
    rig.up()
    master = rig.master
    called: list[float] = []

    def on_step(k: int) -> None:
        if k == 40:
            called.append(time.time())
            master.quick_stop("operator")

    stream(master, 70, on_step=on_step)
    assert master.fault is not None and "operator" in master.fault.reason
    listener.drain()
    frames = sorted(listener.payloads)
    for node in (1, 2):
        rpdos = [(t, struct.unpack("<iH", d)[1]) for t, c, d in frames if c == RPDO1 + node]
        first_qs = next(t for t, cw in rpdos if cw == cia402.CW_QUICK_STOP)
        assert first_qs - called[0] < 0.5, "the quick stop did not go out at once"
        last = None
        checked = 0
        for t, cob, data in frames:
            if t <= first_qs:
                continue
            if cob == RPDO1 + node:
                last = struct.unpack("<iH", data)[1]
            elif cob == SYNC:
                assert last in (None, cia402.CW_QUICK_STOP), (node, hex(last))
                checked += 1
        assert checked >= 10
        assert rig.sim(node).state != cia402.State.OPERATION_ENABLED


def test_a_drive_enabled_while_the_sync_runs_is_never_without_a_setpoint(local_rig):
    """The daemon's cycle runs while enable() walks the drives up: each drive's holding target goes
    out at once and joins every set already buffered, so no SYNC finds an enabled drive without one
    (the strict drive would count it, and fault past its RPDO timeout). With a lead of 8 at 4 ms a step
    late by up to 28 ms still costs none: a PC busy enough to hold the test's cycle off longer is not
    what is tested."""
    rig, _listener = lead_rig(local_rig, 2, 8, cycle_s=0.004, feedback_timeout_s=2.0)
    master = rig.master
    master.boot()
    for node in (1, 2):
        rig.sim(node).rpdo_timeout_syncs = 3
    enabling: list[threading.Thread] = []

    def on_step(k: int) -> None:
        if k == 10:  # from another thread, as the daemon does: the cycle goes on meanwhile
            enabling.append(threading.Thread(target=master.enable, name="enable"))
            enabling[0].start()

    stream(master, 200, on_step=on_step)
    enabling[0].join(30.0)
    assert master.streaming and master.fault is None, master.fault
    assert [rig.sim(node).missed_setpoints for node in (1, 2)] == [0, 0]
    assert all(rig.sim(node).state == cia402.State.OPERATION_ENABLED for node in (1, 2))


def canopen_table(**canopen: object) -> Table:
    return Table({"canopen": {"axes": {"x": {"node_id": 1}}, **canopen}}, "m.toml")


def test_the_setpoint_lead_key_needs_the_sync_process_and_says_so():
    c = read_canopen(canopen_table(interface="canon_local", channel="a", sync="process", setpoint_lead=3),
                     ["x"], 0.002)
    assert c.setpoint_lead == 3
    with pytest.raises(ConfigError, match=r'^m\.toml: canopen\.setpoint_lead: 3 needs sync = "process"'):
        read_canopen(canopen_table(setpoint_lead=3), ["x"], 0.002)
    with pytest.raises(ConfigError, match=r"canopen\.setpoint_lead"):
        read_canopen(canopen_table(interface="canon_local", channel="a", sync="process", setpoint_lead=9),
                     ["x"], 0.002)


# ------------------------------------------------------------------------------- the daemon's cycle
class CountingMaster:
    """As much of the master as the cycle uses: it wants ``wanted`` setpoints at each step."""

    def __init__(self, wanted: list[int]) -> None:
        self.wanted = wanted
        self.streaming = True
        self.sent: list[tuple[int, tuple[float, ...] | None]] = []
        self.step = 0

    def setpoints_wanted(self) -> int:
        return self.wanted[self.step]

    def sync(self) -> None:
        pass

    def cycle(self, positions):
        from fieldbus.canopen.master_records import DriveFeedback

        self.sent.append((self.step, None if positions is None else tuple(positions)))
        self.last_set_tag = 0  # sent at once
        return DriveFeedback(0, (0.0,), (0.0,), (cia402.State.OPERATION_ENABLED,), None, (0,))


class Ramp:
    """A planner that counts its setpoints."""

    is_idle = False
    waiting_for = None

    def __init__(self) -> None:
        self.n = 0

    def next_setpoint(self):
        from types import SimpleNamespace

        self.n += 1
        return SimpleNamespace(positions=(0.001 * self.n,), events=(), line=0, file="")


def test_the_cycle_runs_as_many_setpoints_as_the_buffer_wants_and_none_when_it_is_full():
    from types import SimpleNamespace

    from motiond.runtime.cycle import Cycle

    hooks = SimpleNamespace(io_cycle=lambda *a: None, fault=lambda *a: None)
    limits = SimpleNamespace(names=("x",), cycle_s=0.002)
    cyc = Cycle(limits, None, late_fault_s=1.0, simulated=True, hooks=hooks)  # type: ignore[arg-type]
    master = CountingMaster([4, 1, 0, 3])
    cyc.master, cyc.planner = master, Ramp()
    for k in range(4):
        master.step = k
        cyc._step(k, 0.0)
    per_step = [sum(1 for s, p in master.sent if s == k and p is not None) for k in range(4)]
    # the first step fills the lead; a full buffer takes none; a late step catches up
    assert per_step == [4, 1, 0, 3]
    assert [p for _, p in master.sent if p is not None] == [(0.001 * i,) for i in range(1, 9)]  # none lost
    assert [p for s, p in master.sent if s == 2] == [None]  # the checks still ran


def test_canon_run_with_the_setpoints_ahead(tmp_path):
    """``canon run`` with the motion side in its own process, the SYNC process sending the setpoints
    3 SYNCs ahead: the program runs to its end where it should, and the summary judges late cycles by
    the lead."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    from motion_process_helpers import SHORT, machine_text

    text = machine_text("canon_local", f"lead-{os.getpid()}", simulate=True)
    text = text.replace("simulate = true", 'simulate = true\nsync = "process"\nsetpoint_lead = 3', 1)
    machine = tmp_path / "machine.toml"
    machine.write_text(text)
    prog = tmp_path / "short.ngc"
    prog.write_text(SHORT)
    r = subprocess.run([sys.executable, "-m", "motiond.cli", "run", "--json", "--no-telemetry",
                        "--config", str(machine), str(prog)], capture_output=True, text=True, timeout=150,
                       cwd=Path(__file__).resolve().parent.parent)
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["ok"] and d["final_positions"] == {"x": 5.0, "y": 4.0, "z": 2.0}
    for a, want in zip("xyz", (5.0, 4.0, 2.0), strict=True):
        assert d["final_actual"][a] == pytest.approx(want, abs=1e-3)
    assert d["timing"]["setpoint_lead"] == 3


def test_a_drive_homing_leaves_the_buffered_sets_and_rejoins_them_after():
    """Homing's controlword goes by SDO (0x001F, bit 4 homing operation start): no cyclic RPDO
    buffered for the axis before it may reach the drive while it homes (their controlword 0x000F
    clears the start bit on a real drive): on the bus, none between the SDO that starts the homing and
    the one that ends it. After homing its holding target is in every buffered set again: no SYNC
    finds it without one but, at most, the one during the switch back to CSP (8 missed without the
    rejoin)."""
    import dataclasses

    from canopen_helpers import LocalListener, Rig, make_config, unique_channel

    from fieldbus.canopen.config import CanBusConfig
    from fieldbus.canopen.drive_sim import SimDrive

    channel = unique_channel()
    sims = [SimDrive(1), SimDrive(2, home_switch_counts=20000)]
    cfg = make_config(2, bus=CanBusConfig("canon_local", channel), sync="process", setpoint_lead=8,
                      cycle_s=0.010, feedback_timeout_s=2.0, homing="cia402", home_offset=-1.0)
    y = dataclasses.replace(cfg.drives[1], homing_method=19)
    cfg = dataclasses.replace(cfg, drives=(cfg.drives[0], y))
    listener = LocalListener(channel)
    rig = Rig(cfg, sims, check_budget=False)
    try:
        rig.up()
        master = rig.master
        homed: list[float] = []

        def home_y() -> None:
            homed.append(master.home("y"))

        steps = [0]
        before: list[int] = []

        def step(k: int, t: float) -> None:  # the targets held, as many cycles as the buffer wants
            steps[0] += 1
            if steps[0] == 10:  # the first step fills the buffer only after the first SYNC: from here on
                before.append(rig.sim(2).missed_setpoints)
            if steps[0] == 20:  # from another thread, as the daemon's service operations do
                threading.Thread(target=home_y, name="home").start()
            for _ in range(max(1, master.setpoints_wanted())):
                master.cycle(None)

        runner = PeriodicRunner(cfg.cycle_s, step, cycles=200, tick=master.sync_tick).start()
        assert runner.join(60.0) and runner.error is None  # 2 s: the search takes 0.2 s and more
        assert homed == [pytest.approx(-1.0)], (homed, master.fault)
        assert master.fault is None, master.fault
        assert rig.sim(2).mode == cia402.MODE_CSP
        # at most the SYNC between the SDO that switches the drive back to CSP and the holding target
        # sent again once it shows CSP (the simulated drive drops a pending target on a mode change)
        assert rig.sim(2).missed_setpoints - before[0] <= 1
        listener.drain()
        # SDO downloads to node 2's controlword: 0x2B, index 0x6040, sub 0, the value
        frames = sorted(listener.payloads)
        start = next(t for t, c, d in frames if c == 0x602 and d[:6] == bytes([0x2B, 0x40, 0x60, 0, 0x1F, 0]))
        end = next(t for t, c, d in frames if c == 0x602 and t > start
                   and d[:6] == bytes([0x2B, 0x40, 0x60, 0, 0x0F, 0]))
        assert [t for t, c, _ in frames if c == RPDO1 + 2 and start < t < end] == []
        assert sum(1 for t, c, _ in frames if c == RPDO1 + 1 and start < t < end) > 5  # x streamed on
    finally:
        rig.close()
        listener.close()


class TaggingMaster(CountingMaster):
    """... that pushes each set tagged with its SYNC, SYNC ``step + 1`` the last reported."""

    setpoint_generation = 0

    def __init__(self, wanted: list[int]) -> None:
        super().__init__(wanted)
        self.next_tag = 2

    @property
    def sync_number(self) -> int:
        return self.step + 1

    def cycle(self, positions):
        fb = super().cycle(positions)
        if positions is not None:
            self.last_set_tag, self.next_tag = self.next_tag, self.next_tag + 1
        return fb


class EventfulRamp(Ramp):
    """Its 2nd setpoint carries an event (an output switched with the move); after its 3rd it stands
    at a sync point."""

    def __init__(self) -> None:
        super().__init__()
        self.waiting_for = None
        self.point = object()

    def next_setpoint(self):
        sp = super().next_setpoint()
        if self.n == 2:
            sp.events = ("output on",)
        if self.n >= 3:
            self.waiting_for = self.point
        return sp


def test_with_setpoints_ahead_what_rides_on_a_setpoint_waits_until_it_goes_out():
    """An output switched with a move, and the planner's stop after it, are acted on when the
    setpoint's set goes out (right after the SYNC before its own), not when the cycle computed it
    ``setpoint_lead - 1`` SYNCs earlier."""
    from types import SimpleNamespace

    from motiond.runtime.cycle import Cycle

    seen: list[tuple[int, object]] = []
    master = TaggingMaster([3, 1, 1, 1, 1, 1])
    hooks = SimpleNamespace(io_cycle=lambda *a: None, fault=lambda *a: None,
                            io_event=lambda ev, stream: seen.append((master.step, ev)),
                            io_wait=lambda w: False)
    limits = SimpleNamespace(names=("x",), cycle_s=0.002)
    cyc = Cycle(limits, None, late_fault_s=1.0, simulated=True, hooks=hooks)  # type: ignore[arg-type]
    planner = EventfulRamp()
    cyc.master, cyc.planner = master, planner
    reached = []
    for k in range(6):
        master.step = k
        cyc._step(k, 0.0)
        reached.append(cyc._sync_reached is planner.point)
    # step 0 (SYNC 1 reported) computes setpoints 1-3 for SYNCs 2-4: the 2nd, for SYNC 3, goes out
    # after SYNC 2, reported at step 1; the 3rd (then the sync point) after SYNC 3, at step 2
    assert seen == [(1, "output on")]
    assert reached == [False, False, True, True, True, True]
