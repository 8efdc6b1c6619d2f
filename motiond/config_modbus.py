"""Read the ``[[modbus.*]]`` arrays of the machine file into :mod:`fieldbus.modbus.config`.

``modbus_for(load_machine(path))`` is what the daemon calls. ``read_modbus(root)`` takes the machine
file's root :class:`~motiond.configkit.Table` and returns a
:class:`~fieldbus.modbus.config.ModbusConfig`, or None when the file has no ``[modbus]`` part (a
machine without Modbus I/O). ``demo_modbus()`` is the Modbus part of the built-in demo machine used
when there is no file at all: one simulated module on 127.0.0.1 with 8 digital outputs, 4 analog
outputs, 8 digital inputs and 4 analog inputs. Every mistake names the file and the dotted key, e.g.
``machine.toml: modbus.analog_outputs[1].type: must be one of int16, uint16, float32, got 'int32'``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from fieldbus.modbus.codec import CodecError, encode
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
from motiond.configkit import ConfigError, Table, in_range, non_negative, one_of, positive

if TYPE_CHECKING:
    from motiond.config import MachineConfig

DEMO_PORT = 5020
_ARRAYS = ("devices", "digital_outputs", "analog_outputs", "digital_inputs", "analog_inputs")
_LOOPBACK = ("127.0.0.1", "localhost", "::1")


def demo_modbus(port: int = DEMO_PORT) -> ModbusConfig:
    """The demo machine's I/O: one simulated module ``io`` on 127.0.0.1:``port``.

    Digital outputs 0-7 are coils 0-7; analog outputs 0-3 are holding registers 0-3 (int16, two
    decimals: scale 100); digital inputs 0-7 are discrete inputs 0-7; analog inputs 0-3 are input
    registers 0-3 (int16, scale 0.01).
    """
    dev = ModbusDevice("io", host="127.0.0.1", port=port, unit=1, timeout_s=0.5, retries=3, poll_ms=20,
                       simulate=True)
    out = Conversion(ValueType.INT16, WordOrder.BIG, 100.0, 0.0)
    inp = Conversion(ValueType.INT16, WordOrder.BIG, 0.01, 0.0)
    return ModbusConfig(
        devices=(dev,),
        digital_outputs=tuple(DigitalOutputMap(i, "io", i) for i in range(8)),
        analog_outputs=tuple(AnalogOutputMap(i, "io", i, out) for i in range(4)),
        digital_inputs=tuple(DigitalInputMap(i, "io", i) for i in range(8)),
        analog_inputs=tuple(AnalogInputMap(i, "io", i, inp) for i in range(4)),
    )


def modbus_for(machine: MachineConfig) -> ModbusConfig | None:
    """The Modbus configuration of a loaded machine: the demo module for the built-in demo machine
    (no file), the file's ``[modbus]`` part otherwise (None when it has none)."""
    if machine.path is None or machine.root is None:
        return demo_modbus()
    return read_modbus(machine.root)


def read_modbus(root: Table) -> ModbusConfig | None:
    """The ``modbus`` part of a machine file (None if it has none); raises :class:`ConfigError`."""
    if "modbus" not in root:
        return None
    mb = root.table("modbus")
    tabs = {name: mb.array_of_tables(name) for name in _ARRAYS}  # read once: they remember their keys
    devices = [_device(t) for t in tabs["devices"]]
    if not devices:
        raise mb.error("devices", "at least one [[modbus.devices]] is required")
    names: dict[str, Table] = {}
    for dev, t in zip(devices, tabs["devices"], strict=True):
        if dev.name in names:
            raise t.error("name", f"device name {dev.name!r} is used twice")
        names[dev.name] = t

    def device_of(t: Table) -> str:
        if "device" not in t and len(devices) == 1:
            return devices[0].name
        name = t.get("device", str)
        if name not in names:
            raise t.error("device", f"no [[modbus.devices]] is named {name!r} "
                                    f"(known: {', '.join(sorted(names))})")
        return name

    dos = [_digital_output(t, device_of(t)) for t in tabs["digital_outputs"]]
    aos = [_analog_output(t, device_of(t)) for t in tabs["analog_outputs"]]
    dis = [_digital_input(t, device_of(t)) for t in tabs["digital_inputs"]]
    ais = [_analog_input(t, device_of(t)) for t in tabs["analog_inputs"]]

    for name, items in (("digital_outputs", dos), ("analog_outputs", aos), ("digital_inputs", dis),
                        ("analog_inputs", ais)):
        tables = tabs[name]
        seen: dict[int, int] = {}
        for i, m in enumerate(items):
            if m.index in seen:
                raise tables[i].error("index", f"{m.index} is already mapped by {name}[{seen[m.index]}]")
            seen[m.index] = i

    # two outputs writing the same coil or register would fight: refuse
    used: dict[tuple[str, str, int], str] = {}
    for i, d in enumerate(dos):
        key = (d.device, "coil", d.coil)
        if key in used:
            raise tabs["digital_outputs"][i].error("coil", f"{d.coil} is already written by {used[key]}")
        used[key] = f"digital output {d.index}"
    for i, a in enumerate(aos):
        for r in range(a.register, a.register + a.conversion.type.registers):
            key = (a.device, "register", r)
            if key in used:
                raise tabs["analog_outputs"][i].error(
                    "register", f"register {r} is already written by {used[key]}")
            used[key] = f"analog output {a.index}"

    for name in _ARRAYS:
        for t in tabs[name]:
            t.check_unknown()
    mb.check_unknown()
    try:
        return ModbusConfig(tuple(devices), tuple(dos), tuple(aos), tuple(dis), tuple(ais))
    except ValueError as exc:  # cross-checks above should have caught it; keep the file name anyway
        raise ConfigError(mb.file, mb.path, str(exc)) from None


def _address(v: int) -> str | None:
    return None if 0 <= v <= 65535 else "must be an address 0..65535"


def _device(t: Table) -> ModbusDevice:
    name = t.get("name", str, check=lambda v: None if v.strip() else "must not be empty")
    serial = t.get("serial", str, "")
    if serial and ("host" in t or "port" in t):
        raise t.error("serial", "a device is reached either by serial (Modbus RTU) or by host/port "
                                "(Modbus TCP), not both")
    host = t.get("host", str, "127.0.0.1", check=lambda v: None if v.strip() else "must not be empty")
    port = t.get("port", int, 502, check=in_range(1, 65535))
    simulate = t.get("simulate", bool, False)
    if simulate and (serial or host not in _LOOPBACK):
        raise t.error("simulate", f"a simulated module listens on 127.0.0.1 only; host is {host!r}"
                      if not serial else "the daemon simulates Modbus TCP modules only; for RTU run "
                      "`canon sim io --config FILE --serial PORT` on the other end of the line")
    return ModbusDevice(
        name=name,
        host=host,
        port=port,
        unit=t.get("unit", int, 1, check=in_range(0, 247)),
        timeout_s=t.get("timeout_s", float, 0.5, check=in_range(0.001, 60.0)),
        retries=t.get("retries", int, 3, check=in_range(0, 20)),
        poll_ms=t.get("poll_ms", float, 20.0, check=in_range(0.0, 60000.0)),
        simulate=simulate,
        serial=serial,
        baudrate=t.get("baudrate", int, 19200, check=positive),
        parity=t.get("parity", str, "N", check=one_of("N", "E", "O")),
        stopbits=t.get("stopbits", int, 1, check=one_of(1, 2)),
        bytesize=t.get("bytesize", int, 8, check=one_of(7, 8)),
        retry_backoff_s=t.get("retry_backoff_s", float, 0.01, check=non_negative),
        reconnect_max_s=t.get("reconnect_max_s", float, 2.0, check=positive),
        separate_poll_connection=t.get("separate_poll_connection", bool, True),
    )


def _index(t: Table) -> int:
    return t.get("index", int, check=lambda v: None if v >= 0 else "must be >= 0")


def _conversion(t: Table) -> Conversion:
    vtype = ValueType(t.get("type", str, "int16", check=one_of(*(v.value for v in ValueType))))
    order = WordOrder(t.get("word_order", str, "big", check=one_of(*(w.value for w in WordOrder))))
    if order is WordOrder.LITTLE and vtype is not ValueType.FLOAT32:
        raise t.error("word_order", f"only float32 (two registers) has a word order; type is {vtype.value}")
    scale = t.get("scale", float, 1.0, check=lambda v: None if v != 0 else "must not be 0")
    offset = t.get("offset", float, 0.0)
    return Conversion(vtype, order, scale, offset)


def _digital_output(t: Table, device: str) -> DigitalOutputMap:
    return DigitalOutputMap(_index(t), device, t.get("coil", int, check=_address), t.get("safe", bool, False))


def _analog_output(t: Table, device: str) -> AnalogOutputMap:
    index = _index(t)
    register = t.get("register", int, check=_address)
    conv = _conversion(t)
    _fits(t, "register", register, conv)
    safe = t.get("safe", float, 0.0)
    try:
        encode(safe, conv)
    except CodecError as exc:
        raise t.error("safe", str(exc)) from None
    return AnalogOutputMap(index, device, register, conv, safe)


def _one_of_keys(t: Table, keys: tuple[str, ...]) -> str:
    present = [k for k in keys if k in t]
    if len(present) != 1:
        raise t.error(keys[0], f"give exactly one of {', '.join(keys)}"
                      + (f" (found {', '.join(present)})" if present else ""))
    return present[0]


def _digital_input(t: Table, device: str) -> DigitalInputMap:
    index = _index(t)
    key = _one_of_keys(t, ("discrete_input", "coil"))
    return DigitalInputMap(index, device, t.get(key, int, check=_address), DigitalSource(key))


def _analog_input(t: Table, device: str) -> AnalogInputMap:
    index = _index(t)
    key = _one_of_keys(t, ("input_register", "holding_register"))
    register = t.get(key, int, check=_address)
    conv = _conversion(t)
    _fits(t, key, register, conv)
    return AnalogInputMap(index, device, register, conv, AnalogSource(key))


def _fits(t: Table, key: str, register: int, conv: Conversion) -> None:
    """A two-register value must not run past the last Modbus address."""
    last = register + conv.type.registers - 1
    if last > 65535:
        raise t.error(key, f"{conv.type.value} takes registers {register} and {last}: beyond the last "
                           "Modbus address 65535")
