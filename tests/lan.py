"""Two network namespaces joined by a veth pair: a private stand-in for a LAN segment.

``lan-a`` holds the machine PC, ``lan-b`` another host; each has the multicast route on its side of
the pair, as a machine PC's route points at its network card. Made and removed by the test that
uses it (unique names, so runs never collide); traffic only between the two, nothing leaves.
"""

from __future__ import annotations

import os
import secrets
import shutil
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager


def lan_skip_reason() -> str | None:
    """Why a LAN of namespaces cannot be made here, or None."""
    if os.geteuid() != 0:
        return "needs root to make two network namespaces joined by a veth pair (run tests/run as root)"
    if shutil.which("ip") is None:
        return "needs iproute2's ip to make network namespaces"
    return None


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=20)


@contextmanager
def lan() -> Iterator[tuple[str, str]]:
    """Yield the names of the two namespaces (machine side, other host), removed afterwards."""
    tag = secrets.token_hex(3)
    a, b = f"canon-lana-{tag}", f"canon-lanb-{tag}"
    va, vb = f"cva{tag}", f"cvb{tag}"  # interface names: at most 15 characters
    made: list[str] = []
    try:
        for ns in (a, b):
            _ip("netns", "add", ns)
            made.append(ns)
        _ip("link", "add", va, "type", "veth", "peer", "name", vb)
        _ip("link", "set", va, "netns", a)
        _ip("link", "set", vb, "netns", b)
        for ns, dev, addr in ((a, va, "169.254.77.1/24"), (b, vb, "169.254.77.2/24")):
            _ip("-n", ns, "addr", "add", addr, "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
            _ip("-n", ns, "route", "add", "224.0.0.0/4", "dev", dev)
        yield a, b
    finally:
        for ns in made:  # the veth pair goes with its namespaces
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=20)


def in_netns(ns: str, argv: list[str]) -> list[str]:
    return ["ip", "netns", "exec", ns, *argv]
