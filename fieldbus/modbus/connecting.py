"""Connecting a Modbus device's clients, for :class:`~fieldbus.modbus.io_worker.IoWorker`: the first
connect at start (bounded attempts, the wait between them doubling, the safe state written before the
link counts as up; when none succeeds, why: refused, no answer, a serial port that does not open), the
pymodbus client for a device (TCP or RTU, its own retries and reconnection off, requests in flight
ended when the peer closes), the write and poll connections opened all or nothing, closed, and the
link marked up or down for the threads that wait on it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from typing import TYPE_CHECKING, Any

from fieldbus.modbus.config import ModbusDevice
from fieldbus.modbus.faults import ModbusConnectError, exception_name

if TYPE_CHECKING:
    from fieldbus.modbus.io_worker import WriteOp, _Link

log = logging.getLogger(__name__)


class ConnectingMixin:
    """Part of :class:`~fieldbus.modbus.io_worker.IoWorker`: its links (``_links``), the ``link_up``
    it reports and the condition other threads wait on (``_cond``); writing goes through its
    ``_write``."""

    _links: dict[str, _Link]
    link_up: dict[str, bool]
    _cond: threading.Condition

    async def _write(self, link: _Link, ops: list[WriteOp]) -> float:
        raise NotImplementedError  # IoWorker's

    async def _connect_all(self) -> list[str]:
        results = await asyncio.gather(*(self._first_connect(lk) for lk in self._links.values()))
        return [r for r in results if r]

    async def _first_connect(self, link: _Link) -> str:
        """Connect at start with bounded attempts; '' or the message naming device, host and port."""
        from fieldbus.modbus.io_worker import _ExceptionResponse, _LinkLost, coalesce  # (imports this)

        dev = link.dev
        delay = dev.retry_backoff_s
        for _attempt in range(dev.retries + 1):
            if await self._connect(link):
                try:
                    for group in coalesce(link.safe_ops):
                        await self._write(link, group)
                except _LinkLost as exc:
                    self._close(link)
                    return f"Modbus device {dev.name!r} at {dev.where}: {exc}"
                except _ExceptionResponse as exc:
                    self._close(link)
                    return (f"Modbus device {dev.name!r} at {dev.where}: writing the safe state: "
                            f"{exception_name(exc.code)}")
                self._set_up(link, True)
                return ""
            await asyncio.sleep(delay)
            delay = min(2 * delay, dev.reconnect_max_s)
        reason = await self._why_unreachable(dev)
        return f"cannot connect to Modbus device {dev.name!r} at {dev.where}: {reason}"

    async def _why_unreachable(self, dev: ModbusDevice) -> str:
        if dev.serial:
            from fieldbus.modbus.serialport import serial_port_problem

            problem = await asyncio.to_thread(serial_port_problem, dev.serial, dev.baudrate, dev.parity,
                                              dev.stopbits, dev.bytesize)
            return problem or f"the serial port opens but no answer came within {dev.timeout_s} s"
        try:
            _r, w = await asyncio.wait_for(asyncio.open_connection(dev.host, dev.port), dev.timeout_s)
        except TimeoutError:
            return f"no answer within {dev.timeout_s} s"
        except ConnectionRefusedError:
            return "connection refused (nothing listening on that port?)"
        except OSError as exc:
            return exc.strerror or str(exc)
        w.close()
        return "the connection was accepted but the Modbus client could not start"

    def _make_client(self, link: _Link) -> Any:
        dev = link.dev

        def trace_connect(connected: bool) -> None:
            if not connected:  # the peer closed: end the requests in flight now, not at their timeout
                for task in list(link.inflight):
                    task.cancel()

        if dev.serial:
            from pymodbus.client import AsyncModbusSerialClient
            from pymodbus.framer import FramerType

            return AsyncModbusSerialClient(
                dev.serial, framer=FramerType.RTU, baudrate=dev.baudrate, bytesize=dev.bytesize,
                parity=dev.parity, stopbits=dev.stopbits, timeout=dev.timeout_s, retries=0,
                reconnect_delay=0, trace_connect=trace_connect, name=dev.name)
        from pymodbus.client import AsyncModbusTcpClient

        return AsyncModbusTcpClient(dev.host, port=dev.port, timeout=dev.timeout_s, retries=0,
                                    reconnect_delay=0, trace_connect=trace_connect, name=dev.name)

    async def _connect(self, link: _Link) -> bool:
        """Open the write connection (and the poll connection, if separate); all or nothing."""
        self._close(link)
        try:
            clients = [self._make_client(link) for _ in range(2 if link.separate else 1)]
        except (ImportError, RuntimeError) as exc:  # RTU without pyserial
            raise ModbusConnectError(f"Modbus device {link.dev.name!r} at {link.dev.where}: "
                                     f"cannot make a client: {exc}") from None
        link.client = clients[0]
        link.poll_client = clients[-1]
        for client in clients:
            try:
                ok = bool(await client.connect())
            except (TimeoutError, OSError) as exc:
                log.debug("connect %s: %s", link.dev.where, exc)
                ok = False
            except Exception as exc:  # RTU: no pyserial (RuntimeError), settings the port refuses
                self._close(link)   # (termios.error, ValueError): no retry will help
                raise ModbusConnectError(f"cannot connect to Modbus device {link.dev.name!r} at "
                                         f"{link.dev.where}: cannot open the serial port: "
                                         f"{self._serial_problem(link.dev, exc)}") from None
            if not ok:
                self._close(link)
                return False
        return True

    @staticmethod
    def _serial_problem(dev: ModbusDevice, exc: BaseException) -> str:
        from fieldbus.modbus.serialport import serial_port_problem

        if isinstance(exc, RuntimeError):
            return "Modbus RTU needs pyserial (pip install pyserial)"
        problem = serial_port_problem(dev.serial, dev.baudrate, dev.parity, dev.stopbits, dev.bytesize)
        return problem or str(exc)

    def _close(self, link: _Link) -> None:
        for client in {id(c): c for c in (link.client, link.poll_client) if c is not None}.values():
            with contextlib.suppress(Exception):
                client.close()
        link.client = link.poll_client = None

    def _set_up(self, link: _Link, up: bool) -> None:
        link.up = up
        self.link_up[link.dev.name] = up
        if up:
            link.up_event.set()
        else:
            link.up_event.clear()
        with self._cond:
            self._cond.notify_all()
