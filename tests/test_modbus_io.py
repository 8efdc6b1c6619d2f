"""M62-M68 through IoExecutor to the simulated module, over real Modbus TCP on 127.0.0.1."""

from __future__ import annotations

import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator

import pytest
from pymodbus.constants import ExcCodes

from fieldbus.modbus.config import (
    AnalogInputMap,
    AnalogOutputMap,
    AnalogSource,
    Conversion,
    DigitalInputMap,
    DigitalOutputMap,
    DigitalSource,
    ModbusConfig,
    ModbusDevice,
    ValueType,
    WordOrder,
)
from fieldbus.modbus.executor import TIMED_OUT, IoExecutor
from fieldbus.modbus.faults import (
    FaultKind,
    IoError,
    LinkDownError,
    ModbusConnectError,
    ModbusFault,
    WaitAborted,
)
from fieldbus.modbus.sim import Rule, SimIoModule
from gcode_canon.commands import AnalogOutput, DigitalOutput, Dwell, InputKind, WaitInput, WaitMode
from planner.setpoints import Setpoint


def m62(p: int) -> DigitalOutput:
    return DigitalOutput(index=p, on=True, synced=True)


def m63(p: int) -> DigitalOutput:
    return DigitalOutput(index=p, on=False, synced=True)


def m64(p: int) -> DigitalOutput:
    return DigitalOutput(index=p, on=True, synced=False)


def m65(p: int) -> DigitalOutput:
    return DigitalOutput(index=p, on=False, synced=False)


def m66(p: int | None = None, e: int | None = None, mode: int = 0, q: float = 0.0) -> WaitInput:
    kind = InputKind.DIGITAL if p is not None else InputKind.ANALOG
    index = p if p is not None else e
    assert index is not None
    return WaitInput(kind=kind, index=index, mode=WaitMode(mode), timeout=q)


def m67(e: int, q: float) -> AnalogOutput:
    return AnalogOutput(index=e, value=q, synced=True)


def m68(e: int, q: float) -> AnalogOutput:
    return AnalogOutput(index=e, value=q, synced=False)


def f32(regs: list[int]) -> float:
    return struct.unpack(">f", struct.pack(">HH", *regs))[0]


def make_config(port: int, *, name: str = "io", poll_ms: float = 10.0, timeout_s: float = 0.2,
                retries: int = 2, extra_do: tuple[DigitalOutputMap, ...] = ()) -> ModbusConfig:
    dev = ModbusDevice(name, port=port, timeout_s=timeout_s, retries=retries, poll_ms=poll_ms,
                       retry_backoff_s=0.01, reconnect_max_s=0.2)
    return ModbusConfig(
        devices=(dev,),
        digital_outputs=(DigitalOutputMap(0, name, 0), DigitalOutputMap(1, name, 1),
                         DigitalOutputMap(2, name, 2), DigitalOutputMap(5, name, 10, safe=True), *extra_do),
        analog_outputs=(
            AnalogOutputMap(0, name, 0, Conversion(ValueType.INT16, scale=100.0)),
            AnalogOutputMap(1, name, 4, Conversion(ValueType.FLOAT32, WordOrder.LITTLE), safe=1.5),
            AnalogOutputMap(2, name, 8, Conversion(ValueType.UINT16, scale=10.0, offset=1000.0)),
        ),
        digital_inputs=(DigitalInputMap(0, name, 0), DigitalInputMap(1, name, 1), DigitalInputMap(2, name, 2),
                        DigitalInputMap(4, name, 20, DigitalSource.COIL)),
        analog_inputs=(
            AnalogInputMap(0, name, 0, Conversion(ValueType.INT16, scale=0.01)),
            AnalogInputMap(1, name, 2, Conversion(ValueType.FLOAT32)),
            AnalogInputMap(2, name, 30, Conversion(ValueType.UINT16, offset=-5.0),
                           AnalogSource.HOLDING_REGISTER),
        ),
    )


class Rig:
    def __init__(self, sim: SimIoModule, ex: IoExecutor, faults: list[ModbusFault], recovered: list[str]):
        self.sim, self.ex, self.faults, self.recovered = sim, ex, faults, recovered


@pytest.fixture
def make_rig() -> Iterator[Callable[..., Rig]]:
    made: list[Rig] = []

    def make(*, rules: tuple[Rule, ...] = (), **kw) -> Rig:
        sim = SimIoModule(size=64, rules=rules).start()
        faults: list[ModbusFault] = []
        recovered: list[str] = []
        ex = IoExecutor(make_config(sim.port, **kw), on_fault=faults.append, on_recover=recovered.append)
        rig = Rig(sim, ex, faults, recovered)
        made.append(rig)
        ex.start()
        return rig

    yield make
    for rig in made:
        rig.ex.stop()
        rig.sim.stop()


@pytest.fixture
def rig(make_rig: Callable[..., Rig]) -> Rig:
    return make_rig()


def until(pred: Callable[[], object], timeout: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.005)
    return bool(pred())


# the safe state, written at start, at stop and on recovery; contiguous outputs share a request
SAFE_STATE = [("coil", 0, (0, 0, 0)), ("coil", 10, (1,)), ("holding_register", 0, (0,)),
              ("holding_register", 4, (0, 0x3FC0)), ("holding_register", 8, (1000,))]


def as_tuples(writes) -> list[tuple[str, int, tuple[int, ...]]]:
    return [(w.table, w.address, w.values) for w in writes]


# --- start, immediate outputs ---------------------------------------------------------------------


def test_start_puts_every_output_in_its_safe_state(rig: Rig) -> None:
    assert as_tuples(rig.sim.writes) == SAFE_STATE
    assert rig.ex.link_up and rig.ex.fault is None


def test_m64_m65_switch_a_coil_at_once(rig: Rig) -> None:
    n = len(rig.sim.writes)
    rig.ex.execute(m64(1)).result(2)
    assert rig.sim.get("coil", 1) == 1
    rig.ex.execute(m65(1)).result(2)
    assert rig.sim.get("coil", 1) == 0
    rig.ex.execute(m65(5)).result(2)  # digital output 5 is coil 10
    assert rig.sim.get("coil", 10) == 0
    assert as_tuples(rig.sim.writes[n:]) == [("coil", 1, (1,)), ("coil", 1, (0,)), ("coil", 10, (0,))]
    st = rig.ex.state()
    assert st.digital_outputs[1] is False and st.digital_outputs[5] is False
    assert st.written_digital_outputs[5] is False


def test_m68_writes_registers_with_each_conversion(rig: Rig) -> None:
    n = len(rig.sim.writes)
    rig.ex.execute(m68(0, -1.234)).result(2)  # int16, scale 100: -123
    rig.ex.execute(m68(1, 3.25)).result(2)  # float32, low word first
    rig.ex.execute(m68(2, 12.34)).result(2)  # uint16, *10 + 1000 = 1123.4 -> 1123
    assert rig.sim.registers("holding_register", 0, 1) == [(-123) & 0xFFFF]
    low, high = rig.sim.registers("holding_register", 4, 2)
    assert f32([high, low]) == 3.25
    assert rig.sim.registers("holding_register", 8, 1) == [1123]
    # the float32 pair goes in one request (function 16), not two
    assert [(w.address, w.function_code) for w in rig.sim.writes[n:]] == [(0, 6), (4, 16), (8, 6)]
    st = rig.ex.state()
    assert st.analog_outputs == {0: -1.234, 1: 3.25, 2: 12.34}
    assert st.written_analog_outputs[0] == pytest.approx(-1.23)


def test_bad_output_commands_are_refused_before_anything_is_sent(rig: Rig) -> None:
    n = len(rig.sim.writes)
    with pytest.raises(IoError, match="digital output 3 is not mapped"):
        rig.ex.execute(m64(3))
    with pytest.raises(IoError, match=r"analog output 0: .*outside the int16 range"):
        rig.ex.execute(m68(0, 400.0))
    with pytest.raises(IoError, match="analog output 9 is not mapped"):
        rig.ex.execute(m68(9, 1.0))
    assert rig.ex.check(m64(3)) == "digital output 3 is not mapped (modbus.digital_outputs)"
    assert "uint16 range" in (rig.ex.check(m67(2, -200.0)) or "")
    assert rig.ex.check(m64(0)) is None
    assert rig.ex.check(m66(e=0, mode=1, q=1)) == "M66 E0 L1: analog inputs can only be read with L0"
    time.sleep(0.05)
    assert len(rig.sim.writes) == n


# --- synchronized outputs -------------------------------------------------------------------------


def test_outputs_on_one_setpoint_to_adjacent_coils_share_one_request(rig: Rig) -> None:
    n = len(rig.sim.writes)
    rig.ex.on_setpoint(Setpoint(0.0, (0.0,), events=(m62(0), m62(1), m62(2), m67(0, 0.5))))
    assert until(lambda: len(rig.sim.writes) >= n + 2)
    time.sleep(0.05)
    got = [(w.table, w.address, w.values, w.function_code) for w in rig.sim.writes[n:]]
    assert got == [("coil", 0, (1, 1, 1), 15), ("holding_register", 0, (50,), 6)]
    st = rig.ex.state()
    assert [st.written_digital_outputs[i] for i in (0, 1, 2)] == [True, True, True]
    # a second write to the same coil in one hand-over is not merged: both go out, in order
    n = len(rig.sim.writes)
    rig.ex.on_setpoint(Setpoint(0.0, (0.0,), events=(m63(0), m62(0))))
    assert until(lambda: len(rig.sim.writes) >= n + 2)
    assert [w.values for w in rig.sim.writes[n:]] == [(0,), (1,)]


def test_m62_m63_m67_wait_for_their_setpoint(rig: Rig) -> None:
    n = len(rig.sim.writes)
    sp_rest = Setpoint(0.0, (0.0,), events=(Dwell(seconds=0.1),))  # other events are not I/O
    rig.ex.on_setpoint(sp_rest)
    time.sleep(0.05)
    assert len(rig.sim.writes) == n
    rig.ex.on_setpoint(Setpoint(0.002, (0.01,), events=(m62(0), m62(2), m67(0, 2.5))))
    assert until(lambda: len(rig.sim.writes) == n + 3)
    assert as_tuples(rig.sim.writes[n:]) == [("coil", 0, (1,)), ("coil", 2, (1,)),
                                             ("holding_register", 0, (250,))]
    rig.ex.on_setpoint(Setpoint(0.004, (0.02,), events=(m63(0),)))
    assert until(lambda: rig.sim.get("coil", 0) == 0)


class CycleLoop:
    """A stand-in for the daemon's cycle loop: absolute deadlines, one setpoint per period."""

    def __init__(self, ex: IoExecutor, stream: list[Setpoint], period: float) -> None:
        self.ex, self.stream, self.period = ex, stream, period
        self.sent: list[float] = []
        self.call_s: list[float] = []

    def run(self) -> None:
        t_next = time.monotonic() + self.period
        for sp in self.stream:
            while (left := t_next - time.monotonic()) > 0:
                time.sleep(min(left, 0.0005) if left < 0.002 else left - 0.0015)
            t = time.monotonic()
            self.sent.append(t)
            self.ex.on_setpoint(sp)
            self.call_s.append(time.monotonic() - t)
            t_next += self.period


def motion_stream(period: float, starts: dict[int, tuple]) -> list[Setpoint]:
    """70 cycles: at rest, then four moves; ``starts`` maps a cycle number to its events."""
    stream: list[Setpoint] = []
    x = 0.0
    for k in range(70):
        moving = 10 <= k < 25 or 30 <= k < 40 or 45 <= k < 52 or 55 <= k < 65
        if moving:
            x += 0.1
        stream.append(Setpoint(k * period, (x, 0.0, 0.0), events=starts.get(k, ())))
    return stream


def test_synchronized_outputs_follow_the_setpoint_stream(rig: Rig) -> None:
    period = 0.004  # a 4 ms cycle
    starts = {10: (m62(0),), 30: (m63(0), m67(0, 1.0)), 45: (m62(0),)}
    stream = motion_stream(period, starts)
    # the events ride on the first setpoint whose position moves
    for k in starts:
        assert stream[k].positions != stream[k - 1].positions
        assert stream[k - 1].positions == stream[k - 2].positions
    n = len(rig.sim.writes)
    loop = CycleLoop(rig.ex, stream, period)
    loop.run()
    assert until(lambda: len(rig.sim.writes) >= n + 4)
    writes = rig.sim.writes[n:]
    assert as_tuples(writes) == [("coil", 0, (1,)), ("coil", 0, (0,)), ("holding_register", 0, (100,)),
                                 ("coil", 0, (1,))]
    for w, k in zip(writes, [10, 30, 30, 45], strict=True):
        assert w.t >= loop.sent[k]  # not before its motion starts
        if k != 45:
            assert w.t < loop.sent[k + 15]  # and long before the next one (the one-cycle bound is
            # checked in test_modbus_sync.py, with the module in its own process as a real one is)
    assert sorted(loop.call_s)[len(loop.call_s) // 2] < period / 4  # handing over is cheap


def test_on_setpoint_does_not_wait_for_a_slow_device(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig(timeout_s=0.6)
    rig.sim.delay_s = 0.15  # each answer takes 150 ms (well below the timeout)
    n = len(rig.sim.writes)
    t0 = time.monotonic()
    rig.ex.on_setpoint(Setpoint(0.0, (0.0,), events=(m62(1),)))
    returned = time.monotonic() - t0
    assert returned < 0.1
    w = rig.sim.wait_write("coil", 1, 1, since=n, timeout=3)
    assert w is not None
    assert rig.ex.fault is None
    rig.sim.delay_s = 0.0


# --- M66 ------------------------------------------------------------------------------------------


def test_m66_l0_reads_the_current_digital_value(rig: Rig) -> None:
    assert rig.ex.wait_input(m66(p=1)) == 0.0
    rig.sim.set("discrete_input", 1, 1)
    assert rig.ex.wait_input(m66(p=1)) == 1.0  # a fresh read, not the last poll
    rig.sim.set("coil", 20, 1)  # digital input 4 comes from coil 20
    assert rig.ex.wait_input(m66(p=4)) == 1.0


def test_m66_l0_does_not_wait_for_the_next_poll_period(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig(poll_ms=3000.0)  # a slow poll: M66 asks for a read of its own
    time.sleep(0.05)
    rig.sim.set("discrete_input", 1, 1)
    v, dt = timed_wait(rig.ex, m66(p=1))
    assert v == 1.0 and dt < 1.5
    rig.sim.set("discrete_input", 1, 0)
    v, dt = timed_wait(rig.ex, m66(p=1, mode=4, q=5))  # fresh read at the start of a wait too
    assert v == 0.0 and dt < 1.5


def test_m66_l0_reads_analog_inputs_with_conversion(rig: Rig) -> None:
    rig.sim.set("input_register", 0, (-1234) & 0xFFFF)
    rig.sim.set_registers("input_register", 2, [0x4050, 0x0000])  # 3.25 as float32, high word first
    rig.sim.set("holding_register", 30, 17)
    assert rig.ex.wait_input(m66(e=0)) == pytest.approx(-12.34)
    assert rig.ex.wait_input(m66(e=1)) == 3.25
    assert rig.ex.wait_input(m66(e=2)) == 12.0  # 17 - 5


def timed_wait(ex: IoExecutor, cmd: WaitInput) -> tuple[float, float]:
    t0 = time.monotonic()
    v = ex.wait_input(cmd)
    return v, time.monotonic() - t0


def test_m66_l1_waits_for_a_rising_edge(rig: Rig) -> None:
    rig.sim.schedule(0.2, "discrete_input", 0, 1)
    v, dt = timed_wait(rig.ex, m66(p=0, mode=1, q=3))
    assert v == 1.0 and 0.15 <= dt < 2.0


def test_m66_l1_on_an_input_already_high_needs_a_new_edge(rig: Rig) -> None:
    rig.sim.set("discrete_input", 0, 1)
    assert until(lambda: rig.ex.state().digital_inputs[0])
    rig.sim.schedule(0.15, "discrete_input", 0, 0)
    rig.sim.schedule(0.3, "discrete_input", 0, 1)
    v, dt = timed_wait(rig.ex, m66(p=0, mode=1, q=3))
    assert v == 1.0 and 0.22 <= dt < 2.0  # not at once, not at the fall (0.15 s): at the new rise


def test_m66_l2_waits_for_a_falling_edge(rig: Rig) -> None:
    rig.sim.set("discrete_input", 2, 1)
    assert until(lambda: rig.ex.state().digital_inputs[2])
    rig.sim.schedule(0.2, "discrete_input", 2, 0)
    v, dt = timed_wait(rig.ex, m66(p=2, mode=2, q=3))
    assert v == 0.0 and 0.15 <= dt < 2.0


def test_m66_l3_l4_return_at_once_when_already_there(rig: Rig) -> None:
    v, dt = timed_wait(rig.ex, m66(p=1, mode=4, q=3))  # low already
    assert v == 0.0 and dt < 1.0
    rig.sim.set("discrete_input", 1, 1)
    v, dt = timed_wait(rig.ex, m66(p=1, mode=3, q=3))  # high already (fresh read)
    assert v == 1.0 and dt < 1.0


def test_m66_l3_l4_wait_for_the_level(rig: Rig) -> None:
    rig.sim.schedule(0.2, "discrete_input", 1, 1)
    v, dt = timed_wait(rig.ex, m66(p=1, mode=3, q=3))
    assert v == 1.0 and 0.15 <= dt < 2.0
    rig.sim.schedule(0.2, "discrete_input", 1, 0)
    v, dt = timed_wait(rig.ex, m66(p=1, mode=4, q=3))
    assert v == 0.0 and 0.15 <= dt < 2.0


@pytest.mark.parametrize("mode", [1, 2, 3])
def test_m66_timeout_gives_minus_one(rig: Rig, mode: int) -> None:
    v, dt = timed_wait(rig.ex, m66(p=0, mode=mode, q=0.3))  # input stays low
    assert v == TIMED_OUT == -1.0
    assert 0.3 <= dt < 1.5


def test_m66_waits_for_an_input_that_answers_an_output() -> None:
    rule = Rule("coil", 0, 1, 0.3, "discrete_input", 0, 1)  # a clamp closes 300 ms after its valve opens
    with SimIoModule(size=64, rules=[rule]) as sim:
        ex = IoExecutor(make_config(sim.port))
        with ex:
            t0 = time.monotonic()
            ex.execute(m64(0))
            v = ex.wait_input(m66(p=0, mode=3, q=2))
            dt = time.monotonic() - t0
    assert v == 1.0 and 0.25 <= dt < 1.5


def test_m66_bad_commands(rig: Rig) -> None:
    with pytest.raises(IoError, match="analog inputs can only be read with L0"):
        rig.ex.wait_input(m66(e=0, mode=3, q=1))
    with pytest.raises(IoError, match="digital input 7 is not mapped"):
        rig.ex.wait_input(m66(p=7))


def test_m66_can_be_aborted(rig: Rig) -> None:
    cancel = threading.Event()
    threading.Timer(0.1, cancel.set).start()
    t0 = time.monotonic()
    with pytest.raises(WaitAborted):
        rig.ex.wait_input(m66(p=0, mode=3, q=10), cancel=cancel)
    assert time.monotonic() - t0 < 2.0


# --- polled inputs in the machine state -----------------------------------------------------------


def test_inputs_are_polled_into_the_state(rig: Rig) -> None:
    rig.sim.set("discrete_input", 2, 1)
    rig.sim.set("input_register", 0, 250)
    assert until(lambda: rig.ex.state().digital_inputs[2] and rig.ex.state().analog_inputs[0] == 2.5)
    st = rig.ex.state()
    assert st.digital_inputs == {0: False, 1: False, 2: True, 4: False}
    assert st.input_age_s < 1.0
    assert st.links == {"io": True} and st.fault is None
    di, do, ai, ao = st.arrays()  # dense, indexed by P/E number, for the status message
    assert di == [False, False, True, False, False] and len(do) == 6 and do[5] is True
    assert ai == [2.5, 0.0, -5.0] and ao == [0.0, 1.5, 0.0] and st.io_ok
    # polled at the configured period (10 ms): count polls over a bounded interval
    p0 = rig.ex.worker.counters["polls"]
    time.sleep(0.3)
    polls = rig.ex.worker.counters["polls"] - p0
    assert 5 <= polls <= 32


# --- faults ---------------------------------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_device_at_start_names_host_and_port() -> None:
    port = free_port()  # nothing listens there
    ex = IoExecutor(make_config(port, timeout_s=0.1, retries=1))
    t0 = time.monotonic()
    with pytest.raises(ModbusConnectError) as err:
        ex.start()
    assert time.monotonic() - t0 < 5
    msg = str(err.value)
    assert f"127.0.0.1:{port}" in msg and "'io'" in msg and "connection refused" in msg
    ex.stop()


def test_wrong_address_at_start_is_named(rig: Rig) -> None:
    sim = SimIoModule(size=8).start()  # coil 10 (digital output 5) does not exist there
    try:
        ex = IoExecutor(make_config(sim.port))
        with pytest.raises(ModbusConnectError, match=r"127\.0\.0\.1:\d+: .*ILLEGAL_ADDRESS"):
            ex.start()
        ex.stop()
    finally:
        sim.stop()


def test_exception_response_to_a_write_is_a_named_fault(rig: Rig) -> None:
    rig.sim.fail("coil", 2, ExcCodes.DEVICE_FAILURE)
    fut = rig.ex.execute(m64(2))
    with pytest.raises(LinkDownError, match="DEVICE_FAILURE"):
        fut.result(3)
    assert until(lambda: rig.faults)
    f = rig.faults[0]
    assert f.kind is FaultKind.EXCEPTION and f.table == "coil" and f.address == 2
    assert "write coil 2 (digital output 2): exception 4 DEVICE_FAILURE" in str(f)
    assert f"127.0.0.1:{rig.sim.port}" in str(f)
    assert rig.ex.fault is f
    assert rig.ex.link_up  # the device answered: the link is fine
    rig.sim.fail("coil", 2, None)
    rig.ex.execute(m64(2)).result(3)
    assert rig.sim.get("coil", 2) == 1


def test_exception_response_to_a_poll_is_reported_once(rig: Rig) -> None:
    rig.sim.fail("input_register", 2, ExcCodes.ILLEGAL_ADDRESS)
    assert until(lambda: rig.faults)
    time.sleep(0.1)  # ten more polls
    assert len(rig.faults) == 1
    f = rig.faults[0]
    assert f.kind is FaultKind.EXCEPTION and f.table == "input_register"
    assert "read input register 0" in f.message and "ILLEGAL_ADDRESS" in f.message
    with pytest.raises(LinkDownError, match="analog input 1 cannot be read"):
        rig.ex.wait_input(m66(e=1))
    rig.sim.fail("input_register", 2, None)
    rig.sim.set("input_register", 0, 100)
    assert rig.ex.wait_input(m66(e=0)) == 1.0


def test_timeouts_retry_with_backoff_then_lose_the_link(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig(timeout_s=0.1, retries=2)
    rig.sim.delay_s = 0.5  # answers come too late
    t0 = time.monotonic()
    assert until(lambda: rig.faults, timeout=5)
    lost_after = time.monotonic() - t0
    f = rig.faults[0]
    assert f.kind is FaultKind.LINK_LOST and "after 3 tries of 0.1 s" in f.message
    assert 0.3 <= lost_after < 3.0
    assert rig.ex.worker.counters["retries"] >= 2
    assert not rig.ex.link_up
    rig.sim.delay_s = 0.0
    assert until(lambda: rig.recovered, timeout=5)
    assert rig.ex.link_up


def test_link_lost_and_back(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    sim, ex = rig.sim, rig.ex
    ex.execute(m64(0)).result(2)
    ex.execute(m68(1, 7.0)).result(2)
    sim.stop()
    assert until(lambda: rig.faults, timeout=3)
    f = rig.faults[0]
    assert f.kind is FaultKind.LINK_LOST and f"127.0.0.1:{sim.port}" in str(f)
    assert ex.fault is f and not ex.link_up and ex.state().links == {"io": False}
    # while down: outputs are refused (and reported from the cycle loop), inputs cannot be read
    with pytest.raises(LinkDownError, match="is down"):
        ex.execute(m64(1))
    ex.on_setpoint(Setpoint(0.0, (0.0,), events=(m62(1),)))  # must not raise on the cycle loop
    assert any(x.kind is FaultKind.REJECTED for x in rig.faults)
    with pytest.raises(LinkDownError):
        ex.wait_input(m66(p=0))
    assert not ex.acknowledge()
    # the module comes back: safe state first, then recovery is reported
    n = len(sim.writes)
    sim.start()
    assert until(lambda: rig.recovered == ["io"], timeout=5)
    assert as_tuples(sim.writes[n:n + len(SAFE_STATE)]) == SAFE_STATE
    assert sim.get("coil", 0) == 0 and sim.registers("holding_register", 4, 2) == [0, 0x3FC0]
    st = ex.state()
    assert st.digital_outputs[0] is False and st.analog_outputs[1] == 1.5
    assert ex.link_up and ex.acknowledge() and ex.fault is None
    ex.execute(m64(1)).result(2)
    assert sim.get("coil", 1) == 1
    assert ex.wait_input(m66(p=0)) == 0.0


def test_a_wait_in_progress_ends_when_the_link_drops(rig: Rig) -> None:
    threading.Timer(0.15, rig.sim.stop).start()
    t0 = time.monotonic()
    with pytest.raises(LinkDownError):
        rig.ex.wait_input(m66(p=0, mode=3, q=10))
    assert time.monotonic() - t0 < 3.0


def test_stop_writes_the_safe_state(rig: Rig) -> None:
    rig.ex.execute(m64(0)).result(2)
    rig.ex.execute(m65(5)).result(2)
    rig.ex.stop()
    assert rig.sim.get("coil", 0) == 0 and rig.sim.get("coil", 10) == 1


# --- several devices ------------------------------------------------------------------------------


def test_two_devices_each_get_their_own_traffic() -> None:
    with SimIoModule(size=16) as a, SimIoModule(size=16) as b:
        cfg = ModbusConfig(
            devices=tuple(ModbusDevice(name, port=m.port, timeout_s=0.2, retries=1, poll_ms=10,
                                       reconnect_max_s=0.2) for name, m in (("a", a), ("b", b))),
            digital_outputs=(DigitalOutputMap(0, "a", 3), DigitalOutputMap(1, "b", 3)),
            digital_inputs=(DigitalInputMap(0, "a", 0), DigitalInputMap(1, "b", 0)),
        )
        faults: list[ModbusFault] = []
        with IoExecutor(cfg, on_fault=faults.append) as ex:
            ex.execute(m64(1)).result(2)
            assert b.get("coil", 3) == 1 and a.get("coil", 3) == 0
            b.set("discrete_input", 0, 1)
            assert ex.wait_input(m66(p=1)) == 1.0 and ex.wait_input(m66(p=0)) == 0.0
            b.stop()
            assert until(lambda: faults)
            assert faults[0].device == "b" and ex.state().links == {"a": True, "b": False}
            ex.execute(m64(0)).result(2)  # device a carries on
            assert a.get("coil", 3) == 1


def test_one_shared_connection_for_writes_and_polls() -> None:
    with SimIoModule(size=64) as sim:
        dev = ModbusDevice("io", port=sim.port, timeout_s=0.2, retries=1, poll_ms=5, reconnect_max_s=0.2,
                           separate_poll_connection=False)
        cfg = ModbusConfig((dev,), digital_outputs=(DigitalOutputMap(0, "io", 0),),
                           digital_inputs=(DigitalInputMap(0, "io", 0),))
        recovered: list[str] = []
        with IoExecutor(cfg, on_recover=recovered.append) as ex:
            for i in range(20):  # writes interleave with polls every 5 ms on the one connection
                ex.execute(DigitalOutput(index=0, on=bool(i & 1), synced=False)).result(2)
            sim.set("discrete_input", 0, 1)
            assert ex.wait_input(m66(p=0, mode=3, q=2)) == 1.0
            sim.stop()
            assert until(lambda: not ex.link_up)
            sim.start()
            assert until(lambda: recovered == ["io"], timeout=5)
            ex.execute(m64(0)).result(2)
            assert sim.get("coil", 0) == 1


def test_rtu_device_that_cannot_be_opened_is_named() -> None:
    dev = ModbusDevice("rtu", serial="/dev/ttyNONEXISTENT9", timeout_s=0.1, retries=0)
    ex = IoExecutor(ModbusConfig((dev,), digital_outputs=(DigitalOutputMap(0, "rtu", 0),)))
    with pytest.raises(ModbusConnectError, match="'rtu' at /dev/ttyNONEXISTENT9"):
        ex.start()
    ex.stop()
    assert not ex.worker.running


def test_a_device_with_outputs_only_is_watched_too() -> None:
    with SimIoModule(size=16) as sim:
        dev = ModbusDevice("out", port=sim.port, timeout_s=0.1, retries=0, poll_ms=10, reconnect_max_s=0.2)
        faults: list[ModbusFault] = []
        with IoExecutor(ModbusConfig((dev,), digital_outputs=(DigitalOutputMap(0, "out", 5),)),
                        on_fault=faults.append) as ex:
            assert until(lambda: sim.requests > 20)  # a read-back of coil 5 every 10 ms
            sim.delay_s = 0.5  # the device hangs: no write is needed to notice
            assert until(lambda: faults, timeout=3)
            assert faults[0].kind is FaultKind.LINK_LOST and "read coil 5" in faults[0].message
            sim.delay_s = 0.0
            assert until(lambda: ex.link_up, timeout=5)


def test_a_gcode_program_through_the_interpreter() -> None:
    """M64/M65/M68 executed as the interpreter yields them; M66 answered by the executor into #5399."""
    from gcode_canon.interpreter import Interpreter
    from gcode_canon.machine import DryRunMachine
    from gcode_canon.settings import InterpreterSettings

    program = ("M64 P0\n"  # valve on; the clamp (discrete input 0) closes 0.3 s later
               "M66 P0 L3 Q2\n#1 = #5399\n"
               "M65 P0\n"
               "M66 P0 L4 Q0.2\n#2 = #5399\n"  # the clamp stays closed: timeout, -1
               "M68 E0 Q1.25\n"
               "M66 E0 L0\n#3 = #5399\n"
               "M2\n")
    rule = Rule("coil", 0, 1, 0.3, "discrete_input", 0, 1)
    with SimIoModule(size=64, rules=[rule]) as sim:
        sim.set("input_register", 0, 321)
        with IoExecutor(make_config(sim.port)) as ex:
            class Machine(DryRunMachine):
                def wait_input(self, cmd: WaitInput) -> float:
                    return ex.wait_input(cmd)

            interp = Interpreter(InterpreterSettings(), Machine())
            for cmd in interp.run_string(program, "clamp.ngc"):
                if isinstance(cmd, DigitalOutput | AnalogOutput):
                    assert not cmd.synced
                    ex.execute(cmd).result(2)
            params = interp.params
            assert params.get_numbered(1) == 1.0
            assert params.get_numbered(2) == -1.0
            assert params.get_numbered(3) == pytest.approx(3.21)
        # on, off, then the safe state at stop
        assert [w.values[0] for w in sim.writes_to("coil", 0)][-3:] == [1, 0, 0]
        assert sim.get("holding_register", 0) == 0  # safe state at stop, after 125 was written
        assert (125,) in [w.values for w in sim.writes_to("holding_register", 0)]


def test_coalesce_keeps_order_and_modbus_limits() -> None:
    from fieldbus.modbus.io_worker import WriteOp, coalesce

    def w(table: str, address: int, n: int = 1) -> WriteOp:
        return WriteOp(table, address, [1] * n, f"{table} {address}")

    groups = coalesce([w("coil", 0), w("coil", 1), w("coil", 3), w("holding_register", 4),
                       w("holding_register", 5, 2), w("coil", 4), w("coil", 4)])
    assert [[(o.table, o.address) for o in g] for g in groups] == [
        [("coil", 0), ("coil", 1)], [("coil", 3)], [("holding_register", 4), ("holding_register", 5)],
        [("coil", 4)], [("coil", 4)]]
    coils = coalesce([w("coil", i) for i in range(2000)])
    assert [len(g) for g in coils] == [1968, 32]
    regs = coalesce([w("holding_register", 2 * i, 2) for i in range(70)])
    assert [sum(len(o.values) for o in g) for g in regs] == [122, 18]


def test_reads_are_grouped_within_the_modbus_limits() -> None:
    from fieldbus.modbus.io_worker import plan_reads

    di = [DigitalInputMap(i, "io", a) for i, a in enumerate([0, 1, 10, 40, 2100])]
    di.append(DigitalInputMap(9, "io", 5, DigitalSource.COIL))
    ai = [AnalogInputMap(0, "io", 0, Conversion(ValueType.FLOAT32)), AnalogInputMap(1, "io", 124),
          AnalogInputMap(2, "io", 3, source=AnalogSource.HOLDING_REGISTER)]
    chunks = {(c.table, c.start, c.count) for c in plan_reads(di, ai)}
    assert chunks == {("discrete_input", 0, 11), ("discrete_input", 40, 1), ("discrete_input", 2100, 1),
                      ("coil", 5, 1), ("input_register", 0, 2), ("input_register", 124, 1),
                      ("holding_register", 3, 1)}
    many = plan_reads([DigitalInputMap(i, "io", i) for i in range(2500)], [])
    assert [(c.start, c.count) for c in many] == [(0, 2000), (2000, 500)]


def test_the_demo_machine_runs_on_its_simulated_module() -> None:
    """What the daemon does with no machine file: start the simulated module, then the executor."""
    from fieldbus.modbus.sim import start_simulated
    from motiond.config_modbus import demo_modbus

    with socket.socket() as s:  # the demo's port 5020 may be taken by someone's `canon sim io`
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = demo_modbus(port=port)
    (sim,) = start_simulated(cfg)
    try:
        assert sim.port == port and sim.size == 256
        with IoExecutor(cfg) as ex:
            ex.execute(m64(7)).result(2)
            ex.execute(m68(3, 1.5)).result(2)
            sim.set("discrete_input", 7, 1)
            sim.set("input_register", 3, 250)
            assert ex.wait_input(m66(p=7)) == 1.0 and ex.wait_input(m66(e=3)) == 2.5
        assert sim.get("coil", 7) == 0  # safe state at stop, after the 1 written
        assert (150,) in [w.values for w in sim.writes_to("holding_register", 3)]
    finally:
        sim.stop()
