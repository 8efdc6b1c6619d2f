"""The ``[telemetry]`` table of the machine file, as this layer's own dataclass.

``motiond.config`` reads the TOML keys into it (with ``motiond.configkit``); the checks are here so
that every reader agrees on them, written as complaint functions that fit ``Table.get(check=...)``:

    url = "udpm://239.255.76.67:7667?ttl=0"   # any LCM URL; ttl=0 keeps traffic on this host
    status_hz = 50                           # status publish rate, > 0 and <= 1000
    key_file = ""                            # the command key (telemetry.auth); "": <state dir>/command.key
    event_queue = 1000                       # events waiting to be published before drops
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from telemetry.publisher import DEFAULT_EVENT_QUEUE, DEFAULT_STATUS_HZ, MAX_STATUS_HZ
from telemetry.url import DEFAULT_URL, check_url, parse_url

__all__ = ["TelemetryConfig", "check_event_queue", "check_status_hz", "check_url"]


def check_status_hz(v: float) -> str | None:
    return None if 0 < v <= MAX_STATUS_HZ else f"must be > 0 and <= {MAX_STATUS_HZ:g}"


def check_event_queue(v: int) -> str | None:
    return None if 1 <= v <= 1_000_000 else "must be between 1 and 1000000"


@dataclass(frozen=True)
class TelemetryConfig:
    url: str = DEFAULT_URL
    status_hz: float = DEFAULT_STATUS_HZ
    key_file: str = ""
    event_queue: int = DEFAULT_EVENT_QUEUE

    def __post_init__(self) -> None:
        for key, complaint in (("url", check_url(self.url)), ("status_hz", check_status_hz(self.status_hz)),
                               ("event_queue", check_event_queue(self.event_queue))):
            if complaint:
                raise ValueError(f"telemetry.{key}: {complaint}, got {getattr(self, key)!r}")

    @classmethod
    def from_table(cls, table: Any) -> TelemetryConfig:
        """Read the ``[telemetry]`` table from a ``motiond.configkit.Table`` (any object with its
        ``get(name, kind, default, check=)`` and ``check_unknown()``; this layer does not import
        motiond). Errors are the table's, naming the file and the key."""
        config = cls(
            url=table.get("url", str, DEFAULT_URL, check=check_url),
            status_hz=table.get("status_hz", float, DEFAULT_STATUS_HZ, check=check_status_hz),
            key_file=_key_file(table),
            event_queue=table.get("event_queue", int, DEFAULT_EVENT_QUEUE, check=check_event_queue),
        )
        table.check_unknown()
        return config

    @property
    def leaves_host(self) -> bool:
        """Traffic on ``url`` can reach other hosts (commands are signed whatever the URL)."""
        return parse_url(self.url).leaves_host


def _key_file(table: Any) -> str:
    """``key_file``, relative to the machine file's directory; the old ``token`` refused with the way
    that replaced it (a token in the machine file travelled in clear text in every command)."""
    if "token" in table:
        raise table.error("token", "no longer used: commands are signed with the command key (key_file, "
                                   "created by the daemon at first start); remove the token "
                                   "(docs/telemetry.md, 'Who may command the machine')")
    text = table.get("key_file", str, "")
    if text and not os.path.isabs(text) and getattr(table, "file", ""):
        text = os.path.join(os.path.dirname(os.path.abspath(table.file)), text)
    return text
