"""The client half of LCM commands: send one ``canon.command`` and wait for its ``canon.reply``.

The daemon answers every command on ``CANON_COMMAND`` with one reply on ``CANON_REPLY`` carrying the
command's ``request_id`` and ``sender`` (:class:`telemetry.commands.CommandServer`). A client picks its
own reply by both: several HMIs may command the same machine and all of them see every reply.

:func:`send_command` is what ``canon ctl``, Python HMIs and the end-to-end tests use. It checks the verb
and its arguments with :func:`telemetry.commands.check_command` *before* sending (a typo is the user's
mistake, reported at once, not after a round trip), subscribes to the replies *before* publishing (a
fast daemon could otherwise answer before anyone listens), and waits at most ``timeout`` seconds.

The verbs of :data:`SERVICE_VERBS` (enable, disable, estop_reset, reset, home) talk SDO to the drives
for up to tens of seconds; the daemon runs them on a worker of its own so that its command channel
never waits (an E-stop during a homing is answered at once). Their reply says the command was
*accepted*; the result follows as one ``canon.event`` of kind ``command`` whose text carries the
request id and sender (:func:`result_text`). :func:`send_command` waits for that event too (at most
``wait_result`` seconds) and returns the result as the reply, so a client sees what it always saw:
``ok``, or ``error`` with the reason the operation failed.

``memq://`` keeps messages inside one LCM instance, so a client and a responder in the same process
meet only on the same instance: :func:`client_lcm` gives every caller in this process one shared
``memq://`` instance (the CLI-level tests run ``canon ctl --url memq://`` against a responder on it).
"""

from __future__ import annotations

import os
import secrets
import select
import socket
import threading
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any

from telemetry.auth import client_key, sign
from telemetry.commands import check_command, make_command
from telemetry.publisher import CANON_COMMAND, CANON_EVENT, CANON_REPLY, open_lcm
from telemetry.url import parse_url

__all__ = ["RESULT_TIMEOUT_S", "SERVICE_VERBS", "CommandError", "NoReply", "NoResult", "Reply", "client_lcm",
           "handle_one", "new_sender", "no_answer_message", "parse_result", "result_text", "send_command",
           "shared_memq"]

_HANDLE_SLICE_S = 0.1  # longest single wait for traffic while waiting for a reply

SERVICE_VERBS = frozenset({"enable", "disable", "estop_reset", "reset", "home"})
"""Verbs the daemon accepts at once and carries out on its service worker; the result is an event."""
RESULT_TIMEOUT_S = 120.0
"""Default wait for a service verb's result: a CiA 402 homing may take ``homing_timeout_s`` (30 s by
default) per axis."""
RESULT_KIND = "command"
"""``canon.event.kind`` of a service verb's result (INFO: done, ERROR: failed)."""


def _request_tag(request_id: int, sender: str) -> str:
    return f"(request {request_id} from {sender})"


def result_text(verb: str, request_id: int, sender: str, error: str | None) -> str:
    """The text of the event that reports a service verb's result (``error`` None: it succeeded).

    One definition for the daemon that writes it and the clients that look for it.
    """
    tag = _request_tag(request_id, sender)
    return f"{verb} done {tag}" if error is None else f"{verb} failed {tag}: {error}"


def parse_result(event: Any, verb: str, request_id: int, sender: str) -> tuple[bool, str] | None:
    """``(ok, error)`` if ``event`` (a ``canon.event``) is the result of that request, else None."""
    if event.kind != RESULT_KIND:
        return None
    tag = _request_tag(request_id, sender)
    if event.text == f"{verb} done {tag}":
        return True, ""
    prefix = f"{verb} failed {tag}: "
    if event.text.startswith(prefix):
        return False, event.text[len(prefix):]
    return None


class NoResult(TimeoutError):
    """A service verb was accepted, but its result event did not arrive within the wait."""

    def __init__(self, verb: str, timeout: float, request_id: int) -> None:
        self.verb = verb
        self.timeout = timeout
        self.request_id = request_id
        super().__init__(f"{verb!r} (request {request_id}) was accepted, but no result arrived within "
                         f"{timeout:g} s: it may still be running ('canon status' shows the machine)")


class CommandError(ValueError):
    """The command is malformed (unknown verb, wrong arguments); nothing was sent."""


class NoReply(TimeoutError):
    """No reply with our request id arrived within the timeout."""

    def __init__(self, verb: str, timeout: float, request_id: int) -> None:
        self.verb = verb
        self.timeout = timeout
        self.request_id = request_id
        super().__init__(f"no reply to {verb!r} (request {request_id}) within {timeout:g} s")


@dataclass(frozen=True)
class Reply:
    """A ``canon.reply`` as plain data: ``ok``, or ``error`` says why the command was refused."""

    request_id: int
    sender: str
    verb: str
    ok: bool
    error: str
    utime: int

    @classmethod
    def from_lcm(cls, msg: Any) -> Reply:
        return cls(int(msg.request_id), str(msg.sender), str(msg.verb), bool(msg.ok), str(msg.error),
                   int(msg.utime))

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def new_sender(program: str = "canon-ctl") -> str:
    """``program@host:pid``: names this client in commands, so that it can pick out its replies."""
    return f"{program}@{socket.gethostname()}:{os.getpid()}"


_memq: Any = None
_memq_lock = threading.Lock()


def shared_memq() -> Any:
    """This process's one shared ``memq://`` LCM instance (created on first use)."""
    global _memq
    with _memq_lock:
        if _memq is None:
            import lcm

            _memq = lcm.LCM("memq://")
        return _memq


def client_lcm(url: str) -> Any:
    """An LCM instance for a client on ``url``: :func:`shared_memq` for ``memq://``, else a new one.

    Raises ``telemetry.publisher.TelemetryUnavailable`` (with the reason and the fix) when LCM cannot
    work on ``url``, a malformed URL included.
    """
    try:
        provider = parse_url(url).provider
    except ValueError:
        provider = ""
    if provider == "memq":
        return shared_memq()
    return open_lcm(url)


def no_answer_message(what: str, url: str, timeout: float) -> str:
    """The message for "nothing arrived": the daemon is probably not running, or on another URL."""
    text = (f"no {what} within {timeout:g} s on {url}: the daemon may not be running, or it uses another "
            "LCM URL (give the machine's --config, or --url)")
    try:
        if parse_url(url).provider == "memq":
            text += "; memq:// reaches only this process, so no daemon can answer on it"
    except ValueError:
        pass
    return text


def handle_one(lc: Any, timeout: float) -> bool:
    """Wait up to ``timeout`` seconds for traffic on ``lc`` and dispatch one message; True if one was.

    The wait is Python's ``select`` on ``lc.fileno()``, not ``lc.handle_timeout()``: a Ctrl-C during
    LCM's own wait makes it fail with ``OSError: lcm_handle_timeout() returned -1`` on top of the
    ``KeyboardInterrupt``, which leaves the interpreter unable to print; here Ctrl-C is a plain
    ``KeyboardInterrupt``.
    """
    ready, _, _ = select.select([lc.fileno()], [], [], max(0.0, timeout))
    if not ready:
        return False
    try:
        lc.handle()
    except RuntimeError as exc:
        if "imultaneous" not in str(exc):
            raise
        raise RuntimeError("another thread is handling this LCM instance (LCM allows one at a time): "
                           "call send_command(..., handle=False) and let that thread deliver the "
                           "reply") from None
    return True


def send_command(lc: Any, verb: str, strings: Sequence[str] = (), values: Sequence[float] = (),
                 key: bytes | None = None, timeout: float = 5.0, *, sender: str | None = None,
                 request_id: int | None = None, handle: bool = True, channel: str = CANON_COMMAND,
                 reply_channel: str = CANON_REPLY, wait_result: float = RESULT_TIMEOUT_S,
                 event_channel: str = CANON_EVENT) -> Reply:
    """Send ``verb`` with its arguments on ``lc`` and return the daemon's :class:`Reply`.

    Raises :class:`CommandError` (nothing sent) when the verb or its arguments are malformed, and
    :class:`NoReply` when no reply with this request's id and sender arrives within ``timeout``
    seconds. A refused command is not an exception: the reply has ``ok`` False and the reason in
    ``error``.

    A verb of :data:`SERVICE_VERBS` that the daemon accepted is then waited for: its result event
    (:func:`result_text`) within ``wait_result`` seconds, returned as the reply (``ok`` False and the
    reason when the operation failed); :class:`NoResult` when it does not come. ``wait_result`` 0
    returns the acceptance at once.

    ``key``: the command key the command is signed with (:mod:`telemetry.auth`); None:
    :func:`telemetry.auth.client_key` (``$CANON_KEY``, ``$CANON_KEY_FILE``, the default key files),
    which raises ``telemetry.auth.CommandKeyError`` saying where to put it when there is none.

    ``handle``: True (a client of its own) handles ``lc`` here while waiting. LCM lets one thread at a
    time handle an instance, so when another thread already does (a ``CommandServer.start()`` or an
    HMI's loop on the same instance), pass False: that thread's dispatch delivers the reply.
    """
    if not timeout > 0:
        raise ValueError(f"timeout must be > 0, got {timeout!r}")
    if not wait_result >= 0:
        raise ValueError(f"wait_result must be >= 0, got {wait_result!r}")
    sender = sender if sender is not None else new_sender()
    rid = request_id if request_id is not None else secrets.randbits(62) + 1
    cmd = make_command(verb, list(strings), list(values), request_id=rid, sender=sender)
    problem = check_command(cmd)
    if problem is not None:
        raise CommandError(problem)
    sign(cmd, client_key() if key is None else key)

    from telemetry.lcmtypes.canon import event, reply

    done = threading.Event()
    got: list[Any] = []
    result: list[tuple[bool, str]] = []
    finished = threading.Event()

    def on_reply(_channel: str, data: bytes) -> None:
        try:
            rep = reply.decode(data)
        except Exception:  # a foreign message on the channel: not ours
            return
        if rep.request_id == rid and rep.sender == sender and not done.is_set():
            got.append(rep)
            done.set()

    def on_event(_channel: str, data: bytes) -> None:
        try:
            ev = event.decode(data)
        except Exception:
            return
        res = parse_result(ev, verb, rid, sender)
        if res is not None and not finished.is_set():
            result.append(res)
            finished.set()

    def wait(flag: threading.Event, limit: float) -> bool:
        deadline = time.monotonic() + limit
        while not flag.is_set():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            if handle:
                handle_one(lc, min(left, _HANDLE_SLICE_S))
            else:
                flag.wait(min(left, _HANDLE_SLICE_S))
        return True

    waits_result = verb in SERVICE_VERBS and wait_result > 0
    subscription = lc.subscribe(reply_channel, on_reply)
    # subscribed before publishing: the result of a quick operation may come before the reply
    events = lc.subscribe(event_channel, on_event) if waits_result else None
    try:
        lc.publish(channel, cmd.encode())
        if not wait(done, timeout):
            raise NoReply(verb, timeout, rid)
        rep = Reply.from_lcm(got[0])
        if not (waits_result and rep.ok):
            return rep
        if not wait(finished, wait_result):
            raise NoResult(verb, wait_result, rid)
        ok, error = result[0]
        return replace(rep, ok=ok, error=error)
    finally:
        lc.unsubscribe(subscription)
        if events is not None:
            lc.unsubscribe(events)
