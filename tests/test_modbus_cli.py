"""``canon sim io`` as a separate process, and reading the ``[[modbus.*]]`` part of a machine file."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from pymodbus.client import AsyncModbusTcpClient

from motiond.cli import main

_LINE = re.compile(r"^(\d+\.\d+) (\S+): write (\w+) (\d+) = ([\d ]+)$")


class SimProcess:
    """``canon sim io ARGS --log-writes`` in a child process; its write log is parsed as it comes."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "motiond.cli", "sim", "io", "--log-writes", *args],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1,
            env={**os.environ, "COLUMNS": "200"},
        )
        self.lines: list[str] = []
        self.port: int | None = None
        self._got_port = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        if not self._got_port.wait(20):
            self.stop()
            raise RuntimeError(f"canon sim io did not start: {self.lines} {self.proc.stderr.read()}")

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))
            m = re.search(r"listening on 127\.0\.0\.1:(\d+)", line)
            if m:
                self.port = int(m.group(1))
                self._got_port.set()
        self._got_port.set()

    def writes(self) -> list[tuple[float, str, int, tuple[int, ...]]]:
        out = []
        for line in list(self.lines):
            m = _LINE.match(line)
            if m:
                out.append((float(m.group(1)), m.group(3), int(m.group(4)),
                            tuple(int(v) for v in m.group(5).split())))
        return out

    def wait_writes(self, n: int, timeout: float = 5.0) -> list[tuple[float, str, int, tuple[int, ...]]]:
        deadline = time.monotonic() + timeout
        while len(self.writes()) < n and time.monotonic() < deadline:
            time.sleep(0.01)
        return self.writes()

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


def client_io(port: int, fn):
    async def run():
        c = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=1.0, retries=0, reconnect_delay=0)
        if not await c.connect():
            raise ConnectionError(port)
        try:
            return await fn(c)
        finally:
            c.close()

    return asyncio.run(asyncio.wait_for(run(), 10))


def test_sim_io_serves_logs_writes_and_stops_on_sigterm() -> None:
    sim = SimProcess("--port", "0")
    try:
        async def fn(c):
            await c.write_coil(3, True, device_id=1)
            await c.write_registers(1, [10, 20], device_id=1)
            return (await c.read_coils(0, count=4, device_id=1)).bits[:4]

        assert client_io(sim.port, fn) == [False, False, False, True]
        writes = sim.wait_writes(2)
        assert [w[1:] for w in writes] == [("coil", 3, (1,)), ("holding_register", 1, (10, 20))]
        assert abs(writes[0][0] - time.monotonic()) < 30  # the same monotonic clock as ours
    finally:
        rc = sim.stop()
    assert rc == 0
    assert sim.lines[-1] == "stopped"


def test_sim_io_script_makes_an_input_answer_an_output(tmp_path: Path) -> None:
    script = tmp_path / "clamp.toml"
    script.write_text('[[rule]]\non = "coil"\naddress = 0\nequals = 1\nafter_s = 0.3\n'
                      'set = "discrete_input"\nset_address = 5\nvalue = 1\n\n'
                      '[[at]]\nafter_s = 0.0\nset = "input_register"\nset_address = 2\nvalue = 1234\n')
    sim = SimProcess("--port", "0", "--script", str(script))
    try:
        async def fn(c):
            ir = (await c.read_input_registers(2, count=1, device_id=1)).registers
            await c.write_coil(0, True, device_id=1)
            t0 = time.monotonic()
            for _ in range(300):  # bounded: 3 s
                if (await c.read_discrete_inputs(5, count=1, device_id=1)).bits[0]:
                    return ir, time.monotonic() - t0
                await asyncio.sleep(0.01)
            return ir, None

        ir, rose = client_io(sim.port, fn)
    finally:
        sim.stop()
    assert ir == [1234]
    assert rose is not None and 0.25 <= rose < 1.5


def test_sim_io_config_serves_each_simulated_device(tmp_path: Path) -> None:
    cfg = tmp_path / "m.toml"
    cfg.write_text('[[modbus.devices]]\nname = "a"\nport = 1\nunit = 7\nsimulate = true\n\n'
                   '[[modbus.devices]]\nname = "real"\nhost = "192.0.2.1"\n')
    sim = SimProcess("--config", str(cfg), "--port", "0")
    try:
        assert any("'a' (unit 7) listening on 127.0.0.1:" in line for line in sim.lines)

        async def fn(c):
            return not (await c.read_coils(0, count=1, device_id=7)).isError()

        assert client_io(sim.port, fn)
    finally:
        sim.stop()


@pytest.mark.parametrize(("script", "message"), [
    ('[[rule]]\non = "discrete_input"\naddress = 0\nequals = 1\nset = "coil"\nset_address = 0\nvalue = 1\n',
     "rule[0].on: must be one of coil, holding_register"),
    ('[[rule]]\non = "coil"\nadress = 0\n', "rule[0].address: missing (required)"),
    ('[[at]]\nafter_s = 1.0\nset = "coil"\nset_address = 0\nvalue = 1\nextra = 2\n',
     "at[0].extra: unknown key"),
    ('[[at]]\nafter_s = 1.0\nset = "coil"\nset_address = 300\nvalue = 1\n', "beyond --size 256"),
])
def test_sim_io_bad_script_is_one_line_naming_file_and_key(tmp_path: Path, capsys, script: str,
                                                            message: str) -> None:
    f = tmp_path / "s.toml"
    f.write_text(script)
    assert main(["sim", "io", "--port", "0", "--script", str(f)]) == 1
    err = capsys.readouterr().err.strip()
    assert str(f) in err and message in err and "\n" not in err


def test_sim_io_without_a_simulated_device(tmp_path: Path, capsys) -> None:
    cfg = tmp_path / "m.toml"
    cfg.write_text('[[modbus.devices]]\nname = "real"\nhost = "192.0.2.1"\n')
    assert main(["sim", "io", "--config", str(cfg)]) == 1
    assert "no [[modbus.devices]] to serve on this host ('real' at 192.0.2.1:502)" in capsys.readouterr().err


def test_sim_io_serves_the_device_a_daemon_connects_to(tmp_path: Path) -> None:
    # simulate = false on this host: the daemon connects to it and does not serve it itself
    cfg = tmp_path / "m.toml"
    cfg.write_text('[[modbus.devices]]\nname = "io"\nhost = "127.0.0.1"\nport = 1\nunit = 3\n'
                   'simulate = false\n\n[[modbus.devices]]\nname = "remote"\nhost = "192.0.2.1"\n')
    sim = SimProcess("--config", str(cfg), "--port", "0")
    try:
        assert any("'io' (unit 3) listening on 127.0.0.1:" in line for line in sim.lines)

        async def fn(c):
            return not (await c.read_coils(0, count=1, device_id=3)).isError()

        assert client_io(sim.port, fn)
    finally:
        sim.stop()


def test_sim_io_port_in_use_is_a_clear_error(capsys) -> None:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["sim", "io", "--port", str(port)]) == 1
    err = capsys.readouterr().err
    assert f"cannot listen on 127.0.0.1:{port}" in err


def test_sim_io_is_big_enough_for_the_configuration(tmp_path: Path) -> None:
    cfg = tmp_path / "m.toml"
    cfg.write_text('[[modbus.devices]]\nname = "io"\nsimulate = true\n'
                   '[[modbus.analog_inputs]]\nindex = 0\ninput_register = 999\ntype = "float32"\n')
    sim = SimProcess("--config", str(cfg), "--port", "0")
    try:
        async def fn(c):
            return (await c.read_input_registers(999, count=2, device_id=1)).isError()

        assert client_io(sim.port, fn) is False
    finally:
        sim.stop()
