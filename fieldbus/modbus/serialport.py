"""Serial ports for Modbus RTU: what is wrong with one (for messages), and a cable made of ptys.

:func:`serial_port_problem` turns "the port could not be opened" into the reason (no such device,
permission denied, in use), so that a configuration naming a missing adapter gets a one-line error
naming the port rather than a pyserial traceback.

:class:`PtyLink` is a null-modem cable without hardware: two pseudo-terminal pairs whose master sides
a relay thread joins, so that whatever is written to one end's port (``a``) is read on the other's
(``b``) and back. The simulated module serves Modbus RTU on one end and the client opens the other;
:meth:`PtyLink.cut` pulls the cable out (the relay keeps reading both sides and throws the bytes
away, as a dead line loses them) and :meth:`PtyLink.restore` puts it back. Linux and other POSIX
systems only; nothing leaves this machine.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import select
import threading
import tty

log = logging.getLogger(__name__)


def serial_port_problem(port: str, baudrate: int = 19200, parity: str = "N", stopbits: int = 1,
                        bytesize: int = 8) -> str | None:
    """Why ``port`` cannot be opened as a serial port with these line settings, in a few words; None
    if it can.

    Opens the port briefly with pyserial (as the client and server will) when it exists. URLs that
    pyserial understands (``socket://``, ``rfc2217://``, ``loop://``) are left to pyserial."""
    if "://" in port:
        return None
    if not os.path.exists(port):
        return "no such serial port (is the adapter plugged in, is the name right?)"
    try:
        import serial
    except ImportError:
        return "Modbus RTU needs pyserial (pip install pyserial)"
    import termios

    try:
        with serial.Serial(port, exclusive=True, baudrate=baudrate, parity=parity, stopbits=stopbits,
                           bytesize=bytesize) as ser:
            ser.timeout = 0  # as pymodbus sets it: reconfigures the port once more
    except (termios.error, ValueError) as exc:  # the driver (or pyserial) refuses the settings
        why = exc.args[-1] if exc.args else exc
        return (f"the port does not take {baudrate} baud {bytesize}{parity}{stopbits}: {why}"
                + (" (pseudo-terminals here refuse parity: use parity N)"
                   if parity != "N" and "/pts/" in port else ""))
    except serial.SerialException as exc:
        cause = exc.__cause__ if isinstance(exc.__cause__, OSError) else None
        code = exc.errno if isinstance(exc.errno, int) else (cause.errno if cause else None)
        if code in (errno.EACCES, errno.EPERM):
            return "permission denied (is the user in the dialout group?)"
        if code in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EBUSY) or "exclusively lock" in str(exc):
            return "the port is in use by another program"
        return str(exc) or "cannot be opened"
    return None


class PtyLink:
    """Two pseudo-terminals joined like a null-modem cable (module docstring).

    ``a`` and ``b`` are the two ports' paths (``/dev/pts/N``); :meth:`start` must have been called.
    The relay holds both slave sides open, so a program closing and reopening its end (a client
    reconnecting) does not hang the line up."""

    def __init__(self) -> None:
        self._fds: list[int] = []  # master a, slave a, master b, slave b
        self._thread: threading.Thread | None = None
        self._wake_r = self._wake_w = -1
        self._connected = threading.Event()
        self._running = False
        self.a = ""
        self.b = ""
        self.relayed = 0
        """Bytes passed from one end to the other."""
        self.dropped = 0
        """Bytes thrown away while the cable was cut."""

    def start(self) -> PtyLink:
        if self._thread is not None:
            return self
        ma, sa = os.openpty()
        mb, sb = os.openpty()
        self._fds = [ma, sa, mb, sb]
        for fd in (sa, sb):  # raw, no echo, until the program on that end sets its own attributes
            tty.setraw(fd)
        for fd in (ma, mb):
            os.set_blocking(fd, False)
        self.a, self.b = os.ttyname(sa), os.ttyname(sb)
        self._wake_r, self._wake_w = os.pipe()
        self._connected.set()
        self._running = True
        self._thread = threading.Thread(target=self._relay, name="pty-link", daemon=True)
        self._thread.start()
        return self

    def cut(self) -> None:
        """Pull the cable: from now on bytes sent by either end are lost."""
        self._connected.clear()

    def restore(self) -> None:
        """Put the cable back."""
        self._connected.set()

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    def stop(self, timeout: float = 5.0) -> None:
        """End the relay and close both pseudo-terminals."""
        thread = self._thread
        if thread is None:
            return
        self._running = False
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")
        thread.join(timeout)
        self._thread = None
        for fd in (*self._fds, self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._fds = []

    def __enter__(self) -> PtyLink:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _relay(self) -> None:
        ma, _sa, mb, _sb = self._fds
        peer = {ma: mb, mb: ma}
        pending = {ma: b"", mb: b""}  # bytes read from a master, not yet written to the other
        while self._running:
            want_write = [peer[fd] for fd, data in pending.items() if data]
            try:
                readable, writable, _ = select.select([ma, mb, self._wake_r], want_write, [], 0.5)
            except (OSError, ValueError):
                return
            if self._wake_r in readable:
                return
            for fd in (ma, mb):
                if fd in readable:
                    try:
                        data = os.read(fd, 4096)
                    except BlockingIOError:
                        continue
                    except OSError as exc:  # EIO: no slave open (cannot happen: we hold both)
                        log.debug("pty link: read: %s", exc)
                        continue
                    if self._connected.is_set():
                        pending[fd] += data
                    else:
                        self.dropped += len(data)
            for src, dst in ((ma, mb), (mb, ma)):
                if pending[src] and (dst in writable or not want_write):
                    if not self._connected.is_set():
                        self.dropped += len(pending[src])
                        pending[src] = b""
                        continue
                    try:
                        n = os.write(dst, pending[src])
                    except BlockingIOError:
                        continue
                    except OSError as exc:
                        log.debug("pty link: write: %s", exc)
                        pending[src] = b""
                        continue
                    self.relayed += n
                    pending[src] = pending[src][n:]
