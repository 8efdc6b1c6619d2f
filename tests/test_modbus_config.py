"""motiond.config_modbus: the [[modbus.*]] part of the machine file, and its mistakes."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

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
from motiond.config_modbus import demo_modbus, read_modbus
from motiond.configkit import ConfigError, Table, load_toml

ROOT = Path(__file__).resolve().parent.parent


def read(text: str, tmp_path: Path) -> ModbusConfig | None:
    f = tmp_path / "machine.toml"
    f.write_text(text)
    return read_modbus(Table(load_toml(f), str(f)))


def error(text: str, tmp_path: Path) -> str:
    with pytest.raises(ConfigError) as err:
        read(text, tmp_path)
    msg = str(err.value)
    assert msg.startswith(str(tmp_path / "machine.toml") + ": ")
    return msg.split(": ", 1)[1]


def test_the_schema_in_developing_md_reads(tmp_path: Path) -> None:
    doc = (ROOT / "docs" / "DEVELOPING.md").read_text()
    block = re.search(r"```toml\n(.*?)```", doc, re.S)
    assert block is not None
    start = block.group(1).index("[[modbus.devices]]")
    end = block.group(1).index("[telemetry]")
    cfg = read(block.group(1)[start:end], tmp_path)
    assert cfg is not None
    assert cfg.devices == (ModbusDevice("io", "127.0.0.1", 5020, 1, 0.5, 3, 20.0, True),)
    assert cfg.digital_outputs == (DigitalOutputMap(0, "io", 0, False),)
    conv = Conversion(ValueType.INT16, WordOrder.BIG, 100.0, 0.0)
    assert cfg.analog_outputs == (AnalogOutputMap(0, "io", 0, conv, 0.0),)
    assert cfg.digital_inputs == (DigitalInputMap(0, "io", 0, DigitalSource.DISCRETE_INPUT),)
    assert cfg.analog_inputs == (AnalogInputMap(0, "io", 0, Conversion(ValueType.INT16, scale=0.01)),)


def test_no_modbus_part_means_no_modbus(tmp_path: Path) -> None:
    assert read('[machine]\nname = "lathe"\n', tmp_path) is None


def test_full_example_with_two_devices(tmp_path: Path) -> None:
    cfg = read("""
[[modbus.devices]]
name = "io"
port = 5020
poll_ms = 10

[[modbus.devices]]
name = "rtu"
serial = "/dev/ttyUSB0"
baudrate = 115200
parity = "E"
unit = 3

[[modbus.digital_outputs]]
index = 4
device = "rtu"
coil = 17
safe = true

[[modbus.analog_outputs]]
index = 1
device = "io"
register = 10
type = "float32"
word_order = "little"
scale = 2
offset = -1.5
safe = 0.75

[[modbus.digital_inputs]]
index = 2
device = "io"
coil = 40

[[modbus.analog_inputs]]
index = 3
device = "rtu"
holding_register = 7
type = "uint16"
scale = 0.1
offset = 4
""", tmp_path)
    assert cfg is not None
    io, rtu = cfg.devices
    assert (io.port, io.poll_ms, io.where) == (5020, 10.0, "127.0.0.1:5020")
    assert (rtu.serial, rtu.baudrate, rtu.parity, rtu.unit, rtu.where) == ("/dev/ttyUSB0", 115200, "E", 3,
                                                                            "/dev/ttyUSB0")
    assert cfg.digital_outputs == (DigitalOutputMap(4, "rtu", 17, True),)
    assert cfg.analog_outputs == (AnalogOutputMap(1, "io", 10, Conversion(ValueType.FLOAT32, WordOrder.LITTLE,
                                                                          2.0, -1.5), 0.75),)
    assert cfg.digital_inputs == (DigitalInputMap(2, "io", 40, DigitalSource.COIL),)
    conv = Conversion(ValueType.UINT16, scale=0.1, offset=4.0)
    assert cfg.analog_inputs == (AnalogInputMap(3, "rtu", 7, conv, AnalogSource.HOLDING_REGISTER),)


def test_device_may_be_left_out_with_one_device(tmp_path: Path) -> None:
    cfg = read('[[modbus.devices]]\nname = "io"\n[[modbus.digital_outputs]]\nindex = 0\ncoil = 3\n', tmp_path)
    assert cfg is not None and cfg.digital_outputs == (DigitalOutputMap(0, "io", 3),)


DEV = '[[modbus.devices]]\nname = "io"\n'
DO = '[[modbus.digital_outputs]]\n'


@pytest.mark.parametrize(("text", "message"), [
    ("[modbus]\n", "modbus.devices: at least one [[modbus.devices]] is required"),
    ('[[modbus.devices]]\nname = ""\n', "modbus.devices[0].name: must not be empty"),
    (DEV + 'port = 70000\n', "modbus.devices[0].port: must be between 1 and 65535, got 70000"),
    (DEV + 'timeout_s = 0\n', "modbus.devices[0].timeout_s: must be between 0.001 and 60.0"),
    (DEV + 'retries = -1\n', "modbus.devices[0].retries: must be between 0 and 20"),
    (DEV + 'unit = 300\n', "modbus.devices[0].unit: must be between 0 and 247"),
    (DEV + 'pol_ms = 5\n', "modbus.devices[0].pol_ms: unknown key (misspelt?)"),
    (DEV + 'host = "10.1.2.3"\nsimulate = true\n',
     "modbus.devices[0].simulate: a simulated module listens on"),
    (DEV + 'serial = "/dev/ttyS0"\nport = 502\n', "modbus.devices[0].serial: a device is reached either by"),
    (DEV + 'parity = "X"\n', "modbus.devices[0].parity: must be one of N, E, O"),
    (DEV + 'serial = "/dev/ttyS0"\nbaudrate = 0\n', "modbus.devices[0].baudrate: must be > 0"),
    (DEV + 'serial = "/dev/ttyS0"\nstopbits = 3\n', "modbus.devices[0].stopbits: must be one of 1, 2"),
    (DEV + 'serial = "/dev/ttyS0"\nbytesize = 6\n', "modbus.devices[0].bytesize: must be one of 7, 8"),
    (DEV + 'serial = "/dev/ttyS0"\nsimulate = true\n',
     "modbus.devices[0].simulate: the daemon simulates Modbus TCP modules only; for RTU run "
     "`canon sim io --config FILE --serial PORT`"),
    (DEV + DEV, "modbus.devices[1].name: device name 'io' is used twice"),
    (DEV + '[modbus.digital_output]\nindex = 0\n', "modbus.digital_output: unknown key (misspelt?)"),
    (DEV + '[[modbus.digital_outputs]]\nindex = 0\ndevice = "oi"\ncoil = 0\n',
     "modbus.digital_outputs[0].device: no [[modbus.devices]] is named 'oi' (known: io)"),
    (DEV + '[[modbus.digital_outputs]]\nindex = 0\n', "modbus.digital_outputs[0].coil: missing (required)"),
    (DEV + DO + 'index = -1\ncoil = 0\n', "modbus.digital_outputs[0].index: must be >= 0"),
    (DEV + '[[modbus.digital_outputs]]\nindex = 0\ncoil = 70000\n',
     "modbus.digital_outputs[0].coil: must be an address 0..65535"),
    (DEV + '[[modbus.digital_outputs]]\nindex = 0\ncoil = 0\nsafe = 1\n',
     "modbus.digital_outputs[0].safe: must be bool, got int 1"),
    (DEV + DO + 'index = 0\ncoil = 0\n' + DO + 'index = 0\ncoil = 1\n',
     "modbus.digital_outputs[1].index: 0 is already mapped by digital_outputs[0]"),
    (DEV + DO + 'index = 0\ncoil = 5\n' + DO + 'index = 1\ncoil = 5\n',
     "modbus.digital_outputs[1].coil: 5 is already written by digital output 0"),
    (DEV + '[[modbus.analog_outputs]]\nindex = 0\nregister = 0\ntype = "int32"\n',
     "modbus.analog_outputs[0].type: must be one of int16, uint16, float32, got 'int32'"),
    (DEV + '[[modbus.analog_outputs]]\nindex = 0\nregister = 0\nscale = 0\n',
     "modbus.analog_outputs[0].scale: must not be 0"),
    (DEV + '[[modbus.analog_outputs]]\nindex = 0\nregister = 0\nword_order = "little"\n',
     "modbus.analog_outputs[0].word_order: only float32 (two registers) has a word order"),
    (DEV + '[[modbus.analog_outputs]]\nindex = 0\nregister = 0\nscale = 100.0\nsafe = 400.0\n',
     "modbus.analog_outputs[0].safe: 400.0 gives register value 40000, outside the int16 range"),
    (DEV + '[[modbus.analog_outputs]]\nindex = 0\nregister = 0\ntype = "float32"\n'
     '[[modbus.analog_outputs]]\nindex = 1\nregister = 1\n',
     "modbus.analog_outputs[1].register: register 1 is already written by analog output 0"),
    (DEV + '[[modbus.digital_inputs]]\nindex = 0\n',
     "modbus.digital_inputs[0].discrete_input: give exactly one of discrete_input, coil"),
    (DEV + '[[modbus.digital_inputs]]\nindex = 0\ndiscrete_input = 1\ncoil = 1\n',
     "give exactly one of discrete_input, coil (found discrete_input, coil)"),
    (DEV + '[[modbus.analog_inputs]]\nindex = 0\nregister = 1\n',
     "modbus.analog_inputs[0].input_register: give exactly one of input_register, holding_register"),
    (DEV + '[[modbus.analog_inputs]]\nindex = 0\ninput_register = 1\nscael = 2\n',
     "modbus.analog_inputs[0].scael: unknown key (misspelt?)"),
    ('[[modbus.devices]]\nname = "a"\n[[modbus.devices]]\nname = "b"\n[[modbus.digital_inputs]]\nindex = 0\n'
     'discrete_input = 0\n', "modbus.digital_inputs[0].device: missing (required)"),
    ('modbus = 3\n', "modbus: must be a table"),
    ('[modbus]\ndevices = 3\n', "modbus.devices: must be an array of tables"),
])
def test_mistakes_name_the_key(tmp_path: Path, text: str, message: str) -> None:
    assert message in error(text, tmp_path)


def test_demo_config() -> None:
    cfg = demo_modbus()
    (dev,) = cfg.devices
    assert (dev.host, dev.port, dev.simulate) == ("127.0.0.1", 5020, True)
    assert [m.index for m in cfg.digital_outputs] == list(range(8))
    assert [m.index for m in cfg.analog_outputs] == list(range(4))
    assert [m.index for m in cfg.digital_inputs] == list(range(8))
    assert [m.index for m in cfg.analog_inputs] == list(range(4))
    assert demo_modbus(port=6000).devices[0].port == 6000


def test_modbus_config_cross_checks_from_code() -> None:
    with pytest.raises(ValueError, match="digital output 0: unknown device 'x'"):
        ModbusConfig((ModbusDevice("io"),), digital_outputs=(DigitalOutputMap(0, "x", 0),))
    with pytest.raises(ValueError, match="analog input 1 mapped twice"):
        ModbusConfig((ModbusDevice("io"),),
                     analog_inputs=(AnalogInputMap(1, "io", 0), AnalogInputMap(1, "io", 2)))


def test_modbus_for_a_loaded_machine(tmp_path: Path) -> None:
    from motiond.config import load_machine
    from motiond.config_modbus import modbus_for

    assert modbus_for(load_machine(None)) == demo_modbus()
    axes = "[axes.x]\nmax_velocity = 100.0\nmax_acceleration = 1000.0\nmax_jerk = 10000.0\n"
    f = tmp_path / "m.toml"
    f.write_text(axes)
    assert modbus_for(load_machine(str(f))) is None
    f.write_text(axes + '[[modbus.devices]]\nname = "io"\nport = 1502\n'
                 '[[modbus.digital_outputs]]\nindex = 3\ncoil = 7\n')
    cfg = modbus_for(load_machine(str(f)))
    assert cfg is not None and cfg.devices[0].port == 1502
    assert cfg.digital_outputs == (DigitalOutputMap(3, "io", 7),)
    f.write_text(axes + '[[modbus.devices]]\nname = "io"\nprot = 1502\n')
    with pytest.raises(ConfigError, match=r"m\.toml: modbus\.devices\[0\]\.prot: unknown key"):
        modbus_for(load_machine(str(f)))
