"""The simulated I/O module over real Modbus TCP on loopback, with pymodbus's client."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator

import pytest
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.constants import ExcCodes

from fieldbus.modbus.sim import Rule, SimIoModule


@pytest.fixture
def sim() -> Iterator[SimIoModule]:
    mod = SimIoModule(size=64).start()
    try:
        yield mod
    finally:
        mod.stop()


def talk(port: int, fn):  # run fn(client) in a fresh loop with a connected client
    async def main():
        client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=1.0, retries=0, reconnect_delay=0)
        if not await client.connect():
            raise ConnectionError(f"cannot connect to 127.0.0.1:{port}")
        try:
            return await fn(client)
        finally:
            client.close()

    return asyncio.run(asyncio.wait_for(main(), 10))


def test_listens_on_loopback_with_a_free_port(sim: SimIoModule) -> None:
    assert sim.host == "127.0.0.1"
    assert sim.port > 0
    assert sim.running


def test_inputs_set_from_the_test_are_read_by_a_client(sim: SimIoModule) -> None:
    sim.set("discrete_input", 3, True)
    sim.set("discrete_input", 17, 1)
    sim.set("input_register", 5, 54321)
    sim.set_registers("holding_register", 10, [7, 8])

    async def fn(c):
        di = await c.read_discrete_inputs(0, count=20, device_id=1)
        ir = await c.read_input_registers(4, count=3, device_id=1)
        hr = await c.read_holding_registers(10, count=2, device_id=1)
        return di.bits[:20], ir.registers, hr.registers

    bits, ir, hr = talk(sim.port, fn)
    assert [i for i, b in enumerate(bits) if b] == [3, 17]
    assert ir == [0, 54321, 0]
    assert hr == [7, 8]


def test_every_write_is_recorded_with_a_timestamp(sim: SimIoModule) -> None:
    async def fn(c):
        t0 = time.monotonic()
        await c.write_coil(5, True, device_id=1)
        await c.write_coils(8, [True, False, True], device_id=1)
        await c.write_register(2, 0xBEEF, device_id=1)
        await c.write_registers(20, [1, 2], device_id=1)
        return t0, time.monotonic()

    t0, t1 = talk(sim.port, fn)
    got = [(w.table, w.address, w.values, w.function_code) for w in sim.writes]
    assert got == [("coil", 5, (1,), 5), ("coil", 8, (1, 0, 1), 15),
                   ("holding_register", 2, (0xBEEF,), 6), ("holding_register", 20, (1, 2), 16)]
    stamps = [w.t for w in sim.writes]
    assert t0 <= stamps[0] <= stamps[1] <= stamps[2] <= stamps[3] <= t1
    assert sim.get("coil", 5) == 1 and sim.get("coil", 10) == 1 and sim.get("coil", 9) == 0
    assert sim.registers("holding_register", 20, 2) == [1, 2]
    assert sim.wait_write("coil", 9, 0, timeout=0.1) is sim.writes[1]
    assert sim.wait_write("coil", 9, 1, timeout=0.05) is None


def test_rule_raises_an_input_300_ms_after_an_output() -> None:
    rule = Rule("coil", 0, 1, 0.3, "discrete_input", 4, 1)
    with SimIoModule(size=16, rules=[rule]) as sim:
        async def fn(c):
            await c.write_coil(0, True, device_id=1)
            t_on = time.monotonic()
            before = (await c.read_discrete_inputs(4, count=1, device_id=1)).bits[0]
            for _ in range(200):  # bounded: 2 s
                if (await c.read_discrete_inputs(4, count=1, device_id=1)).bits[0]:
                    return before, time.monotonic() - t_on
                await asyncio.sleep(0.01)
            return before, None

        before, rose_after = talk(sim.port, fn)
    assert before is False
    assert rose_after is not None and 0.25 <= rose_after < 1.0


def test_schedule_changes_an_input_later(sim: SimIoModule) -> None:
    sim.schedule(0.15, "input_register", 1, 99)
    assert sim.get("input_register", 1) == 0
    deadline = time.monotonic() + 2
    while sim.get("input_register", 1) != 99 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert sim.get("input_register", 1) == 99


def test_exception_responses(sim: SimIoModule) -> None:
    sim.fail("coil", 3, ExcCodes.DEVICE_FAILURE)

    async def fn(c):
        beyond = await c.read_coils(64, count=1, device_id=1)
        failed = await c.write_coil(3, True, device_id=1)
        sim.fail("coil", 3, None)
        ok = await c.write_coil(3, True, device_id=1)
        sim.fail("discrete_input", 20, ExcCodes.ILLEGAL_VALUE)
        di_bad = await c.read_discrete_inputs(16, count=8, device_id=1)
        di_ok = await c.read_discrete_inputs(0, count=8, device_id=1)
        return beyond, failed, ok, di_bad, di_ok

    beyond, failed, ok, di_bad, di_ok = talk(sim.port, fn)
    assert beyond.isError() and beyond.exception_code == ExcCodes.ILLEGAL_ADDRESS
    assert failed.isError() and failed.exception_code == ExcCodes.DEVICE_FAILURE
    assert not ok.isError()
    assert di_bad.isError() and di_bad.exception_code == ExcCodes.ILLEGAL_VALUE
    assert not di_ok.isError()
    assert [w.address for w in sim.writes] == [3]  # the refused write is not recorded


def test_stop_and_restart_on_the_same_port_keeps_contents(sim: SimIoModule) -> None:
    port = sim.port
    sim.set("input_register", 0, 42)
    sim.stop()
    assert not sim.running
    with pytest.raises(ConnectionError):  # nothing listens
        talk(port, lambda c: c.read_coils(0, count=1, device_id=1))
    sim.start()
    assert sim.port == port

    async def fn(c):
        return (await c.read_input_registers(0, count=1, device_id=1)).registers

    assert talk(port, fn) == [42]


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="size"):
        SimIoModule(size=0)
    with pytest.raises(ValueError, match="loopback only"):
        SimIoModule(host="0.0.0.0")
    with pytest.raises(ValueError, match="a rule fires on a write"):
        Rule("discrete_input", 0, 1, 0.1, "coil", 0, 1)
    sim = SimIoModule(size=8)
    with pytest.raises(ValueError, match=r"outside 0\.\.7"):
        sim.set("coil", 8, 1)
    with pytest.raises(ValueError, match="unknown table"):
        sim.set("coils", 0, 1)
    with pytest.raises(ValueError, match=r"0\.\.65535"):
        sim.set("input_register", 0, 70000)
