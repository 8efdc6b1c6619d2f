"""LCM URLs: parse them as LCM does, and tell whether traffic on one can leave this host.

LCM's URL is ``PROVIDER://NETWORK?KEY=VALUE&...`` with providers ``udpm`` (UDP multicast),
``mpudpm`` (multi-port UDP multicast), ``tcpq`` (through a TCP hub), ``memq`` (inside one process) and
``file`` (a log file). An empty URL means ``$LCM_DEFAULT_URL``, else LCM's default, which is ours.

Whether what the daemon *sends* leaves the host: for ``udpm``/``mpudpm`` a multicast TTL above 0 lets
packets through routers (LCM's TTL defaults to 0); ``tcpq`` always counts as leaving (the hub may
accept other hosts, which we cannot see from here); ``memq`` and ``file`` never do. It says nothing
about what the daemon *accepts*: a TTL does not stop other hosts' packets from arriving, which is why
every command is signed whatever the URL (:mod:`telemetry.auth`).
"""

from __future__ import annotations

import ipaddress
import os
from dataclasses import dataclass, field

DEFAULT_URL = "udpm://239.255.76.67:7667?ttl=0"
DEFAULT_GROUP = "239.255.76.67:7667"
PROVIDERS = ("udpm", "mpudpm", "tcpq", "memq", "file")
_MULTICAST_PROVIDERS = ("udpm", "mpudpm")


@dataclass(frozen=True)
class LcmUrl:
    """A parsed LCM URL. ``url`` is the text LCM is given (the default filled in)."""

    url: str
    provider: str
    network: str
    options: dict[str, str] = field(default_factory=dict)
    group: str = ""     # udpm/mpudpm: multicast address
    port: int = 0       # udpm/mpudpm: UDP port
    ttl: int = 0        # udpm/mpudpm: multicast TTL (0: never leaves this host)

    @property
    def leaves_host(self) -> bool:
        if self.provider in _MULTICAST_PROVIDERS:
            return self.ttl > 0
        return self.provider not in ("memq", "file")


def parse_url(url: str | None) -> LcmUrl:
    """Parse ``url`` as LCM would; ``ValueError`` says what is wrong (the caller names the key)."""
    text = (url or "").strip() or os.environ.get("LCM_DEFAULT_URL", "").strip() or DEFAULT_URL
    provider, sep, rest = text.partition("://")
    if not sep or not provider:
        raise ValueError(f"not an LCM URL: {text!r} (expected PROVIDER://NETWORK?OPTIONS, "
                         f"e.g. {DEFAULT_URL})")
    if provider not in PROVIDERS:
        raise ValueError(f"unknown LCM provider {provider!r} in {text!r} (known: {', '.join(PROVIDERS)})")
    network, _, query = rest.partition("?")
    options: dict[str, str] = {}
    for part in query.replace("?", "&").split("&"):
        if part:
            key, _, value = part.partition("=")
            options[key] = value
    if provider not in _MULTICAST_PROVIDERS:
        return LcmUrl(text, provider, network, options)

    group, _, port_text = (network or DEFAULT_GROUP).partition(":")
    try:
        address = ipaddress.IPv4Address(group)
    except ValueError:
        raise ValueError(f"{text!r}: {group!r} is not an IPv4 address") from None
    if not address.is_multicast:
        raise ValueError(f"{text!r}: {group} is not a multicast address (224.0.0.0 to 239.255.255.255)")
    port = 0
    if port_text:
        if not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
            raise ValueError(f"{text!r}: port must be a number from 0 to 65535, got {port_text!r}")
        port = int(port_text)
    ttl_text = options.get("ttl", "0")
    if not ttl_text.isdigit() or int(ttl_text) > 255:
        raise ValueError(f"{text!r}: ttl must be a number from 0 to 255 (0 keeps traffic on this host), "
                         f"got {ttl_text!r}")
    return LcmUrl(text, provider, network, options, group, port, int(ttl_text))


def url_leaves_host(url: str | None) -> bool:
    """True when traffic on ``url`` can reach other hosts (see the module docstring)."""
    return parse_url(url).leaves_host


def check_url(url: str) -> str | None:
    """A complaint about ``url``, or None: fits ``motiond.configkit.Table.get(check=...)``."""
    try:
        parse_url(url)
    except ValueError as exc:
        return str(exc)
    return None


COMMAND_RECEIVE_BUFFER = 4 * 1024 * 1024
"""Receive buffer the daemon asks for on ``udpm``: a burst of commands (1,000 per second from a
misbehaving client) must wait in the kernel while the interpreter lock is busy, not be dropped. The
kernel grants at most ``net.core.rmem_max`` (often 208 kB: raise it to 4 MB on a machine PC)."""


def with_receive_buffer(url: str, size: int = COMMAND_RECEIVE_BUFFER,
                        rmem_max_file: str = "/proc/sys/net/core/rmem_max") -> str:
    """``url`` with ``recv_buf_size`` (``udpm`` without one): ``size``, capped at what the kernel grants
    so that LCM does not warn about getting less; other URLs unchanged."""
    parsed = parse_url(url)
    if parsed.provider != "udpm" or "recv_buf_size" in parsed.options:
        return parsed.url
    try:
        with open(rmem_max_file) as fh:
            size = min(size, int(fh.read().strip()))
    except (OSError, ValueError):
        pass
    sep = "&" if "?" in parsed.url else "?"
    return f"{parsed.url}{sep}recv_buf_size={size}"
