"""Commands over LCM: the verbs, their arguments, and a server that checks and answers them.

A client publishes a signed ``canon.command`` on ``CANON_COMMAND``; :class:`CommandServer` decodes
it, refuses it if :class:`telemetry.auth.Verifier` (MAC, time, sequence) or :func:`check_command`
says so, else passes it to the daemon's handler, and publishes one ``canon.reply`` with the same
``request_id`` and ``sender`` on ``CANON_REPLY``. The handler runs on the LCM thread: it should
queue the work and return at once.
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import struct
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from telemetry.auth import WINDOW_S, RateLimiter, Verifier, sign
from telemetry.publisher import CANON_COMMAND, CANON_REPLY, now_utime
from telemetry.worker import Worker

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Verb:
    strings: tuple[int, int]   # allowed number of text arguments (min, max)
    values: tuple[int, int]    # allowed number of numeric arguments (min, max)
    help: str


_SWITCH = "values[0]: 1 on, 0 off"
VERBS: dict[str, Verb] = {
    "run": Verb((1, 1), (0, 1), "strings[0]: program file; values[0]: line to start at (optional)"),
    "mdi": Verb((1, 1), (0, 0), "strings[0]: one line of G-code"),
    "pause": Verb((0, 0), (0, 0), "feed hold"),
    "resume": Verb((0, 0), (0, 0), "continue after pause or a single-block stop"),
    "feed_override": Verb((0, 0), (1, 1), "values[0]: factor, 1.0 = 100 %"),
    "abort": Verb((0, 0), (0, 0), "stop the program with a controlled stop"),
    "estop": Verb((0, 0), (0, 0), "emergency stop: quick stop on every drive"),
    "estop_reset": Verb((0, 0), (0, 0), "leave emergency stop (drives stay disabled)"),
    "enable": Verb((0, 0), (0, 0), "enable the drives (operation enabled)"),
    "disable": Verb((0, 0), (0, 0), "disable the drives"),
    "home": Verb((0, 9), (0, 0), "strings: axis letters to home (none: all)"),
    "jog": Verb((1, 1), (1, 2), "strings[0]: axis; values[0]: velocity (signed, units/s); "
                                "values[1]: distance (optional; none or 0: until a jog with velocity 0)"),
    "single_block": Verb((0, 0), (1, 1), _SWITCH),
    "optional_stop": Verb((0, 0), (1, 1), _SWITCH),
    "block_delete": Verb((0, 0), (1, 1), _SWITCH),
    "reset": Verb((0, 0), (0, 0), "clear faults and the last error"),
}


def _count(lo: int, hi: int) -> str:
    if lo == hi:
        return str(lo)
    return f"{lo} to {hi}"


def check_command(command: Any) -> str | None:
    """Whether ``command``'s verb and arguments are well formed: None, or what is wrong."""
    verb = VERBS.get(command.verb)
    if verb is None:
        return f"unknown verb {command.verb!r} (known: {', '.join(VERBS)})"
    if command.num_strings != len(command.strings) or command.num_values != len(command.values):
        return "num_strings/num_values do not match the arrays"
    for what, n, (lo, hi) in (("text", command.num_strings, verb.strings),
                              ("numeric", command.num_values, verb.values)):
        if not lo <= n <= hi:
            return f"{command.verb} takes {_count(lo, hi)} {what} argument(s), got {n} ({verb.help})"
    if not all(math.isfinite(v) for v in command.values):
        return f"{command.verb}: numeric arguments must be finite numbers"
    return None


def make_command(verb: str, strings: tuple[str, ...] | list[str] = (),
                 values: tuple[float, ...] | list[float] = (), *, request_id: int = 0,
                 sender: str = "", key: bytes | None = None, seq: int | None = None) -> Any:
    """A ``canon.command`` filled in (``utime`` now), signed with ``key`` when given
    (:func:`telemetry.auth.sign`: ``seq`` and ``mac``)."""
    from telemetry.lcmtypes.canon import command

    cmd = command()
    cmd.utime = now_utime()
    cmd.request_id = request_id
    cmd.sender = sender
    cmd.verb = verb
    cmd.strings = list(strings)
    cmd.num_strings = len(cmd.strings)
    cmd.values = [float(v) for v in values]
    cmd.num_values = len(cmd.values)
    if key is not None:
        sign(cmd, key, seq)
    elif seq is not None:
        cmd.seq = int(seq)
    return cmd


def _raw_verb(data: bytes) -> str:
    """The verb of an encoded ``canon.command``, read without decoding the rest ("" if it is not one):
    fingerprint, utime, request_id (8 bytes each), sender (int32 length with its NUL, bytes), seq (8),
    then the verb."""
    try:
        (n,) = struct.unpack_from(">i", data, 24)
        at = 28 + n + 8
        (m,) = struct.unpack_from(">i", data, at)
        if not 1 <= m <= 64:
            return ""
        return data[at + 4:at + 3 + m].decode("ascii")
    except (struct.error, UnicodeDecodeError):
        return ""


Handler = Callable[[Any], "str | None"]
SecurityHook = Callable[[str], None]

IMMEDIATE_VERBS = frozenset({"estop"})
"""Carried out on the receiving thread the moment the command is read: nothing queues before them."""
URGENT_VERBS = frozenset({"abort", "pause", "resume", "feed_override"})
"""Carried out on a thread of their own, in order, never behind the other verbs, never rate-limited."""
COMMANDS_PER_S = 20.0
"""The other verbs: each sender may send this many per second on average (bursts of twice that);
beyond it a command is refused with the reason (``refused: rate limit ...``), never dropped."""
LANE_DEPTH = 64
"""Commands waiting per lane (urgent, other); one more is refused ``busy`` with the reason."""

ESTOPS_REMEMBERED = 64
"""E-stop datagrams remembered (by their bytes, MAC included) so the second copy is skipped."""

RECEIVE_QUEUE = 10_000
"""Commands LCM may hold for dispatch (its default is 30 per subscription, beyond which it drops)."""

REFUSAL_REPLIES_PER_S = 10.0
"""Replies to refused (unauthenticated) commands, all senders together: a flood of forged packets
must not turn the daemon into a flood of replies and events. Beyond it they are counted, not sent."""


class CommandServer(Worker):
    """Answers ``canon.command`` messages: authenticate, check, call ``handler``, publish the reply.

    Every command must be signed with ``key`` (:mod:`telemetry.auth`: MAC, time window, per-sender
    sequence), whatever the URL. A refused one gets a reply with the reason and ``on_security(text)``
    (the daemon publishes it as a ``security`` event); both at most :data:`REFUSAL_REPLIES_PER_S`
    per second, the rest counted in ``unanswered``. ``handler(command)`` returns None when the
    command is accepted, or the reason it is not.

    Commands read from LCM take one of three ways, so that an E-stop never waits behind anything:
    :data:`IMMEDIATE_VERBS` (``estop``) are handled at once on the thread that reads them: for a
    ``udpm`` ``url`` (the one ``lc`` was opened with) a socket of their own that the kernel hands
    E-stops only (:mod:`telemetry.estop_socket`; its thread's body wrapped by ``estop_thread``, the
    daemon's stop-path ranking), else LCM's receiving thread;
    :data:`URGENT_VERBS` (abort, hold, resume, feed override) on the ``urgent`` lane's thread; the
    others, at most :data:`COMMANDS_PER_S` per sender, on the ``normal`` lane's thread. The handler
    must therefore be callable from these three threads at once. A command refused by the rate limit
    or a full lane gets a reply saying so. :meth:`answer` decides one command on the calling thread.
    Call :meth:`subscribe` if the daemon runs its own
    ``lc.handle()`` loop, or :meth:`start` for a thread that does. ``replies`` / ``refused`` /
    ``bad_messages`` count what happened.
    """

    thread_name = "canon-command-server"

    def __init__(self, lc: Any, handler: Handler, *, key: bytes, url: str = "",
                 channel: str = CANON_COMMAND, reply_channel: str = CANON_REPLY,
                 window_s: float = WINDOW_S, on_security: SecurityHook | None = None,
                 refusal_rate: float = REFUSAL_REPLIES_PER_S,
                 estop_thread: Callable[[Callable[[], None]], Callable[[], None]] | None = None,
                 estop_cpu_budget: float | None = None) -> None:
        self.lc = lc
        self.handler = handler
        self.url = url
        self.verifier = Verifier(key, window_s=window_s)
        self.on_security = on_security
        self.channel = channel
        self.reply_channel = reply_channel
        self.replies = 0
        self.refused = 0
        self.unanswered = 0
        self.bad_messages = 0
        self.errors = 0
        self.rate_limited = 0
        self._refusals = RateLimiter(refusal_rate, 2 * refusal_rate)
        self._per_sender = RateLimiter(COMMANDS_PER_S, 2 * COMMANDS_PER_S)
        self._lanes: dict[str, queue.Queue[Any]] = {"urgent": queue.Queue(LANE_DEPTH),
                                                    "normal": queue.Queue(LANE_DEPTH)}
        self._lane_threads: list[threading.Thread] = []
        self._intake: queue.Queue[bytes] = queue.Queue(RECEIVE_QUEUE)
        self._intake_thread: threading.Thread | None = None
        self._lanes_stop = threading.Event()
        self._subscription: Any = None
        self._estop_thread = estop_thread
        self._estop_cpu_budget = estop_cpu_budget  # None: the E-stop socket's default (CPU_BUDGET)
        self.estop_listener: Any = None
        """:class:`telemetry.estop_socket.EstopListener` while E-stops come through their own socket."""
        self._estops_read: OrderedDict[bytes, None] = OrderedDict()
        self._estops_lock = threading.Lock()
        self.estop_socket_refused = ""
        """Why E-stops come through the ordinary socket ("" while they have their own)."""
        Worker.__init__(self)

    def subscribe(self) -> None:
        """Receive commands from ``lc`` (whoever handles it) and start the lanes' threads."""
        if not self._lane_threads:
            self._lanes_stop.clear()
            for name, lane in self._lanes.items():
                t = threading.Thread(target=self._lane_main, args=(lane,), name=f"canon-command-{name}",
                                     daemon=True)
                t.start()
                self._lane_threads.append(t)
            self._intake_thread = threading.Thread(target=self._intake_main, name="canon-command-intake",
                                                   daemon=True)
            self._intake_thread.start()
            self._lane_threads.append(self._intake_thread)
        if self.estop_listener is None:
            self._open_estop_socket()
        if self._subscription is None:
            self._subscription = self.lc.subscribe(self.channel, self.on_message)
            # LCM keeps 30 messages per subscription waiting for dispatch and drops the rest: a burst of
            # commands while this process is busy would lose some (an E-stop among them)
            with contextlib.suppress(AttributeError):
                self._subscription.set_queue_capacity(RECEIVE_QUEUE)

    def _open_estop_socket(self) -> None:
        """E-stops through a socket of their own (:mod:`telemetry.estop_socket`), where the URL allows."""
        from telemetry.estop_socket import EstopListener, open_estop_socket
        from telemetry.lcmtypes.canon import command
        from telemetry.url import parse_url

        if not self.url:  # which URL ``lc`` was opened with is not known: the ordinary socket only
            self.estop_socket_refused = "the command server was not told its LCM URL"
            return
        try:
            url = parse_url(self.url)
        except ValueError as exc:
            self.estop_socket_refused = str(exc)
            return
        sock, why = open_estop_socket(url, self.channel, command._get_packed_fingerprint())
        if sock is None:
            self.estop_socket_refused = why
            log.info("E-stops share the command socket: %s", why)
            return
        self.estop_socket_refused = ""
        budget = {} if self._estop_cpu_budget is None else {"cpu_budget": self._estop_cpu_budget}
        self.estop_listener = EstopListener(sock, self.channel, self._take_estop, self._estop_thread,
                                            **budget).start()

    def _first_read(self, data: bytes) -> bool:
        """Whether this E-stop datagram is read here for the first time. An E-stop arrives twice, on its
        own socket and on the ordinary one: whichever thread reads it first decides it, the other skips
        it (deciding it again would refuse it as a replay). Neither relies on the other: an E-stop the
        filtered socket did not get (its queue full, another transport) is still decided."""
        with self._estops_lock:
            if data in self._estops_read:
                return False
            self._estops_read[data] = None
            if len(self._estops_read) > ESTOPS_REMEMBERED:
                self._estops_read.popitem(last=False)
            return True

    def _take_estop(self, data: bytes) -> None:
        if not self._first_read(data):
            return
        try:
            self._take(data)
        except Exception:
            self.errors += 1
            raise

    def on_message(self, channel: str, data: bytes) -> None:
        """LCM's dispatch: an E-stop is decided at once (or left to its own socket, which has it
        already); anything else goes to the intake thread, so that a backlog of other commands never
        stands in front of an E-stop."""
        verb = _raw_verb(data)
        if verb in IMMEDIATE_VERBS and not self._first_read(data):
            return  # the E-stop's own socket had it first and decided it
        if self._intake_thread is not None and verb not in IMMEDIATE_VERBS:
            try:
                self._intake.put_nowait(data)
                return
            except queue.Full:
                pass  # decided here then: it is refused 'busy' by the full lane or the rate limit
        self._take(data, channel)

    def _take(self, data: bytes, channel: str = "") -> None:
        from telemetry.lcmtypes.canon import command

        try:
            cmd = command.decode(data)
        except Exception as exc:  # a foreign type on our channel: nothing to answer
            self.bad_messages += 1
            if self._refusals.allow():
                log.warning("ignoring a message on %s that is not a canon.command: %s",
                            channel or self.channel, exc)
            return
        self.dispatch(cmd, data)

    def _intake_main(self) -> None:
        while not self._lanes_stop.is_set():
            try:
                data = self._intake.get(timeout=0.05)
            except queue.Empty:
                continue
            try:
                self._take(data)
            except Exception:
                self.errors += 1
                log.exception("command server: a command could not be handled")

    def dispatch(self, cmd: Any, data: bytes) -> None:
        """Receiving thread: authenticate and check ``cmd``, then carry it out or queue it by its verb."""
        denied = self.verifier.check(cmd, data)
        if denied is not None:
            self._refuse_unauthenticated(cmd, denied)
            return
        error = check_command(cmd)
        if error is not None:
            self.refused += 1
            self._reply(cmd, error)
            return
        if cmd.verb in IMMEDIATE_VERBS:
            self._execute(cmd)
            return
        lane = self._lanes["urgent"] if cmd.verb in URGENT_VERBS else self._lanes["normal"]
        if cmd.verb not in URGENT_VERBS and not self._per_sender.allow(str(cmd.sender)):
            self.refused += 1
            self.rate_limited += 1
            self._reply(cmd, f"refused: rate limit: more than {COMMANDS_PER_S:g} commands per second from "
                             f"{str(cmd.sender)[:80]!r} (estop, abort, pause, resume and feed_override are "
                             "never limited); send it again later")
            return
        try:
            lane.put_nowait(cmd)
        except queue.Full:
            self.refused += 1
            self._reply(cmd, f"busy: {LANE_DEPTH} commands are waiting to be carried out; send it again "
                             "later")

    def _lane_main(self, lane: queue.Queue[Any]) -> None:
        while not self._lanes_stop.is_set():
            try:
                cmd = lane.get(timeout=0.05)
            except queue.Empty:
                continue
            try:
                self._execute(cmd)
            except Exception:  # a failed reply must not end the lane
                self.errors += 1
                log.exception("command %s from %r: answering failed", cmd.verb, cmd.sender)

    def _execute(self, cmd: Any) -> Any:
        """Call the handler on a checked, authenticated command and publish the reply."""
        try:
            error = self.handler(cmd)
        except Exception as exc:
            log.exception("command %s from %r failed", cmd.verb, cmd.sender)
            error = f"internal error: {type(exc).__name__}: {exc}"
        return self._reply(cmd, error)

    def answer(self, cmd: Any, data: bytes | None = None) -> Any:
        """Decide on ``cmd`` (``data``: the bytes it came as; None: its own encoding) and publish the
        reply; returns the reply, or None when a refusal went unanswered (rate limit)."""
        denied = self.verifier.check(cmd, cmd.encode() if data is None else data)
        if denied is not None:
            return self._refuse_unauthenticated(cmd, denied)
        error = check_command(cmd)
        if error is None:
            return self._execute(cmd)
        self.refused += 1
        log.warning("command %s from %r refused: %s", cmd.verb, cmd.sender, error)
        return self._reply(cmd, error)

    def _refuse_unauthenticated(self, cmd: Any, reason: str) -> Any:
        self.refused += 1
        if not self._refusals.allow():
            self.unanswered += 1
            return None
        text = f"refused: {reason}"
        note = (f"command {str(cmd.verb)[:40]!r} from {str(cmd.sender)[:80]!r} refused: {reason}"
                + (f" ({self.unanswered} more refusals not answered before this one)" if self.unanswered
                   else ""))
        log.warning("%s", note)
        if self.on_security is not None:
            try:
                self.on_security(note)
            except Exception:
                log.exception("reporting a refused command")
        return self._reply(cmd, text)

    def _reply(self, cmd: Any, error: str | None) -> Any:
        from telemetry.lcmtypes.canon import reply

        rep = reply()
        rep.utime = now_utime()
        rep.request_id = cmd.request_id
        rep.sender = cmd.sender
        rep.verb = cmd.verb
        rep.ok = error is None
        rep.error = error or ""
        self.lc.publish(self.reply_channel, rep.encode())
        self.replies += 1
        return rep
    def start(self) -> CommandServer:
        """Subscribe and handle LCM traffic on a thread of our own."""
        self.subscribe()
        self._start_thread()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        super().stop(timeout)
        if self._subscription is not None:
            self.lc.unsubscribe(self._subscription)
            self._subscription = None
        if self.estop_listener is not None:
            self.estop_listener.stop(timeout)
            self.estop_listener = None
        self._lanes_stop.set()
        for t in self._lane_threads:
            t.join(timeout)
        self._lane_threads = []
        self._intake_thread = None
        while True:  # read but not yet decided: decided now (refused 'busy' as the lanes no longer run)
            try:
                data = self._intake.get_nowait()
            except queue.Empty:
                break
            with contextlib.suppress(Exception):
                self._take(data)
        for lane in self._lanes.values():  # none dropped silently: what was waiting is told so
            while True:
                try:
                    cmd = lane.get_nowait()
                except queue.Empty:
                    break
                self.refused += 1
                with contextlib.suppress(Exception):
                    self._reply(cmd, "not carried out: the daemon's command server is stopping")

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.lc.handle_timeout(50)
            except Exception:
                # An LCM error (a failed publish of a reply, a socket hiccup) must not end command
                # handling for the life of the daemon: count it, log it, keep serving.
                self.errors += 1
                log.exception("command server: handling LCM traffic failed; still serving")
                self._stop.wait(0.05)
