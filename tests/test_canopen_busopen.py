"""The udp_multicast bus's receive buffer (fieldbus/canopen/busopen.py): python-can leaves it at the
kernel's default, about 50 ms of a 3-drive bus at 2 ms; a stalled process then loses SYNCs."""

from __future__ import annotations

import os
import socket

import can
import pytest
from canopen_helpers import unique_channel

from fieldbus.canopen.busopen import UDP_RECEIVE_BUFFER_LOW, open_bus, widen_receive_buffer
from fieldbus.canopen.config import CanBusConfig


def _rcvbuf(bus: can.BusABC) -> int:
    return bus._multicast._socket.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)  # type: ignore[attr-defined]


@pytest.mark.multicast
def test_open_bus_widens_the_udp_receive_buffer_beyond_python_cans_default() -> None:
    config = CanBusConfig("udp_multicast", f"239.74.165.{1 + os.getpid() % 250}")
    plain = can.Bus(**config.bus_kwargs())
    widened = open_bus(config)
    try:
        assert _rcvbuf(widened) > _rcvbuf(plain)
        assert _rcvbuf(widened) >= UDP_RECEIVE_BUFFER_LOW  # tests/run runs as root: past rmem_max too
    finally:
        plain.shutdown()
        widened.shutdown()


def test_a_bus_without_a_udp_socket_is_left_alone() -> None:
    bus = can.Bus(interface="virtual", channel=unique_channel())
    try:
        assert widen_receive_buffer(bus) == 0
    finally:
        bus.shutdown()
