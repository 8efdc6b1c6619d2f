"""IoExecutor: what the daemon calls to carry out M62-M68 on the Modbus I/O.

Three callers, three threads, none of which waits on the network:

* the cycle loop calls :meth:`IoExecutor.on_setpoint` every cycle; the synchronized outputs
  (M62/M63/M67) the planner put on that setpoint are converted and queued for the I/O worker at once,
  so they go on the wire in the cycle in which their motion starts;
* the interpreter's machine callbacks call :meth:`IoExecutor.execute` for M64/M65/M68 (queued at
  once; the returned future completes when the device has confirmed) and
  :meth:`IoExecutor.wait_input` for M66, which blocks the interpreter, not the cycle loop, and returns
  the value for #5399 (-1 on timeout);
* telemetry calls :meth:`IoExecutor.state`.

Faults (link lost, exception responses, outputs that cannot be sent) go to ``on_fault`` from the I/O
thread, and the first one stays in :attr:`IoExecutor.fault` until :meth:`IoExecutor.acknowledge`: the
daemon feed-holds on it. When a link returns, the worker writes every mapped output's safe value
before anything else and calls ``on_recover``. Writes posted while a link is down are refused and
reported, not replayed later: replaying a "laser on" after the recovery would undo the safe state.
"""

from __future__ import annotations

import concurrent.futures
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from types import MappingProxyType

from fieldbus.modbus.codec import CodecError, decode_output, encode
from fieldbus.modbus.config import AnalogOutputMap, DigitalOutputMap, ModbusConfig
from fieldbus.modbus.faults import FaultKind, IoError, LinkDownError, ModbusFault, WaitAborted
from fieldbus.modbus.io_worker import InputSnapshot, IoWorker, WriteOp, named_write
from gcode_canon.commands import AnalogOutput, Canon, DigitalOutput, InputKind, WaitInput, WaitMode
from planner.setpoints import Setpoint

log = logging.getLogger(__name__)

TIMED_OUT = -1.0
"""What M66 leaves in #5399 when the wait times out."""


@dataclass(frozen=True, slots=True)
class IoState:
    """A snapshot for telemetry. ``*_outputs`` are the values commanded last; ``written_*`` what the
    device has confirmed; inputs as last polled, ``input_age_s`` ago; ``links`` up or down."""

    t: float
    digital_outputs: MappingProxyType[int, bool]
    analog_outputs: MappingProxyType[int, float]
    written_digital_outputs: MappingProxyType[int, bool]
    written_analog_outputs: MappingProxyType[int, float]
    digital_inputs: MappingProxyType[int, bool]
    analog_inputs: MappingProxyType[int, float]
    input_age_s: float
    links: MappingProxyType[str, bool]
    fault: str | None
    named_inputs: MappingProxyType[str, float] = field(default_factory=lambda: MappingProxyType({}))
    named_outputs: MappingProxyType[str, float] = field(default_factory=lambda: MappingProxyType({}))
    """The named points (:class:`fieldbus.modbus.config.NamedPoint`): inputs as polled, outputs as
    commanded last."""

    @property
    def io_ok(self) -> bool:
        """Every Modbus device answers (``canon_status.io_ok``)."""
        return all(self.links.values())

    def arrays(self) -> tuple[list[bool], list[bool], list[float], list[float]]:
        """Digital inputs, digital outputs, analog inputs, analog outputs as dense lists indexed by
        the P/E number (unmapped numbers below the highest: False / 0.0), as ``canon_status`` sends."""
        def dense(m: MappingProxyType, empty: object) -> list:
            out = [empty] * (max(m) + 1 if m else 0)
            for k, v in m.items():
                out[k] = v
            return out

        return (dense(self.digital_inputs, False), dense(self.digital_outputs, False),
                dense(self.analog_inputs, 0.0), dense(self.analog_outputs, 0.0))


class IoExecutor:
    """Carries out the canonical I/O commands on the configured Modbus devices (module docstring)."""

    def __init__(self, config: ModbusConfig, *,
                 on_fault: Callable[[ModbusFault], None] | None = None,
                 on_recover: Callable[[str], None] | None = None) -> None:
        self.config = config
        self.on_fault = on_fault
        self.on_recover = on_recover
        self.fault: ModbusFault | None = None
        """The first fault not yet acknowledged (the daemon holds the feed while it is set)."""
        self.faults: deque[ModbusFault] = deque(maxlen=100)
        """The latest faults, newest last (bounded: a link down at 1 kHz rejects a lot)."""
        self._do = {m.index: m for m in config.digital_outputs}
        self._ao = {m.index: m for m in config.analog_outputs}
        self._di = {m.index: m for m in config.digital_inputs}
        self._ai = {m.index: m for m in config.analog_inputs}
        self._devices = {d.name: d for d in config.devices}
        self._by_coil = {(m.device, m.coil): m for m in config.digital_outputs}
        self._by_register = {(m.device, m.register): m for m in config.analog_outputs}
        self._named_out = {p.key: p for p in config.named if p.output}
        self._by_named = {(p.device, p.table, p.address): p for p in self._named_out.values()}
        for m in config.analog_outputs:  # a safe value that does not fit is a configuration error
            try:
                encode(m.safe, m.conversion)
            except CodecError as exc:
                raise IoError(f"analog output {m.index}: safe value: {exc}") from None
        # every key present from the start: state() copies these while other threads assign
        self._cmd_do: dict[int, bool] = {m.index: m.safe for m in config.digital_outputs}
        self._cmd_ao: dict[int, float] = {m.index: m.safe for m in config.analog_outputs}
        self._out_do: dict[int, bool] = dict(self._cmd_do)
        self._out_ao: dict[int, float] = dict(self._cmd_ao)
        self._cmd_named: dict[str, float] = {k: p.safe for k, p in self._named_out.items()}
        self._out_named: dict[str, float] = dict(self._cmd_named)
        self._cancel = threading.Event()
        self._lock = threading.Lock()
        self.worker = IoWorker(config, on_fault=self._on_fault, on_recover=self._on_recover,
                               on_written=self._on_written)

    # --- life cycle -----------------------------------------------------------------------------

    def start(self, timeout: float | None = None) -> IoExecutor:
        """Connect to every device, put the outputs in their safe state and start polling.
        :class:`fieldbus.modbus.faults.ModbusConnectError` names any device that cannot be reached."""
        self._cancel.clear()
        self.worker.start(timeout)
        return self

    def stop(self, *, safe: bool = True) -> None:
        """Cancel waits, write the safe state (``safe``, where the link is up), close the links."""
        self._cancel.set()
        self.worker.notify()
        self.worker.stop(safe=safe)

    def __enter__(self) -> IoExecutor:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def link_up(self) -> bool:
        return all(self.worker.link_up.values())

    def acknowledge(self) -> bool:
        """Clear :attr:`fault` if every link is up again; True if cleared."""
        with self._lock:
            if self.link_up:
                self.fault = None
                return True
            return False

    # --- the cycle loop -------------------------------------------------------------------------

    def on_setpoint(self, setpoint: Setpoint) -> None:
        """Carry out the I/O events riding on this cycle's setpoint. Never blocks, never raises for
        an I/O problem (that becomes a fault): it runs on the cycle loop."""
        batches: dict[str, list[tuple[DigitalOutput | AnalogOutput, WriteOp]]] = {}
        for ev in setpoint.events:
            if isinstance(ev, DigitalOutput | AnalogOutput):
                try:
                    device, op = self._op(ev)
                except IoError as exc:
                    self._reject(ev, str(exc))
                    continue
                batches.setdefault(device, []).append((ev, op))
        for device, items in batches.items():  # one hand-over per device: contiguous writes coalesce
            try:
                self.worker.post(device, *(op for _ev, op in items))
            except IoError as exc:
                for ev, _op in items:
                    self._reject(ev, str(exc))
                continue
            for ev, _op in items:
                self._commanded(ev)

    def write_point(self, key: str, value: float) -> concurrent.futures.Future[float]:
        """Set the named output point ``key`` (a coil: 0/1) now; never blocks. Returns the future of
        the device's confirmation (the ``time.monotonic()`` it came back). Raises :class:`IoError`
        for an unknown key or a value that does not fit, :class:`LinkDownError` if the link is down."""
        p = self._named_out.get(key)
        if p is None:
            raise IoError(f"no output point named {key!r}")
        try:
            op = named_write(p, value)
        except CodecError as exc:
            raise IoError(f"{key}: {exc}") from None
        op.future = concurrent.futures.Future()
        self.worker.post(p.device, op)
        self._cmd_named[key] = float(value)
        return op.future

    def commanded_point(self, key: str) -> float:
        """The value output point ``key`` was last commanded to (its safe value after a recovery)."""
        return self._cmd_named[key]

    def written_point(self, key: str) -> float:
        """The value of output point ``key`` the device has confirmed last."""
        return self._out_named[key]

    # --- the interpreter ------------------------------------------------------------------------

    def check(self, cmd: Canon) -> str | None:
        """What is wrong with an I/O command for this configuration (unmapped number, value that does
        not fit, M66 mode for analog input), or None; for the interpreter before queueing it."""
        try:
            if isinstance(cmd, DigitalOutput):
                self._map_do(cmd.index)
            elif isinstance(cmd, AnalogOutput):
                m = self._map_ao(cmd.index)
                self._encode(m, cmd.value)
            elif isinstance(cmd, WaitInput):
                self._map_input(cmd)
        except IoError as exc:
            return str(exc)
        return None

    def execute(self, cmd: DigitalOutput | AnalogOutput) -> concurrent.futures.Future[float]:
        """Write an output now (M64/M65/M68; a synchronized one given here is also written now).
        Returns a future that completes with the ``time.monotonic()`` of the device's confirmation,
        or with :class:`LinkDownError`. Raises :class:`IoError` for an unmapped number, a value that
        does not fit, or a link that is down."""
        if not isinstance(cmd, DigitalOutput | AnalogOutput):
            raise IoError(f"{cmd.NAME} is not an output command")
        return self._send(cmd)

    def wait_input(self, cmd: WaitInput, cancel: threading.Event | None = None) -> float:
        """M66: read or wait for an input; the value for #5399, or -1 when the wait times out.

        L0 (immediate) returns the value from a poll that started after the call (one is asked for at
        once, so this takes about one round trip, not a poll period). L1/L2 wait for a
        rising/falling edge after the wait began: a change between the first read after the call and
        a later poll; L3/L4 for the input to be (or already be) high/low. Analog inputs take L0
        only. Raises :class:`LinkDownError` when the device cannot be read (the link fault is reported
        to the daemon as well) and :class:`WaitAborted` when ``cancel`` or :meth:`stop` ends it.
        """
        kind, index, device = self._map_input(cmd)
        dev = self._devices[device]
        key = (kind, index)
        t0 = time.monotonic()
        # how long a fresh sample may take: a poll period, plus a request with all its retries
        fresh_s = dev.poll_ms / 1000.0 + (dev.retries + 1) * (dev.timeout_s + dev.retry_backoff_s) + 0.1
        worker = self.worker

        def value(snap: InputSnapshot) -> float:
            if kind == "digital":
                return 1.0 if snap.digital[index] else 0.0
            return float(snap.analog[index])

        def stopped() -> bool:
            return self._cancel.is_set() or (cancel is not None and cancel.is_set())

        def read_fresh(after: float, budget: float) -> InputSnapshot:
            snap = worker.wait_poll(
                lambda s: (s.polls.get(device, (0, -1.0))[1] >= after) or not worker.link_up[device]
                or stopped(), budget, self._cancel if cancel is None else cancel)
            if stopped():
                raise WaitAborted(f"M66 {'P' if kind == 'digital' else 'E'}{index}: wait aborted")
            if not worker.link_up[device]:
                raise LinkDownError(f"M66: input cannot be read, the link to Modbus device {device!r} at "
                                    f"{dev.where} is down")
            if snap is None or not fresh_after(snap, after):
                raise LinkDownError(f"M66: no poll of Modbus device {device!r} at {dev.where} completed "
                                    f"within {budget:.2f} s")
            if key in snap.bad:
                raise LinkDownError(f"M66: {kind} input {index} cannot be read (the device answers its "
                                    f"read with an exception; see the fault)")
            return snap

        def fresh_after(snap: InputSnapshot, after: float) -> bool:
            poll = snap.polls.get(device)
            return poll is not None and poll[1] >= after

        worker.poll_now(device)  # a fresh read now, not at the next poll period
        if cmd.mode is WaitMode.IMMEDIATE:
            return value(read_fresh(t0, fresh_s))

        prev: float | None = None  # edges count from the first read after the wait began
        deadline = t0 + max(cmd.timeout, 0.0)
        snap = read_fresh(t0, fresh_s + max(cmd.timeout, 0.0))
        while True:
            cur = value(snap)
            mode = cmd.mode
            if (mode is WaitMode.HIGH and cur == 1.0) or (mode is WaitMode.LOW and cur == 0.0) \
                    or (mode is WaitMode.RISE and prev == 0.0 and cur == 1.0) \
                    or (mode is WaitMode.FALL and prev == 1.0 and cur == 0.0):
                return cur
            prev = cur
            last_start = snap.polls[device][1]
            left = deadline - time.monotonic()
            if left <= 0:
                return TIMED_OUT
            snap_next = worker.wait_poll(
                lambda s, ls=last_start: s.polls.get(device, (0, -1.0))[1] > ls
                or not worker.link_up[device] or stopped(), left, self._cancel if cancel is None else cancel)
            if stopped():
                raise WaitAborted(f"M66 {'P' if kind == 'digital' else 'E'}{index}: wait aborted")
            if snap_next is None:
                return TIMED_OUT
            if not worker.link_up[device]:
                raise LinkDownError(f"M66: input cannot be read, the link to Modbus device {device!r} at "
                                    f"{dev.where} is down")
            if key in snap_next.bad:
                raise LinkDownError(f"M66: {kind} input {index} cannot be read (exception response)")
            snap = snap_next

    # --- telemetry ------------------------------------------------------------------------------

    def state(self) -> IoState:
        snap = self.worker.snapshot
        now = time.monotonic()
        fault = self.fault
        return IoState(
            t=now,
            digital_outputs=MappingProxyType(dict(self._cmd_do)),
            analog_outputs=MappingProxyType(dict(self._cmd_ao)),
            written_digital_outputs=MappingProxyType(dict(self._out_do)),
            written_analog_outputs=MappingProxyType(dict(self._out_ao)),
            digital_inputs=snap.digital,
            analog_inputs=snap.analog,
            input_age_s=now - snap.t if snap.seq else float("inf"),
            links=MappingProxyType(dict(self.worker.link_up)),
            fault=str(fault) if fault is not None else None,
            named_inputs=snap.named,
            named_outputs=MappingProxyType(dict(self._cmd_named)),
        )

    # --- internals ------------------------------------------------------------------------------

    def _map_do(self, index: int) -> DigitalOutputMap:
        m = self._do.get(index)
        if m is None:
            raise IoError(f"digital output {index} is not mapped (modbus.digital_outputs)")
        return m

    def _map_ao(self, index: int) -> AnalogOutputMap:
        m = self._ao.get(index)
        if m is None:
            raise IoError(f"analog output {index} is not mapped (modbus.analog_outputs)")
        return m

    def _map_input(self, cmd: WaitInput) -> tuple[str, int, str]:
        if cmd.kind is InputKind.DIGITAL:
            d = self._di.get(cmd.index)
            if d is None:
                raise IoError(f"M66 P{cmd.index}: digital input {cmd.index} is not mapped "
                              "(modbus.digital_inputs)")
            return "digital", cmd.index, d.device
        a = self._ai.get(cmd.index)
        if a is None:
            raise IoError(f"M66 E{cmd.index}: analog input {cmd.index} is not mapped (modbus.analog_inputs)")
        if cmd.mode is not WaitMode.IMMEDIATE:
            raise IoError(f"M66 E{cmd.index} L{int(cmd.mode)}: analog inputs can only be read with L0")
        return "analog", cmd.index, a.device

    @staticmethod
    def _encode(m: AnalogOutputMap, value: float) -> list[int]:
        try:
            return encode(value, m.conversion)
        except CodecError as exc:
            raise IoError(f"analog output {m.index}: {exc}") from None

    def _op(self, cmd: DigitalOutput | AnalogOutput) -> tuple[str, WriteOp]:
        """The device and the write for an output command; :class:`IoError` if it cannot be sent."""
        if isinstance(cmd, DigitalOutput):
            m = self._map_do(cmd.index)
            return m.device, WriteOp("coil", m.coil, [int(cmd.on)], f"digital output {cmd.index}",
                                     future=concurrent.futures.Future())
        ma = self._map_ao(cmd.index)
        return ma.device, WriteOp("holding_register", ma.register, self._encode(ma, cmd.value),
                                  f"analog output {cmd.index}", future=concurrent.futures.Future())

    def _commanded(self, cmd: DigitalOutput | AnalogOutput) -> None:
        if isinstance(cmd, DigitalOutput):
            self._cmd_do[cmd.index] = cmd.on
        else:
            self._cmd_ao[cmd.index] = cmd.value

    def _send(self, cmd: DigitalOutput | AnalogOutput) -> concurrent.futures.Future[float]:
        device, op = self._op(cmd)
        self.worker.post(device, op)
        self._commanded(cmd)
        assert op.future is not None
        return op.future

    def _reject(self, cmd: DigitalOutput | AnalogOutput, why: str) -> None:
        m = (self._do if isinstance(cmd, DigitalOutput) else self._ao).get(cmd.index)
        dev = self._devices.get(m.device) if m is not None else None
        where = f"{cmd.file}:{cmd.line}: " if cmd.file else ""
        self._on_fault(ModbusFault(FaultKind.REJECTED, dev.name if dev else "?", dev.where if dev else "?",
                                   f"{where}{why}"))

    def _on_written(self, op: WriteOp, t: float) -> None:
        """I/O thread: record what the device confirmed, for :meth:`state`."""
        p = self._by_named.get((op.device, op.table, op.address))
        if p is not None:
            self._out_named[p.key] = float(op.values[0]) if p.bit else decode_output(op.values, p.conversion)
        elif op.table == "coil":
            d = self._by_coil.get((op.device, op.address))
            if d is not None:
                self._out_do[d.index] = bool(op.values[0])
        else:
            a = self._by_register.get((op.device, op.address))
            if a is not None:
                self._out_ao[a.index] = decode_output(op.values, a.conversion)

    def _on_fault(self, fault: ModbusFault) -> None:
        with self._lock:
            self.faults.append(fault)
            if self.fault is None:
                self.fault = fault
        if fault.kind is FaultKind.LINK_LOST:
            self.worker.notify()
        if self.on_fault is not None:
            try:
                self.on_fault(fault)
            except Exception:
                log.exception("on_fault callback failed")

    def _on_recover(self, device: str) -> None:
        for m in self.config.digital_outputs:
            if m.device == device:
                self._cmd_do[m.index] = m.safe
        for ma in self.config.analog_outputs:
            if ma.device == device:
                self._cmd_ao[ma.index] = ma.safe
        for p in self._named_out.values():
            if p.device == device:
                self._cmd_named[p.key] = p.safe
        if self.on_recover is not None:
            try:
                self.on_recover(device)
            except Exception:
                log.exception("on_recover callback failed")


__all__ = ["TIMED_OUT", "IoExecutor", "IoState", "LinkDownError"]
