"""Signed commands: who may drive the machine over LCM, whatever the URL.

Anyone who can put a UDP packet on the LCM group can send a ``canon.command``, and a multicast TTL of 0
limits only what the daemon sends, never what it accepts: a host on the same LAN segment reaches a
daemon with ``ttl=0`` as soon as the multicast route points at the network card. So every command is
signed, on every URL:

* ``mac``: HMAC-SHA256 with the *command key* (32 random bytes) over the whole message as encoded with
  an empty ``mac`` (``mac_len`` 0), type fingerprint included: every field is covered. The key never
  travels on the wire; it lives in a file readable by the daemon's user and the operators' group
  (:func:`load_or_create_key`, created at the daemon's first start with mode 0640).
* ``sender`` is the client's id and ``seq`` a number strictly increasing per sender
  (:func:`next_seq`): the daemon remembers the sequence numbers it accepted from each sender and
  refuses one seen before or older than those it remembers (a replay; :data:`REORDER`).
* ``utime`` must lie within ``window_s`` (5 s) of the daemon's clock: a message captured and sent
  again later is stale, even after the daemon forgot its sender.

:class:`Verifier` makes these checks in that order (MAC first: nobody without the key can fill the
daemon's table of senders). A sender is forgotten ``2 * window_s`` after its last command, when any
replay of its commands is stale anyway. :class:`RateLimiter` bounds what one key (a client, or all
refusals together) may cost the daemon.

What this does not do: hide anything. Commands, replies, status and events stay readable by anyone
on the network segment (docs/telemetry.md, threat model).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import hmac
import logging
import os
import secrets
import stat
import threading
import time
from collections import OrderedDict
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

KEY_BYTES = 32
MAC_BYTES = 32
KEY_FILE_NAME = "command.key"
KEY_MODE = 0o640
WINDOW_S = 5.0
MAX_SENDERS = 4096
ENV_KEY = "CANON_KEY"
ENV_KEY_FILE = "CANON_KEY_FILE"
SYSTEM_KEY_FILE = Path("/var/lib/canon") / KEY_FILE_NAME
"""Where the shipped systemd unit's daemon keeps its key (``StateDirectory=canon``)."""

_DOMAIN = b"canon.command.v1\0"


class CommandKeyError(ValueError):
    """The command key cannot be had: the message names the file (or variable) and the fix."""


# ---------------------------------------------------------------- the key file


def parse_key(text: str, where: str) -> bytes:
    """The key from its text form (64 hex digits, surrounding white space ignored)."""
    body = text.strip()
    try:
        key = bytes.fromhex(body)
    except ValueError:
        key = b""
    if len(key) != KEY_BYTES:
        raise CommandKeyError(f"{where}: not a command key (expected {2 * KEY_BYTES} hexadecimal digits)")
    return key


def read_key(path: str | os.PathLike[str]) -> bytes:
    """Read the key file; :class:`CommandKeyError` names the file and what is wrong."""
    name = os.fspath(path)
    try:
        with open(name, "rb") as fh:
            raw = fh.read(4 * KEY_BYTES + 16)
    except FileNotFoundError:
        raise CommandKeyError(f"{name}: no such key file") from None
    except OSError as exc:
        raise CommandKeyError(f"{name}: cannot read the command key: {exc.strerror or exc}") from None
    try:
        text = raw.decode("ascii")
    except UnicodeDecodeError:
        text = ""
    return parse_key(text, name)


def check_key_file_mode(path: str | os.PathLike[str]) -> None:
    """Refuse a key file other users may read or any one but its owner may write."""
    name = os.fspath(path)
    mode = stat.S_IMODE(os.stat(name).st_mode)
    if mode & 0o027:
        raise CommandKeyError(
            f"{name}: the command key is open to other users (mode {mode:04o}); it must be readable only "
            f"by the daemon's user and the operators' group: chmod 640 {name}")


def load_or_create_key(path: str | os.PathLike[str]) -> bytes:
    """The daemon's key: read ``path``, or create it with a new random key (mode 0640) if missing.

    The file is written under a temporary name, synced, then linked into place (``os.link`` fails if
    another process created it meanwhile, and then that one's key is used), so it is never seen half
    written. A key file with wider permissions than 0640 is refused (:func:`check_key_file_mode`).
    """
    name = os.fspath(path)
    if not os.path.exists(name):
        _create_key_file(name)
    check_key_file_mode(name)
    return read_key(name)


def _create_key_file(name: str) -> None:
    directory = os.path.dirname(os.path.abspath(name))
    tmp = os.path.join(directory, f".{os.path.basename(name)}.{secrets.token_hex(6)}.tmp")
    text = (secrets.token_bytes(KEY_BYTES).hex() + "\n").encode("ascii")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o600)
    except OSError as exc:
        raise CommandKeyError(f"{name}: cannot create the command key: {exc.strerror or exc}") from None
    try:
        try:
            os.fchmod(fd, KEY_MODE)  # not left to the umask
            os.write(fd, text)
            os.fsync(fd)
        finally:
            os.close(fd)
        with contextlib.suppress(FileExistsError):  # another daemon made one first: use that
            os.link(tmp, name)
    except OSError as exc:
        raise CommandKeyError(f"{name}: cannot create the command key: {exc.strerror or exc}") from None
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        except OSError as exc:
            if exc.errno != errno.EINVAL:
                raise
        finally:
            os.close(fd)
    log.info("created the command key %s (mode %04o)", name, KEY_MODE)


def default_key_files() -> list[Path]:
    """Where a client looks for the key when nothing says where: the user's own daemon's state
    directory, then the systemd service's."""
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return [Path(base) / "canon" / KEY_FILE_NAME, SYSTEM_KEY_FILE]


def client_key(key_file: str | os.PathLike[str] | None = None) -> bytes:
    """The key for a client (``canon ctl``, an HMI), never from the command line.

    In order: ``$CANON_KEY`` (the key's 64 hex digits), ``$CANON_KEY_FILE``, ``key_file`` (the machine
    file's ``[telemetry] key_file``), then :func:`default_key_files`.
    """
    text = os.environ.get(ENV_KEY, "")
    if text.strip():
        return parse_key(text, f"${ENV_KEY}")
    named = os.environ.get(ENV_KEY_FILE, "").strip() or (os.fspath(key_file) if key_file else "")
    if named:
        return read_key(named)
    tried = default_key_files()
    for candidate in tried:
        if candidate.exists():
            return read_key(candidate)
    raise CommandKeyError(
        "no command key: commands must be signed with the daemon's key. Set CANON_KEY_FILE to its key "
        f"file (the daemon creates {KEY_FILE_NAME} in its state directory at first start; "
        f"{SYSTEM_KEY_FILE} under systemd; readable by the operators' group) or CANON_KEY to its hex "
        f"digits; looked in {', '.join(str(p) for p in tried)}")


# ---------------------------------------------------------------- signing and checking

_seq_lock = threading.Lock()
_last_seq = 0


def next_seq() -> int:
    """A number above every one this process handed out, and above those of an earlier process with
    the same sender id (it starts at the time in microseconds)."""
    global _last_seq
    with _seq_lock:
        _last_seq = max(_last_seq + 1, time.time_ns() // 1000)
        return _last_seq


def compute_mac(key: bytes, unsigned: bytes) -> bytes:
    """HMAC-SHA256 over the message encoded with an empty mac."""
    return hmac.new(key, _DOMAIN + unsigned, hashlib.sha256).digest()


def sign(cmd: Any, key: bytes, seq: int | None = None) -> Any:
    """Give ``cmd`` (a ``canon.command``) its ``seq`` (:func:`next_seq` unless given) and ``mac``."""
    cmd.seq = next_seq() if seq is None else int(seq)
    cmd.mac_len, cmd.mac = 0, b""
    mac = compute_mac(key, cmd.encode())
    cmd.mac_len, cmd.mac = len(mac), mac
    return cmd


def unsigned_bytes(data: bytes, mac_len: int) -> bytes:
    """The encoded message as it was before signing: the trailing ``mac`` cut and ``mac_len`` 0.

    ``mac`` is the type's last field, so this is exact, with no re-encoding (which could differ from
    what the client signed, e.g. for text that is not UTF-8)."""
    return data[:len(data) - mac_len - 2] + b"\0\0"


class Verifier:
    """The daemon's checks of a decoded command and its raw bytes: MAC, time window, sequence.

    :meth:`check` returns None (accepted, the sender's ``seq`` remembered) or the reason it is refused.
    Thread-safe.
    """

    def __init__(self, key: bytes, *, window_s: float = WINDOW_S, max_senders: int = MAX_SENDERS,
                 clock: Any = time.time) -> None:
        if len(key) != KEY_BYTES:
            raise ValueError(f"a command key has {KEY_BYTES} bytes, got {len(key)}")
        if not window_s > 0:
            raise ValueError(f"window_s must be > 0, got {window_s!r}")
        self._key = key
        self.window_s = float(window_s)
        self.max_senders = max_senders
        self._clock = clock
        self._seen: OrderedDict[str, _SeqWindow] = OrderedDict()  # sender -> its recent sequence numbers
        self._lock = threading.Lock()

    def check(self, cmd: Any, data: bytes) -> str | None:
        n = int(cmd.mac_len)
        if n == 0:
            return "unsigned command (commands must carry an HMAC with the command key)"
        if n != MAC_BYTES or not hmac.compare_digest(compute_mac(self._key, unsigned_bytes(data, n)),
                                                     bytes(cmd.mac)):
            return "bad MAC (not signed with this daemon's command key)"
        now = self._clock()
        off = cmd.utime / 1e6 - now
        if abs(off) > self.window_s:
            return (f"stale command: its time is {off:+.1f} s from the daemon's clock (window "
                    f"{self.window_s:g} s; a replay, or the clocks differ)")
        sender = str(cmd.sender)
        seq = int(cmd.seq)
        with self._lock:
            self._forget(now)
            window = self._seen.get(sender)
            if window is None:
                if len(self._seen) >= self.max_senders:
                    return f"too many clients within {2 * self.window_s:g} s ({self.max_senders})"
                window = self._seen[sender] = _SeqWindow()
            if seq <= window.floor or seq in window.recent:
                return f"replayed command: seq {seq} from {sender!r} was seen already (or is older than " \
                       f"the last {REORDER} accepted)"
            window.accept(seq, now)
            self._seen.move_to_end(sender)
        return None

    def _forget(self, now: float) -> None:
        """Drop senders quiet for 2 windows: any replay of theirs is stale by then (oldest first)."""
        horizon = now - 2 * self.window_s - 1.0
        while self._seen:
            sender, window = next(iter(self._seen.items()))
            if window.at >= horizon:
                return
            del self._seen[sender]


REORDER = 256
"""How many of a sender's latest sequence numbers the daemon remembers one by one. A client numbers
its commands strictly increasing, but the daemon may take them out of order (an E-stop is checked
before the commands read ahead of it), so, as IPsec's anti-replay window, any number not seen yet and
above the oldest one remembered is accepted once; a number seen already, or older, is a replay."""


class _SeqWindow:
    __slots__ = ("at", "floor", "recent")

    def __init__(self) -> None:
        self.floor = -(1 << 63)
        self.recent: set[int] = set()
        self.at = 0.0

    def accept(self, seq: int, now: float) -> None:
        self.recent.add(seq)
        self.at = now
        if len(self.recent) > REORDER:
            oldest = min(self.recent)
            self.recent.discard(oldest)
            self.floor = max(self.floor, oldest)


class RateLimiter:
    """Token buckets by key: at most ``rate`` per second on average, ``burst`` at once."""

    def __init__(self, rate: float, burst: float, *, max_keys: int = 4096,
                 clock: Any = time.monotonic) -> None:
        self.rate = float(rate)
        self.burst = float(burst)
        self.max_keys = max_keys
        self._clock = clock
        self._buckets: OrderedDict[str, tuple[float, float]] = OrderedDict()  # key -> (tokens, at)
        self._lock = threading.Lock()

    def allow(self, key: str = "") -> bool:
        now = self._clock()
        with self._lock:
            tokens, at = self._buckets.pop(key, (self.burst, now))
            tokens = min(self.burst, tokens + (now - at) * self.rate)
            ok = tokens >= 1.0
            if ok:
                tokens -= 1.0
            self._buckets[key] = (tokens, now)
            while len(self._buckets) > self.max_keys:
                self._buckets.popitem(last=False)
            return ok
