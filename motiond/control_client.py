"""The client half of LCM commands: send one ``canon.command`` and wait for its ``canon.reply``.

The daemon answers every command on ``CANON_COMMAND`` with one reply on ``CANON_REPLY`` carrying the
command's ``request_id`` and ``sender`` (:class:`telemetry.commands.CommandServer`). A client picks its
own reply by both: several HMIs may command the same machine and all of them see every reply.

:func:`send_command` is what ``canon ctl``, Python HMIs and the end-to-end tests use. It checks the verb
and its arguments with :func:`telemetry.commands.check_command` *before* sending (a typo is the user's
mistake, reported at once, not after a round trip), subscribes to the replies *before* publishing (a
fast daemon could otherwise answer before anyone listens), and waits at most ``timeout`` seconds.

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
from dataclasses import asdict, dataclass
from typing import Any

from telemetry.commands import check_command, make_command
from telemetry.publisher import CANON_COMMAND, CANON_REPLY, open_lcm
from telemetry.url import parse_url

__all__ = ["CommandError", "NoReply", "Reply", "client_lcm", "handle_one", "new_sender", "no_answer_message",
           "send_command", "shared_memq"]

_HANDLE_SLICE_S = 0.1  # longest single wait for traffic while waiting for a reply


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
                 token: str = "", timeout: float = 5.0, *, sender: str | None = None,
                 request_id: int | None = None, handle: bool = True, channel: str = CANON_COMMAND,
                 reply_channel: str = CANON_REPLY) -> Reply:
    """Send ``verb`` with its arguments on ``lc`` and return the daemon's :class:`Reply`.

    Raises :class:`CommandError` (nothing sent) when the verb or its arguments are malformed, and
    :class:`NoReply` when no reply with this request's id and sender arrives within ``timeout``
    seconds. A refused command is not an exception: the reply has ``ok`` False and the reason in
    ``error``.

    ``handle``: True (a client of its own) handles ``lc`` here while waiting. LCM lets one thread at a
    time handle an instance, so when another thread already does (a ``CommandServer.start()`` or an
    HMI's loop on the same instance), pass False: that thread's dispatch delivers the reply.
    """
    if not timeout > 0:
        raise ValueError(f"timeout must be > 0, got {timeout!r}")
    sender = sender if sender is not None else new_sender()
    rid = request_id if request_id is not None else secrets.randbits(62) + 1
    cmd = make_command(verb, list(strings), list(values), request_id=rid, sender=sender, token=token)
    problem = check_command(cmd)
    if problem is not None:
        raise CommandError(problem)

    from telemetry.lcmtypes.canon import reply

    done = threading.Event()
    got: list[Any] = []

    def on_reply(_channel: str, data: bytes) -> None:
        try:
            rep = reply.decode(data)
        except Exception:  # a foreign message on the channel: not ours
            return
        if rep.request_id == rid and rep.sender == sender and not done.is_set():
            got.append(rep)
            done.set()

    subscription = lc.subscribe(reply_channel, on_reply)
    try:
        lc.publish(channel, cmd.encode())
        deadline = time.monotonic() + timeout
        while not done.is_set():
            left = deadline - time.monotonic()
            if left <= 0:
                raise NoReply(verb, timeout, rid)
            if handle:
                handle_one(lc, min(left, _HANDLE_SLICE_S))
            else:
                done.wait(min(left, _HANDLE_SLICE_S))
    finally:
        lc.unsubscribe(subscription)
    return Reply.from_lcm(got[0])
