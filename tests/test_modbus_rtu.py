"""M62-M68 over Modbus RTU on a serial line, without hardware: two pseudo-terminals joined by a relay
thread (``PtyLink``), the simulated module serving RTU on one end, ``IoExecutor`` on the other."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator

import pytest

from fieldbus.modbus.config import (
    AnalogInputMap,
    AnalogOutputMap,
    Conversion,
    DigitalInputMap,
    DigitalOutputMap,
    ModbusConfig,
    ModbusDevice,
    ValueType,
    WordOrder,
)
from fieldbus.modbus.executor import IoExecutor
from fieldbus.modbus.faults import FaultKind, LinkDownError, ModbusConnectError, ModbusFault
from fieldbus.modbus.serialport import PtyLink, serial_port_problem
from fieldbus.modbus.sim import SimIoModule
from gcode_canon.commands import AnalogOutput, DigitalOutput, InputKind, WaitInput, WaitMode
from motiond.cli import main
from planner.setpoints import Setpoint

UNIT = 7  # not the default 1: the unit id must travel in the RTU frame


def m64(p: int, on: bool = True) -> DigitalOutput:
    return DigitalOutput(index=p, on=on, synced=False)


def m68(e: int, q: float) -> AnalogOutput:
    return AnalogOutput(index=e, value=q, synced=False)


def m66(p: int | None = None, e: int | None = None, mode: int = 0, q: float = 0.0) -> WaitInput:
    kind = InputKind.DIGITAL if p is not None else InputKind.ANALOG
    index = p if p is not None else e
    assert index is not None
    return WaitInput(kind=kind, index=index, mode=WaitMode(mode), timeout=q)


def rtu_config(port: str, *, baudrate: int = 38400, parity: str = "N") -> ModbusConfig:
    dev = ModbusDevice("rtu", serial=port, baudrate=baudrate, parity=parity, stopbits=1, bytesize=8,
                       unit=UNIT, timeout_s=0.25, retries=1, poll_ms=20, retry_backoff_s=0.01,
                       reconnect_max_s=0.2)
    return ModbusConfig(
        devices=(dev,),
        digital_outputs=(DigitalOutputMap(0, "rtu", 0), DigitalOutputMap(1, "rtu", 1),
                         DigitalOutputMap(3, "rtu", 9, safe=True)),
        analog_outputs=(AnalogOutputMap(0, "rtu", 2, Conversion(ValueType.INT16, scale=100.0)),
                        AnalogOutputMap(1, "rtu", 4, Conversion(ValueType.FLOAT32, WordOrder.BIG), safe=2.5)),
        digital_inputs=(DigitalInputMap(0, "rtu", 0), DigitalInputMap(2, "rtu", 5)),
        analog_inputs=(AnalogInputMap(0, "rtu", 1, Conversion(ValueType.INT16, scale=0.01)),),
    )


# the safe state as the module receives it: coils 0-1 in one request, then coil 9, then registers
SAFE_STATE = [("coil", 0, (0, 0)), ("coil", 9, (1,)), ("holding_register", 2, (0,)),
              ("holding_register", 4, (0x4020, 0x0000))]


def as_tuples(writes) -> list[tuple[str, int, tuple[int, ...]]]:
    return [(w.table, w.address, w.values) for w in writes]


def until(pred: Callable[[], object], timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.01)
    return bool(pred())


class Rig:
    def __init__(self, link: PtyLink, sim: SimIoModule, ex: IoExecutor) -> None:
        self.link, self.sim, self.ex = link, sim, ex
        self.faults: list[ModbusFault] = []
        self.recovered: list[str] = []


@pytest.fixture
def rig() -> Iterator[Rig]:
    link = PtyLink().start()
    sim = SimIoModule(serial=link.a, unit=UNIT, size=32, baudrate=38400)
    ex = IoExecutor(rtu_config(link.b))
    r = Rig(link, sim, ex)
    ex.on_fault, ex.on_recover = r.faults.append, r.recovered.append
    try:
        sim.start()
        ex.start()
        yield r
    finally:
        ex.stop()
        sim.stop()
        link.stop()


def test_start_writes_the_safe_state_over_rtu(rig: Rig) -> None:
    assert as_tuples(rig.sim.writes) == SAFE_STATE
    assert rig.ex.link_up and rig.ex.fault is None and rig.link.relayed > 0


def test_m64_m65_m68_land_in_the_module(rig: Rig) -> None:
    n = len(rig.sim.writes)
    rig.ex.execute(m64(1)).result(3)
    assert rig.sim.get("coil", 1) == 1
    rig.ex.execute(m64(3, on=False)).result(3)  # digital output 3 is coil 9 (safe: on)
    assert rig.sim.get("coil", 9) == 0
    rig.ex.execute(m64(1, on=False)).result(3)
    assert rig.sim.get("coil", 1) == 0
    rig.ex.execute(m68(0, -1.5)).result(3)  # int16, scale 100
    rig.ex.execute(m68(1, 3.25)).result(3)  # float32, high word first, one request
    assert rig.sim.registers("holding_register", 2, 1) == [(-150) & 0xFFFF]
    assert rig.sim.registers("holding_register", 4, 2) == [0x4050, 0x0000]
    got = [(w.table, w.address, w.values, w.function_code) for w in rig.sim.writes[n:]]
    assert got == [("coil", 1, (1,), 5), ("coil", 9, (0,), 5), ("coil", 1, (0,), 5),
                   ("holding_register", 2, ((-150) & 0xFFFF,), 6), ("holding_register", 4, (0x4050, 0), 16)]


def test_m62_on_a_setpoint_goes_out_over_rtu(rig: Rig) -> None:
    n = len(rig.sim.writes)
    rig.ex.on_setpoint(Setpoint(0.0, (0.0,), events=(DigitalOutput(index=0, on=True, synced=True),
                                                     DigitalOutput(index=1, on=True, synced=True))))
    w = rig.sim.wait_write("coil", 1, 1, since=n, timeout=3)
    assert w is not None and (w.address, w.values, w.function_code) == (0, (1, 1), 15)


def test_m66_l0_reads_a_digital_and_an_analog_input(rig: Rig) -> None:
    assert rig.ex.wait_input(m66(p=2)) == 0.0
    rig.sim.set("discrete_input", 5, 1)  # digital input 2
    rig.sim.set("input_register", 1, (-1234) & 0xFFFF)  # analog input 0, scale 0.01
    assert rig.ex.wait_input(m66(p=2)) == 1.0
    assert rig.ex.wait_input(m66(e=0)) == pytest.approx(-12.34)
    rig.sim.schedule(0.2, "discrete_input", 0, 1)
    assert rig.ex.wait_input(m66(p=0, mode=3, q=3)) == 1.0  # L3: waits for the level


def test_cable_pulled_is_a_fault_and_put_back_restores_the_safe_state_first(rig: Rig) -> None:
    link, sim, ex = rig.link, rig.sim, rig.ex
    ex.execute(m64(0)).result(3)
    ex.execute(m68(1, 7.0)).result(3)
    link.cut()
    # no answer: 2 tries of 0.25 s (plus a poll period) and the link is lost
    assert until(lambda: rig.faults, timeout=5)
    f = rig.faults[0]
    assert f.kind is FaultKind.LINK_LOST and f.device == "rtu" and link.b in str(f)
    assert "no answer" in f.message
    assert not ex.link_up and ex.state().links == {"rtu": False}
    with pytest.raises(LinkDownError, match="is down"):
        ex.execute(m64(1))
    with pytest.raises(LinkDownError):
        ex.wait_input(m66(p=0))
    assert not ex.acknowledge()
    time.sleep(0.3)  # a few reconnect attempts go nowhere while the cable is out
    assert rig.recovered == [] and not ex.link_up and link.dropped > 0
    n = len(sim.writes)
    link.restore()
    assert until(lambda: rig.recovered == ["rtu"], timeout=5)
    assert as_tuples(sim.writes[n:n + len(SAFE_STATE)]) == SAFE_STATE
    assert sim.get("coil", 0) == 0 and sim.registers("holding_register", 4, 2) == [0x4020, 0]
    assert ex.link_up and ex.acknowledge() and ex.fault is None
    ex.execute(m64(1)).result(3)
    assert sim.get("coil", 1) == 1
    sim.set("discrete_input", 0, 1)
    assert ex.wait_input(m66(p=0)) == 1.0


def test_stop_writes_the_safe_state_over_rtu(rig: Rig) -> None:
    rig.ex.execute(m64(0)).result(3)
    rig.ex.execute(m64(3, on=False)).result(3)
    rig.ex.stop()
    assert rig.sim.get("coil", 0) == 0 and rig.sim.get("coil", 9) == 1


def test_the_unit_id_travels_in_the_frame() -> None:
    # a module with another unit id refuses the safe state (pymodbus's simulator answers a request for
    # a unit it does not hold with exception 4, where a device on a real bus would stay silent)
    with PtyLink() as link, SimIoModule(serial=link.a, unit=UNIT + 1, size=32) as sim:
        ex = IoExecutor(rtu_config(link.b, baudrate=19200))
        with pytest.raises(ModbusConnectError) as err:
            ex.start()
        ex.stop()
        assert sim.writes == []
    msg = str(err.value)
    assert f"'rtu' at {link.b}: writing the safe state: exception 4" in msg


def test_nothing_at_the_other_end_is_no_answer_at_start() -> None:
    with PtyLink() as link:  # the port opens, but no module listens on the other end
        ex = IoExecutor(rtu_config(link.b))
        t0 = time.monotonic()
        with pytest.raises(ModbusConnectError) as err:
            ex.start()
        assert time.monotonic() - t0 < 5
        ex.stop()
    assert f"Modbus device 'rtu' at {link.b}: no answer to write coil 0 after 2 tries of 0.25 s" \
        in str(err.value)


# --- a port that does not exist ------------------------------------------------------------------


def test_missing_serial_port_is_named_at_start() -> None:
    port = "/dev/ttyCANON_NO_SUCH_PORT"
    ex = IoExecutor(rtu_config(port))
    t0 = time.monotonic()
    with pytest.raises(ModbusConnectError) as err:
        ex.start()
    assert time.monotonic() - t0 < 5
    ex.stop()
    msg = str(err.value)
    assert f"cannot connect to Modbus device 'rtu' at {port}: no such serial port" in msg


def test_missing_serial_port_for_the_simulator_is_named() -> None:
    port = "/dev/ttyCANON_NO_SUCH_PORT"
    with pytest.raises(OSError, match=rf"cannot open serial port {port}: no such serial port"):
        SimIoModule(serial=port).start()
    assert serial_port_problem(port) is not None


def test_a_port_in_use_is_named() -> None:
    with PtyLink() as link, SimIoModule(serial=link.a, size=8):
        assert serial_port_problem(link.a) == "the port is in use by another program"
        assert serial_port_problem(link.b) is None


def test_sim_io_cli_missing_serial_port(capsys) -> None:
    assert main(["sim", "io", "--serial", "/dev/ttyCANON_NO_SUCH_PORT"]) == 1
    err = capsys.readouterr().err.strip()
    assert "/dev/ttyCANON_NO_SUCH_PORT" in err and "no such serial port" in err
    assert "Traceback" not in err and len(err.splitlines()) == 1


def test_sim_io_cli_option_mistakes(capsys) -> None:
    assert main(["sim", "io", "--serial", "/dev/null", "--port", "0"]) == 1
    assert "--port is for Modbus TCP" in capsys.readouterr().err
    assert main(["sim", "io", "--baudrate", "9600"]) == 1
    assert "--baudrate needs --serial" in capsys.readouterr().err


# --- `canon sim io --serial` as a process --------------------------------------------------------


class SerialSim:
    """``canon sim io --serial PORT ... --log-writes`` in a child process."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "motiond.cli", "sim", "io", "--log-writes", *args],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1)
        self.lines: list[str] = []
        self.ready = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))
            if "listening on" in line:
                self.ready.set()
        self.ready.set()

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._reader.join(5)
        return self.proc.returncode


def test_canon_sim_io_serves_rtu_on_a_serial_port(tmp_path) -> None:
    machine = tmp_path / "machine.toml"
    with PtyLink() as link:
        machine.write_text(f"""
[[modbus.devices]]
name = "rtu"
serial = "{link.b}"
baudrate = 9600
parity = "N"
unit = {UNIT}
timeout_s = 0.5
retries = 2
poll_ms = 20

[[modbus.digital_outputs]]
index = 0
coil = 3

[[modbus.digital_inputs]]
index = 0
discrete_input = 40
""")
        sim = SerialSim("--config", str(machine), "--serial", link.a, "--baudrate", "115200")
        try:
            assert sim.ready.wait(20), sim.lines
            assert any(f"'rtu' (unit {UNIT}) listening on {link.a} (Modbus RTU, 115200 baud, 8N1)" in x
                       for x in sim.lines), sim.lines
            from motiond.config_modbus import read_modbus
            from motiond.configkit import Table, load_toml

            cfg = read_modbus(Table(load_toml(str(machine)), str(machine)))
            assert cfg is not None
            with IoExecutor(cfg) as ex:
                ex.execute(m64(0)).result(3)
                assert ex.wait_input(m66(p=0)) == 0.0  # discrete input 40: the module is big enough
            wrote = re.compile(r"^\d+\.\d+ rtu: write coil 3 = 1$")
            assert until(lambda: any(wrote.match(x) for x in sim.lines), 5), sim.lines
        finally:
            assert sim.stop() == 0
    assert "stopped" in sim.lines


@pytest.mark.skipif(not os.path.exists("/dev/ptmx"), reason="needs pseudo-terminals")
def test_pty_link_relays_both_ways_and_loses_bytes_when_cut() -> None:
    with PtyLink() as link:
        fa = os.open(link.a, os.O_RDWR | os.O_NOCTTY)
        fb = os.open(link.b, os.O_RDWR | os.O_NOCTTY)
        try:
            os.write(fa, b"\x01\x05ping")
            assert read_some(fb, 6) == b"\x01\x05ping"
            os.write(fb, b"pong")
            assert read_some(fa, 4) == b"pong"
            link.cut()
            os.write(fa, b"lost")
            assert until(lambda: link.dropped >= 4, 2)
            link.restore()
            os.write(fa, b"kept")
            assert read_some(fb, 4) == b"kept"  # not "lostkept"
        finally:
            os.close(fa)
            os.close(fb)


def read_some(fd: int, n: int, timeout: float = 2.0) -> bytes:
    import select

    out = b""
    deadline = time.monotonic() + timeout
    while len(out) < n and (left := deadline - time.monotonic()) > 0:
        r, _, _ = select.select([fd], [], [], left)
        if r:
            out += os.read(fd, n - len(out))
    return out
