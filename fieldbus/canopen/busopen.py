"""Opening a python-can bus from its configuration, with a receive buffer that survives a stall.

python-can's ``udp_multicast`` leaves its socket at the kernel's default receive buffer
(``net.core.rmem_default``, 208 KiB on most systems). Each CAN frame is one datagram, and the kernel
charges a datagram's whole buffer (about 1 KiB), not its 80 bytes: at 2 ms with three drives (about
5,000 frames a second on the group) the default holds some 50 ms of traffic. A process that is not
scheduled for longer (a loaded PC) loses frames; a simulated drive that loses its SYNCs then sees the
next target several periods ahead and faults with EMCY 0x8400, as a real drive would on such a jump.
So the socket's buffer is widened to :data:`UDP_RECEIVE_BUFFER` (over ``net.core.rmem_max`` where the
process may, as root can; otherwise up to it, and a warning says so when that is below
:data:`UDP_RECEIVE_BUFFER_LOW`). A SocketCAN raw socket is charged the same way (each frame a whole
socket buffer) and gets the same: in the emulated VM a drive process that read late lost 7 of 174
SYNCs and up to 38 targets in 1.5 s at the default buffer, on vcan0 as it would on can0.
canon's local bus (``canon_local``, :mod:`fieldbus.canopen.localbus`) sizes its own buffers; it is
opened here directly, so that it works where python-can's entry points were not installed (a
checkout whose ``pip install -e .`` predates it).
"""

from __future__ import annotations

import logging
import socket
from typing import Any

import can

from fieldbus.canopen.config import LOCAL_INTERFACE, CanBusConfig

log = logging.getLogger(__name__)

#: the receive buffer asked for on a udp_multicast socket: seconds of traffic, not milliseconds
UDP_RECEIVE_BUFFER = 8 * 1024 * 1024
#: below this (the kernel's cap without privileges) a warning names the sysctl to raise
UDP_RECEIVE_BUFFER_LOW = 2 * 1024 * 1024
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)


def open_bus(config: CanBusConfig, **extra: Any) -> can.BusABC:
    """``can.Bus`` for ``config`` (``extra`` keyword arguments added), its receive buffer widened
    where it is a UDP socket."""
    if config.interface == LOCAL_INTERFACE:  # also where python-can's entry points are not installed
        from fieldbus.canopen.localbus import LocalBus

        kw = {k: v for k, v in config.bus_kwargs().items() if k != "interface"}
        return LocalBus(**kw, **extra)
    bus = can.Bus(**config.bus_kwargs(), **extra)
    if config.interface in ("udp_multicast", "socketcan"):
        widen_receive_buffer(bus)
    return bus


def widen_receive_buffer(bus: can.BusABC, size: int = UDP_RECEIVE_BUFFER) -> int:
    """Widen the receive buffer of a python-can UDP or SocketCAN bus's socket; the size the kernel
    granted (0: not a socket this knows)."""
    sock = getattr(getattr(bus, "_multicast", None), "_socket", None) or getattr(bus, "socket", None)
    if not isinstance(sock, socket.socket):
        return 0
    try:
        sock.setsockopt(socket.SOL_SOCKET, _SO_RCVBUFFORCE, size)  # beyond rmem_max: needs CAP_NET_ADMIN
    except OSError:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)  # capped at net.core.rmem_max
    granted = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)  # the kernel reports twice the size
    if granted < UDP_RECEIVE_BUFFER_LOW:
        log.warning("%s receive buffer only %d KiB (net.core.rmem_max): frames are lost when "
                    "this process stalls for %d ms or so; raise it: sysctl -w net.core.rmem_max=%d",
                    type(bus).__name__, granted // 1024, max(1, granted // 4000), size)
    return granted
