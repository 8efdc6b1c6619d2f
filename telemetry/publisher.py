"""Publishing the machine's state on LCM, and the rule for who may command it.

* :func:`open_lcm` opens an LCM instance for a URL and turns LCM's bare ``RuntimeError: Couldn't
  create LCM`` (no multicast route: an offline PC, a container, a network namespace) into
  :class:`TelemetryUnavailable` with the fix; with ``fallback="memq"`` or ``"none"`` it logs that and
  returns a process-local instance or None, so that ``canon run`` carries on without telemetry.
* :class:`StatusPublisher` publishes the latest status snapshot at a fixed rate from its own thread.
  The cycle loop only swaps in a new snapshot (one attribute assignment): encoding and sending never
  run on the caller's thread, and a slow network cannot delay a cycle.
* :class:`EventPublisher` publishes events as they happen from its own thread through a bounded
  queue: when the queue is full the event is dropped and counted, never waited for.
* Who may command the machine is :mod:`telemetry.auth` (signed commands), whatever the URL.

Both publishers accept ``lc=None`` (no telemetry) and then do nothing, so callers need no branches.
"""

from __future__ import annotations

import errno
import itertools
import logging
import queue
import socket
import time
from typing import Any, Literal, Protocol

import lcm

from telemetry.url import DEFAULT_URL, LcmUrl, parse_url
from telemetry.worker import Worker

log = logging.getLogger(__name__)

CANON_STATUS = "CANON_STATUS"
CANON_EVENT = "CANON_EVENT"
CANON_COMMAND = "CANON_COMMAND"
CANON_REPLY = "CANON_REPLY"
CHANNELS = (CANON_STATUS, CANON_EVENT, CANON_COMMAND, CANON_REPLY)

DEFAULT_STATUS_HZ = 50.0
MAX_STATUS_HZ = 1000.0
DEFAULT_EVENT_QUEUE = 1000

MULTICAST_FIX = "ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo"


class Encodable(Protocol):
    def encode(self) -> bytes: ...


class TelemetryUnavailable(RuntimeError):
    """LCM cannot be opened on the configured URL. ``fix`` says what to do about it."""

    def __init__(self, url: str, reason: str, fix: str) -> None:
        self.url = url
        self.reason = reason
        self.fix = fix
        super().__init__(f"telemetry: cannot open LCM at {url}: {reason}. {fix}")


def now_utime() -> int:
    """Microseconds since the Unix epoch, LCM's ``utime``."""
    return time.time_ns() // 1000


def _multicast_route_problem(parsed: LcmUrl) -> str | None:
    """Why this host cannot send to the URL's multicast group, or None if it can (LCM's own test)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect((parsed.group, parsed.port or 7667))
        except OSError as exc:
            if exc.errno in (errno.ENETUNREACH, errno.EHOSTUNREACH, errno.EADDRNOTAVAIL):
                return f"this host has no route to the multicast group {parsed.group} ({exc.strerror})"
            return f"cannot reach the multicast group {parsed.group}: {exc.strerror or exc}"
    return None


def _unavailable(parsed: LcmUrl, reason: str | None) -> TelemetryUnavailable:
    if parsed.provider in ("udpm", "mpudpm"):
        reason = reason or ("LCM could not join the multicast group " + parsed.group +
                            " (is there a multicast route, and is multicast on for the interface?)")
        fix = ("Usual on an offline machine PC, in a container or a network namespace. Fix, as root, "
               f"keeping LCM on this host: `{MULTICAST_FIX}`; or set [telemetry] url = \"memq://\" to run "
               "without telemetry outside this process.")
    else:
        reason = reason or "LCM refused the URL (see the lines LCM printed above)"
        fix = f"Check [telemetry] url; the default is {DEFAULT_URL}."
    return TelemetryUnavailable(parsed.url, reason, fix)


def preflight(url: str) -> LcmUrl:
    """Check that LCM can work on ``url`` without opening it (no multicast group is joined).

    Raises :class:`TelemetryUnavailable` for a malformed URL or, for ``udpm``, a host with no route
    to the group: the check LCM itself makes first, done here so that the message is ours (LCM would
    print its own advice and raise a bare ``RuntimeError``).
    """
    try:
        parsed = parse_url(url)
    except ValueError as exc:
        raise TelemetryUnavailable(url, str(exc), f"Check [telemetry] url; the default is {DEFAULT_URL}.") \
            from None
    if parsed.provider in ("udpm", "mpudpm"):
        problem = _multicast_route_problem(parsed)
        if problem is not None:
            raise _unavailable(parsed, problem)
    return parsed


def open_lcm(url: str = DEFAULT_URL, *,
             fallback: Literal["raise", "memq", "none"] = "raise") -> lcm.LCM | None:
    """Open LCM on ``url``.

    ``fallback="raise"`` (the daemon, ``canon spy``/``log``): a failure raises
    :class:`TelemetryUnavailable` with the reason and the fix. ``"memq"`` / ``"none"`` (``canon run``):
    the same message is logged as a warning and a ``memq://`` instance (messages stay inside this
    process) or None (no telemetry) is returned instead.
    """
    try:
        parsed = preflight(url)
        try:
            return lcm.LCM(parsed.url)
        except RuntimeError:
            raise _unavailable(parsed, None) from None
    except TelemetryUnavailable as exc:
        if fallback == "raise":
            raise
        if fallback == "memq":
            log.warning("%s Carrying on with telemetry inside this process only (memq://).", exc)
            return lcm.LCM("memq://")
        log.warning("%s Carrying on without telemetry.", exc)
        return None


class StatusPublisher(Worker):
    """Publishes the latest snapshot on ``channel`` every ``1/rate_hz`` seconds from its own thread.

    :meth:`update` hands over a snapshot (an LCM message object; the caller must not change it
    afterwards, build a new one per cycle). The thread wakes on an absolute-deadline clock, encodes
    whatever snapshot is latest and publishes it; if it falls behind it skips the missed periods
    (counted in ``overruns``) rather than publishing a burst. Until the first :meth:`update` nothing
    is published. A snapshot that cannot be encoded (array counts that do not match the arrays) is
    counted in ``errors`` and logged once per distinct message.
    """

    thread_name = "canon-status-publisher"

    def __init__(self, lc: lcm.LCM | None, rate_hz: float = DEFAULT_STATUS_HZ,
                 channel: str = CANON_STATUS) -> None:
        if not 0 < rate_hz <= MAX_STATUS_HZ:
            raise ValueError(f"status rate must be > 0 and <= {MAX_STATUS_HZ:g} Hz, got {rate_hz!r}")
        self.lc = lc
        self.rate_hz = float(rate_hz)
        self.channel = channel
        self.published = 0
        self.errors = 0
        self.overruns = 0
        self._latest: Encodable | None = None
        Worker.__init__(self)
        self._logged: set[str] = set()

    def update(self, snapshot: Encodable) -> None:
        """Make ``snapshot`` the one to publish next. Never blocks."""
        self._latest = snapshot

    @property
    def latest(self) -> Encodable | None:
        return self._latest

    def start(self) -> StatusPublisher:
        if self.lc is not None:
            self._start_thread()
        return self

    def publish_now(self) -> bool:
        """Encode and publish the latest snapshot on the calling thread; False if none or it failed."""
        snapshot = self._latest
        if snapshot is None or self.lc is None:
            return False
        try:
            data = snapshot.encode()
            self.lc.publish(self.channel, data)
        except Exception as exc:  # a bad snapshot or a send error must not end the thread
            self.errors += 1
            text = f"{type(exc).__name__}: {exc}"
            if text not in self._logged and len(self._logged) < 100:
                self._logged.add(text)
                log.error("cannot publish status on %s: %s", self.channel, text)
            return False
        self.published += 1
        return True

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        deadline = time.monotonic()
        while not self._stop.is_set():
            self.publish_now()
            deadline += period
            late = time.monotonic() - deadline
            if late > 0:
                missed = int(late / period) + 1
                self.overruns += missed
                deadline += missed * period
            self._stop.wait(max(0.0, deadline - time.monotonic()))


class EventPublisher(Worker):
    """Publishes events on ``channel`` as they happen, from its own thread.

    :meth:`publish` (or :meth:`emit`) stamps the event's ``seq`` (and ``utime`` when 0) and puts it
    in a bounded queue without waiting; when the queue is full the event is dropped and counted in
    ``dropped`` (put that in ``canon.status.events_dropped``); receivers see the gap in ``seq``.
    """

    thread_name = "canon-event-publisher"

    def __init__(self, lc: lcm.LCM | None, channel: str = CANON_EVENT,
                 maxsize: int = DEFAULT_EVENT_QUEUE) -> None:
        if maxsize < 1:
            raise ValueError(f"event queue size must be >= 1, got {maxsize!r}")
        self.lc = lc
        self.channel = channel
        self.published = 0
        self.dropped = 0
        self.errors = 0
        self._seq = itertools.count(1)
        self._queue: queue.Queue[Any] = queue.Queue(maxsize)
        Worker.__init__(self)

    def publish(self, event: Any) -> bool:
        """Queue ``event`` (a ``canon.event``) for publishing; False if it was dropped. Never blocks."""
        event.seq = next(self._seq)
        if not event.utime:
            event.utime = now_utime()
        if self.lc is None:
            return False
        try:
            self._queue.put_nowait(event)
        except queue.Full:
            self.dropped += 1
            return False
        return True

    def emit(self, severity: int, text: str, *, kind: str = "", source: str = "", file: str = "",
             line: int = 0) -> bool:
        """Build a ``canon.event`` and :meth:`publish` it. ``severity``: ``event.INFO`` etc."""
        from telemetry.lcmtypes.canon import event

        ev = event()
        ev.severity = int(severity)
        ev.kind = kind
        ev.source = source
        ev.file = file
        ev.line = int(line)
        ev.text = text
        return self.publish(ev)

    def start(self) -> EventPublisher:
        if self.lc is not None:
            self._start_thread()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        """Publish what is queued (within ``timeout``), then end the thread."""
        super().stop(timeout)


    def _run(self) -> None:
        assert self.lc is not None
        while True:
            try:
                ev = self._queue.get(timeout=0.05)
            except queue.Empty:
                if self._stop.is_set():
                    return
                continue
            try:
                self.lc.publish(self.channel, ev.encode())
                self.published += 1
            except Exception as exc:  # one bad event must not end the thread
                self.errors += 1
                log.error("cannot publish event on %s: %s: %s", self.channel, type(exc).__name__, exc)
