"""The Modbus traffic, off the cycle loop: one thread with its own asyncio loop, one pymodbus async
client and one task per device.

Other threads talk to it without waiting: :meth:`IoWorker.post` hands a :class:`WriteOp` to the
device's task (``call_soon_threadsafe``), and the inputs come back as an immutable
:class:`InputSnapshot` swapped in after every poll (:attr:`IoWorker.snapshot`), with a condition
variable for those that want to wait for the next one (:meth:`IoWorker.wait_poll`).

Each device has two tasks:

* a writer that serves the queued writes in order (writes handed over together to contiguous
  addresses of one table go out as one request: see :func:`coalesce`), and (re)connects:
  ``timeout_s`` per attempt; on failure it waits and tries again, the wait doubling from
  ``retry_backoff_s`` up to ``reconnect_max_s``. After a connect that follows a lost link it drops
  the writes queued meanwhile, writes every mapped output's safe value, and only then reports the
  recovery and accepts writes;
* a poller that reads the inputs every ``poll_ms`` (a device with outputs only gets one small
  read-back of an output instead, so that a device that stops answering is noticed without a write),
  over a second TCP connection (``separate_poll_connection``, the default) so that a write never
  waits behind a read; with one connection (RTU, or the option off) pymodbus's request lock
  interleaves them, and a write waits for one read at most;
* a request that times out is sent again up to ``retries`` more times, waiting ``retry_backoff_s``,
  then twice that, ... between tries; when all fail, or the connection drops, the link is lost: the
  client is closed, a :class:`FaultKind.LINK_LOST` fault goes to ``on_fault``, and the loop goes back
  to connecting;
* a Modbus exception response is a :class:`FaultKind.EXCEPTION` fault naming the exception and the
  address; the link stays up (the device is there, the request was wrong).

pymodbus's own retries and automatic reconnection are turned off (``retries=0``,
``reconnect_delay=0``) so that this loop alone decides, and reports, what happens.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

from fieldbus.modbus.codec import decode, encode
from fieldbus.modbus.config import (
    AnalogInputMap,
    AnalogSource,
    DigitalInputMap,
    DigitalSource,
    ModbusConfig,
    ModbusDevice,
    NamedPoint,
)
from fieldbus.modbus.connecting import ConnectingMixin
from fieldbus.modbus.faults import (
    FaultKind,
    LinkDownError,
    ModbusConnectError,
    ModbusFault,
    exception_name,
)

log = logging.getLogger(__name__)

MAX_BITS_PER_READ = 2000  # Modbus limits for one read request
MAX_REGS_PER_READ = 125
MAX_COILS_PER_WRITE = 1968
MAX_REGS_PER_WRITE = 123
GAP = 16  # addresses apart before a read is split in two (rather than reading the gap)


@dataclass(slots=True)
class WriteOp:
    """One write for a device task: a coil (``values = [0|1]``) or consecutive holding registers."""

    table: str  # "coil" or "holding_register"
    address: int
    values: list[int]
    what: str  # "digital output 3", for messages
    device: str = ""
    posted: float = field(default_factory=time.monotonic)
    future: concurrent.futures.Future[float] | None = None
    """Completed with the time the answer came back, or with the exception that stopped it."""


@dataclass(frozen=True, slots=True)
class InputSnapshot:
    """The inputs as last polled. ``polls[device]`` is ``(count, start time of that poll)``; ``bad``
    holds the ``("digital"|"analog", index)`` and ``("named", key)`` whose last read failed (their
    values are older). ``named``: the named input points (:class:`NamedPoint`), bits as 0.0/1.0."""

    seq: int
    t: float
    digital: MappingProxyType[int, bool]
    analog: MappingProxyType[int, float]
    polls: MappingProxyType[str, tuple[int, float]]
    bad: frozenset[tuple[str, int | str]] = frozenset()
    named: MappingProxyType[str, float] = field(default_factory=lambda: MappingProxyType({}))


@dataclass(slots=True)
class _Chunk:
    """One read request covering several mapped inputs."""

    table: str  # discrete_input, coil, input_register, holding_register
    start: int
    count: int
    digital: list[DigitalInputMap] = field(default_factory=list)
    analog: list[AnalogInputMap] = field(default_factory=list)
    named: list[NamedPoint] = field(default_factory=list)


_READ = {"discrete_input": "read_discrete_inputs", "coil": "read_coils",
         "input_register": "read_input_registers", "holding_register": "read_holding_registers"}


class _LinkLost(Exception):
    pass


class _ExceptionResponse(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


def _put_all(queue: asyncio.Queue[WriteOp | None], ops: tuple[WriteOp, ...]) -> None:
    for op in ops:
        queue.put_nowait(op)


def named_write(point: NamedPoint, value: float, note: str = "") -> WriteOp:
    """The write that sets a named output point to ``value`` (engineering units; a coil: 0 or 1)."""
    values = [1 if value else 0] if point.bit else encode(value, point.conversion)
    return WriteOp(point.table, point.address, values, f"{point.key}{note}", point.device)


def coalesce(ops: list[WriteOp]) -> list[list[WriteOp]]:
    """Split writes (in order) into groups that one request can carry: consecutive writes to one
    table whose addresses follow each other (M62 P0 and M62 P1 on one setpoint: one write-coils).
    Order is kept; a second write to the same address starts a new group."""
    groups: list[list[WriteOp]] = []
    end = -1
    for op in ops:
        last = groups[-1] if groups else None
        limit = MAX_COILS_PER_WRITE if op.table == "coil" else MAX_REGS_PER_WRITE
        if (last is not None and last[0].table == op.table and op.address == end
                and end - last[0].address + len(op.values) <= limit):
            last.append(op)
        else:
            groups.append([op])
        end = op.address + len(op.values)
    return groups


def plan_reads(digital: list[DigitalInputMap], analog: list[AnalogInputMap],
               named: list[NamedPoint] | None = None) -> list[_Chunk]:
    """Group a device's inputs (and named input points) into as few read requests as the Modbus
    limits allow."""
    chunks: list[_Chunk] = []
    by_table: dict[str, list[tuple[int, int, Any]]] = {}
    for d in digital:
        table = "discrete_input" if d.source is DigitalSource.DISCRETE_INPUT else "coil"
        by_table.setdefault(table, []).append((d.address, 1, d))
    for a in analog:
        table = "input_register" if a.source is AnalogSource.INPUT_REGISTER else "holding_register"
        by_table.setdefault(table, []).append((a.register, a.conversion.type.registers, a))
    for p in named or ():
        by_table.setdefault(p.table, []).append((p.address, p.registers, p))
    for table, items in by_table.items():
        limit = MAX_BITS_PER_READ if table in ("discrete_input", "coil") else MAX_REGS_PER_READ
        items.sort(key=lambda x: x[0])
        cur: _Chunk | None = None
        for addr, n, m in items:
            if cur is None or addr > cur.start + cur.count + GAP or addr + n - cur.start > limit:
                cur = _Chunk(table, addr, n)
                chunks.append(cur)
            cur.count = max(cur.count, addr + n - cur.start)
            if isinstance(m, NamedPoint):
                cur.named.append(m)
            else:
                (cur.digital if isinstance(m, DigitalInputMap) else cur.analog).append(m)
    return chunks


class _Link:
    """One device: its client, queue and read plan (lives on the worker loop)."""

    def __init__(self, dev: ModbusDevice, chunks: list[_Chunk], safe_ops: list[WriteOp]) -> None:
        self.dev = dev
        self.chunks = chunks
        self.safe_ops = safe_ops
        self.client: Any = None  # writes (and polls when not separate)
        self.poll_client: Any = None  # polls: a second connection so writes never queue behind a read
        self.separate = dev.separate_poll_connection and not dev.serial
        self.up_event = asyncio.Event()
        self.poll_now = asyncio.Event()  # a poll is wanted now (M66), not at the next period
        self.queue: asyncio.Queue[WriteOp | None] = asyncio.Queue()  # None: wake up (stopping)
        self.up = False
        self.polls = 0
        self.inflight: set[asyncio.Task[Any]] = set()
        self.reported: set[tuple[str, int]] = set()  # exception faults already reported (polls)


class IoWorker(ConnectingMixin):
    """Runs the Modbus clients of every configured device on one thread; see the module docstring.
    Connecting and closing a device's clients: :class:`~fieldbus.modbus.connecting.ConnectingMixin`."""

    def __init__(self, config: ModbusConfig, *,
                 on_fault: Callable[[ModbusFault], None] | None = None,
                 on_recover: Callable[[str], None] | None = None,
                 on_written: Callable[[WriteOp, float], None] | None = None) -> None:
        self.config = config
        self.on_fault = on_fault
        self.on_recover = on_recover
        self.on_written = on_written
        self._links: dict[str, _Link] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._stop_event: asyncio.Event | None = None
        self._stopping = False
        self._cond = threading.Condition()
        self._digital: dict[int, bool] = {m.index: False for m in config.digital_inputs}
        self._analog: dict[int, float] = {m.index: 0.0 for m in config.analog_inputs}
        self._named: dict[str, float] = {p.key: 0.0 for p in config.named if not p.output}
        self._bad: set[tuple[str, int | str]] = set()
        self._polls: dict[str, tuple[int, float]] = {}
        self._seq = 0
        self.link_up: dict[str, bool] = {d.name: False for d in config.devices}
        self.snapshot = self._make_snapshot(0.0)
        self.counters = {"writes": 0, "polls": 0, "retries": 0, "dropped": 0}

    # --- life cycle -----------------------------------------------------------------------------

    def start(self, timeout: float | None = None) -> None:
        """Connect every device, write the safe state, start polling. Raises
        :class:`ModbusConnectError` naming each device not reachable within its connect budget
        (``(retries + 1)`` attempts of ``timeout_s``) or ``timeout``."""
        if self._thread is not None:
            return
        self._stopping = False
        started = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(started,), name="modbus-io", daemon=True)
        self._thread.start()
        started.wait(5.0)
        assert self._loop is not None
        budget = timeout if timeout is not None else self._request_budget() + 1.0
        fut = asyncio.run_coroutine_threadsafe(self._connect_all(), self._loop)
        try:
            unreachable = fut.result(budget)
        except concurrent.futures.TimeoutError:
            fut.cancel()
            unreachable = [f"Modbus device {n!r} at {lk.dev.where}: no connection within {budget:.1f} s"
                           for n, lk in self._links.items() if not lk.up]
        except ModbusConnectError as exc:
            unreachable = [str(exc)]
        if unreachable:
            self.stop(safe=False)
            raise ModbusConnectError("; ".join(unreachable))
        for link in self._links.values():
            self._tasks += asyncio.run_coroutine_threadsafe(self._spawn(link), self._loop).result(5.0)

    def stop(self, *, safe: bool = True, timeout: float = 5.0) -> None:
        """Stop polling; write the safe state first if ``safe`` and the link is up; close the clients."""
        loop, thread = self._loop, self._thread
        if thread is None or loop is None:
            return
        with contextlib.suppress(RuntimeError, concurrent.futures.TimeoutError):
            asyncio.run_coroutine_threadsafe(self._shutdown(safe), loop).result(timeout)
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout)
        self._thread = None
        self._loop = None
        self._tasks = []
        with self._cond:
            self._cond.notify_all()

    def _request_budget(self) -> float:
        """The longest one request can take on any device, all retries included."""
        return max(((d.retries + 1) * (d.timeout_s + d.retry_backoff_s * 2 ** d.retries)
                    for d in self.config.devices), default=0.0)

    @property
    def running(self) -> bool:
        return self._thread is not None and not self._stopping

    def _run(self, started: threading.Event) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)
        self._stop_event = asyncio.Event()
        for dev in self.config.devices:
            self._links[dev.name] = _Link(dev, self._plan(dev), self._safe_ops(dev))
        started.set()
        try:
            loop.run_forever()
        finally:
            with contextlib.suppress(Exception):
                loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

    def _plan(self, dev: ModbusDevice) -> list[_Chunk]:
        mine = [p for p in self.config.named if p.device == dev.name]
        chunks = plan_reads([m for m in self.config.digital_inputs if m.device == dev.name],
                            [m for m in self.config.analog_inputs if m.device == dev.name],
                            [p for p in mine if not p.output])
        if not chunks:  # outputs only: read one back as a keep-alive
            coils = [m.coil for m in self.config.digital_outputs if m.device == dev.name]
            coils += [p.address for p in mine if p.output and p.table == "coil"]
            regs = [m.register for m in self.config.analog_outputs if m.device == dev.name]
            regs += [p.address for p in mine if p.output and p.table == "holding_register"]
            if coils:
                chunks = [_Chunk("coil", min(coils), 1)]
            elif regs:
                chunks = [_Chunk("holding_register", min(regs), 1)]
        return chunks

    def _safe_ops(self, dev: ModbusDevice) -> list[WriteOp]:
        ops = [WriteOp("coil", m.coil, [int(m.safe)], f"digital output {m.index} (safe state)", dev.name)
               for m in self.config.digital_outputs if m.device == dev.name]
        ops += [WriteOp("holding_register", m.register, encode(m.safe, m.conversion),
                        f"analog output {m.index} (safe state)", dev.name)
                for m in self.config.analog_outputs if m.device == dev.name]
        ops += [named_write(p, p.safe, " (safe state)")
                for p in self.config.named if p.device == dev.name and p.output]
        return sorted(ops, key=lambda op: (op.table, op.address))  # in address order: fewer requests

    async def _spawn(self, link: _Link) -> list[asyncio.Task[None]]:
        return [asyncio.create_task(self._writer_loop(link), name=f"modbus-write:{link.dev.name}"),
                asyncio.create_task(self._poller_loop(link), name=f"modbus-poll:{link.dev.name}")]

    async def _shutdown(self, safe: bool) -> None:
        self._stopping = True
        if self._stop_event is not None:
            self._stop_event.set()
        for link in self._links.values():  # wake both loops; a request in flight is let finish
            link.queue.put_nowait(None)
            link.up_event.set()
            link.poll_now.set()
        tasks = [t for t in self._tasks if isinstance(t, asyncio.Task)]
        if tasks:
            _done, pending = await asyncio.wait(tasks, timeout=self._request_budget() + 0.5)
            for task in pending:
                task.cancel()
            for task in pending:
                with contextlib.suppress(BaseException):
                    await task
        for link in self._links.values():
            if safe and link.up:
                with contextlib.suppress(Exception):
                    for group in coalesce(link.safe_ops):
                        await self._write(link, group)
            self._close(link)
            while not link.queue.empty():
                op = link.queue.get_nowait()
                if op is not None and op.future is not None and not op.future.done():
                    op.future.set_exception(LinkDownError(f"{op.what}: the I/O worker stopped"))

    # --- the device loop ------------------------------------------------------------------------

    async def _writer_loop(self, link: _Link) -> None:
        """Serve the queued writes in order; reconnect (and restore the safe state) when down."""
        dev = link.dev
        delay = dev.retry_backoff_s
        while not self._stopping:
            if not link.up:
                try:
                    connected = await self._connect(link)
                except ModbusConnectError as exc:  # the port changed under us: keep trying, say why
                    log.warning("%s", exc)
                    connected = False
                if not connected or not await self._recover(link):
                    assert self._stop_event is not None
                    with contextlib.suppress(TimeoutError):  # back off; a stop ends the wait
                        await asyncio.wait_for(self._stop_event.wait(), delay)
                    delay = min(2 * delay, dev.reconnect_max_s)
                else:
                    delay = dev.retry_backoff_s
                continue
            batch = [await link.queue.get()]
            while not link.queue.empty():
                batch.append(link.queue.get_nowait())
            groups = coalesce([op for op in batch if op is not None])
            for i, group in enumerate(groups):
                try:
                    await self._serve(link, group)
                except _LinkLost as exc:
                    for rest in groups[i + 1:]:
                        self._fail_ops(rest, f"not written, link lost: {exc}")
                    self._lose(link, str(exc))
                    break

    async def _poller_loop(self, link: _Link) -> None:
        """Poll the inputs every ``poll_ms`` while the link is up (back to back with 0), and at once
        when :meth:`poll_now` asks (an M66 wants a fresh value), without shifting the schedule."""
        period = link.dev.poll_ms / 1000.0
        next_poll = time.monotonic()
        while not self._stopping:
            if not link.up:
                await link.up_event.wait()
                next_poll = time.monotonic()
                continue
            wait = next_poll - time.monotonic()
            if not link.chunks:  # nothing mapped on this device: nothing to poll
                wait = max(wait, 0.1)
            on_demand = link.poll_now.is_set()
            if wait > 0 and not on_demand:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(link.poll_now.wait(), wait)
                continue  # look again: stopping, link down, asked for, or due
            link.poll_now.clear()
            if not link.chunks:
                continue
            try:
                await self._poll(link)
            except _LinkLost as exc:
                self._lose(link, str(exc))
                continue
            if wait <= 0:  # a scheduled poll (an extra one leaves the schedule alone)
                now = time.monotonic()
                next_poll = max(next_poll + period, now) if period > 0 else now

    async def _recover(self, link: _Link) -> bool:
        """After a reconnect: drop stale writes, write the safe state, then report recovery."""
        dropped = 0
        while not link.queue.empty():
            op = link.queue.get_nowait()
            if op is None:
                continue
            dropped += 1
            if op.future is not None and not op.future.done():
                op.future.set_exception(LinkDownError(f"{op.what}: dropped, the link was down"))
        self.counters["dropped"] += dropped
        try:
            for group in coalesce(link.safe_ops):
                await self._write(link, group)
        except (_LinkLost, _ExceptionResponse) as exc:
            self._close(link)
            log.warning("%s: safe state not written after reconnect: %s", link.dev.where, exc)
            return False
        link.reported.clear()  # exception faults are reported afresh after a recovery
        self._set_up(link, True)
        log.warning("Modbus device %r at %s: link restored, outputs in their safe state",
                    link.dev.name, link.dev.where)
        if self.on_recover is not None:
            self.on_recover(link.dev.name)
        return True

    def _lose(self, link: _Link, why: str) -> None:
        """Either loop found the link gone: close it, wake the writer to reconnect, report once."""
        self._close(link)
        for task in list(link.inflight):
            task.cancel()
        link.queue.put_nowait(None)
        was_up = link.up
        self._set_up(link, False)
        if was_up:
            self._fault(FaultKind.LINK_LOST, link, f"link lost: {why}")

    def _fault(self, kind: FaultKind, link: _Link, message: str, table: str | None = None,
               address: int | None = None) -> None:
        fault = ModbusFault(kind, link.dev.name, link.dev.where, message, table, address)
        log.error("%s", fault)
        if self.on_fault is not None:
            try:
                self.on_fault(fault)
            except Exception:
                log.exception("on_fault callback failed")

    @staticmethod
    def _fail_ops(ops: list[WriteOp], why: str) -> None:
        for op in ops:
            if op.future is not None and not op.future.done():
                op.future.set_exception(LinkDownError(f"{op.what}: {why}"))

    async def _serve(self, link: _Link, ops: list[WriteOp]) -> None:
        """Write a group from :func:`coalesce` (one request); exception responses become faults."""
        if self._stopping:
            self._fail_ops(ops, "the I/O worker stopped")
            return
        try:
            t = await self._write(link, ops)
        except _ExceptionResponse as exc:
            first = ops[0]
            whats = ", ".join(o.what for o in ops)
            where = f"{first.table.replace('_', ' ')} {first.address}"
            msg = f"write {where} ({whats}): {exception_name(exc.code)}"
            self._fault(FaultKind.EXCEPTION, link, msg, first.table, first.address)
            self._fail_ops(ops, str(ModbusFault(FaultKind.EXCEPTION, link.dev.name, link.dev.where, msg)))
            return
        except _LinkLost as exc:
            self._fail_ops(ops, f"not written, link lost: {exc}")
            raise
        for op in ops:
            if op.future is not None and not op.future.done():
                op.future.set_result(t)

    async def _write(self, link: _Link, ops: list[WriteOp]) -> float:
        """One request for a group of contiguous writes to one table (usually a group of one)."""
        unit = link.dev.unit
        first = ops[0]
        what = f"write {first.table.replace('_', ' ')} {first.address}"
        addr = first.address
        vals = [v for op in ops for v in op.values]
        if first.table == "coil":
            if len(vals) == 1:
                await self._request(link, what, lambda c: c.write_coil(addr, bool(vals[0]), device_id=unit))
            else:
                bits = [bool(v) for v in vals]
                await self._request(link, what, lambda c: c.write_coils(addr, bits, device_id=unit))
        elif len(vals) == 1:
            await self._request(link, what, lambda c: c.write_register(addr, vals[0], device_id=unit))
        else:  # a float32 pair in one request, so the device never holds half of it
            await self._request(link, what, lambda c: c.write_registers(addr, vals, device_id=unit))
        t = time.monotonic()
        self.counters["writes"] += 1
        if self.on_written is not None:
            for op in ops:
                self.on_written(op, t)
        return t

    async def _request(self, link: _Link, what: str, call: Callable[[Any], Any], poll: bool = False) -> Any:
        """One request with bounded retries on timeout; raises _LinkLost or _ExceptionResponse."""
        from pymodbus.exceptions import ConnectionException, ModbusIOException

        dev = link.dev
        backoff = dev.retry_backoff_s
        for attempt in range(dev.retries + 1):
            client = link.poll_client if poll else link.client
            if client is None or not client.connected:
                raise _LinkLost(f"connection closed ({what})")
            task = asyncio.ensure_future(call(client))
            link.inflight.add(task)
            try:
                rr = await task
            except asyncio.CancelledError:
                if self._stopping:
                    raise
                raise _LinkLost(f"connection closed ({what})") from None
            except ConnectionException as exc:
                raise _LinkLost(f"{what}: {exc}") from None
            except ModbusIOException as exc:
                log.debug("%s %s: try %d: %s", dev.where, what, attempt + 1, exc)
                if attempt < dev.retries:
                    self.counters["retries"] += 1
                    await asyncio.sleep(backoff)
                    backoff *= 2
                continue
            finally:
                link.inflight.discard(task)
            if rr.isError():
                raise _ExceptionResponse(getattr(rr, "exception_code", 0))
            return rr
        raise _LinkLost(f"no answer to {what} after {dev.retries + 1} tries of {dev.timeout_s} s")

    async def _poll(self, link: _Link) -> None:
        unit = link.dev.unit
        t_start = time.monotonic()
        digital: dict[int, bool] = {}
        analog: dict[int, float] = {}
        named: dict[str, float] = {}
        good: set[tuple[str, int | str]] = set()
        bad: set[tuple[str, int | str]] = set()
        for ch in link.chunks:
            keys: set[tuple[str, int | str]] = {("digital", m.index) for m in ch.digital}
            keys |= {("analog", m.index) for m in ch.analog} | {("named", p.key) for p in ch.named}
            what = f"read {ch.table.replace('_', ' ')} {ch.start}"
            method = _READ[ch.table]
            try:
                rr = await self._request(
                    link, what, lambda c, ch=ch, m=method: getattr(c, m)(ch.start, count=ch.count,
                                                                         device_id=unit), poll=True)
            except _ExceptionResponse as exc:
                bad |= keys
                key = (ch.table, ch.start)
                if key not in link.reported:
                    link.reported.add(key)
                    self._fault(FaultKind.EXCEPTION, link,
                                f"{what} (count {ch.count}): {exception_name(exc.code)}", ch.table, ch.start)
                continue
            link.reported.discard((ch.table, ch.start))
            good |= keys
            for m in ch.digital:
                digital[m.index] = bool(rr.bits[m.address - ch.start])
            for m in ch.analog:
                off = m.register - ch.start
                analog[m.index] = decode(rr.registers[off:off + m.conversion.type.registers], m.conversion)
            for p in ch.named:
                off = p.address - ch.start
                named[p.key] = (float(bool(rr.bits[off])) if p.bit
                                else decode(rr.registers[off:off + p.registers], p.conversion))
        link.polls += 1
        self.counters["polls"] += 1
        with self._cond:
            self._digital.update(digital)
            self._analog.update(analog)
            self._named.update(named)
            self._bad.difference_update(good)
            self._bad.update(bad)
            self._polls[link.dev.name] = (link.polls, t_start)
            self._seq += 1
            self.snapshot = self._make_snapshot(time.monotonic())
            self._cond.notify_all()

    def _make_snapshot(self, t: float) -> InputSnapshot:
        return InputSnapshot(self._seq, t, MappingProxyType(dict(self._digital)),
                             MappingProxyType(dict(self._analog)), MappingProxyType(dict(self._polls)),
                             frozenset(self._bad), MappingProxyType(dict(self._named)))

    # --- for other threads ----------------------------------------------------------------------

    def post(self, device: str, *ops: WriteOp) -> None:
        """Queue writes for ``device``'s writer, in order, as one hand-over (writes posted together
        to contiguous addresses of one table go out as one request); never blocks. Raises
        :class:`LinkDownError` at once if the link is down (they would be dropped on recovery anyway)."""
        loop = self._loop
        link = self._links.get(device)
        if loop is None or link is None or self._stopping:
            raise LinkDownError(f"{', '.join(op.what for op in ops)}: the Modbus I/O worker is not running")
        if not link.up:
            self.counters["dropped"] += len(ops)
            raise LinkDownError(f"{', '.join(op.what for op in ops)}: not written, the link to Modbus device "
                                f"{device!r} at {link.dev.where} is down")
        for op in ops:
            op.device = device
        loop.call_soon_threadsafe(_put_all, link.queue, ops)

    def poll_now(self, device: str) -> None:
        """Ask for a poll of ``device`` now rather than at its next period; never blocks."""
        loop, link = self._loop, self._links.get(device)
        if loop is not None and link is not None and not self._stopping:
            with contextlib.suppress(RuntimeError):  # loop closing
                loop.call_soon_threadsafe(link.poll_now.set)

    def wait_poll(self, predicate: Callable[[InputSnapshot], bool], timeout: float,
                  cancel: threading.Event | None = None) -> InputSnapshot | None:
        """Block until ``predicate(snapshot)`` holds (checked now and after every poll and link change)
        or ``timeout`` s pass (None then). ``cancel`` set, or the worker stopping, ends it early."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                snap = self.snapshot
                if predicate(snap):
                    return snap
                if cancel is not None and cancel.is_set():
                    return None
                left = deadline - time.monotonic()
                if left <= 0 or self._thread is None:
                    return None
                self._cond.wait(min(left, 0.05) if cancel is not None else left)

    def notify(self) -> None:
        """Wake every :meth:`wait_poll` (after a cancel)."""
        with self._cond:
            self._cond.notify_all()
