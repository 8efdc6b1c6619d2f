"""A CAN bus between the processes of one computer, with no network: python-can interface ``canon_local``.

For simulated drives in a process other than the master's (``[motion] process = "own"``, ``canon sim
drives``): python-can's ``virtual`` bus exists inside one process only, and ``udp_multicast`` joins a
multicast group (it belongs in a private network namespace, not on a workstation). Never for real
drives: they are on a CAN adapter (``socketcan``).

A channel is a directory (:func:`channel_dir`): a name such as ``"demo"`` is
``$CANON_BUS_DIR/demo``, else ``$XDG_RUNTIME_DIR/canon/bus/demo``, else ``/tmp/canon-<uid>/bus/demo``;
an absolute path is that directory. It is made mode 0700 and must belong to this user (the bus is
this user's alone). Each bus object listens on an ``AF_UNIX`` ``SOCK_SEQPACKET`` socket file of its
own there and keeps one connection to every other socket file of the directory, each frame one
packet (:data:`HEADER` and the data bytes):

* :meth:`LocalBus.send` sends the frame on each of these connections without waiting
  (``MSG_DONTWAIT``). A connection whose peer does not read fills its own send buffer
  (:data:`SEND_BUFFER`, seconds of traffic) and then drops that peer's frames, counted
  (:attr:`LocalBus.dropped`) and logged once per stall: the sender and the other peers go on.
  (Datagram sockets would share one send buffer between all peers and limit a peer's queue to
  ``net.unix.max_dgram_qlen`` frames, 10 on many systems.)
* The peers are the directory's socket files, listed again when its modification time changes (and
  for a moment after each change: the file system's clock is coarse). A socket file that refuses
  connections is left over from a process that died: it is removed. A new socket is bound under a
  hidden name, listens, and only then takes its final name, so a live peer never refuses.
* :meth:`LocalBus._recv_internal` waits on the listening socket and the accepted connections
  (epoll); frames from several peers come out in the order of their timestamps where they wait
  together; each peer's own frames always in the order sent.
* ``receive_own_messages`` as on ``virtual``: the bus connects to itself too.
* :meth:`LocalBus.shutdown` removes the socket file (and the channel directory once empty).
"""

from __future__ import annotations

import contextlib
import errno
import itertools
import logging
import os
import re
import secrets
import selectors
import socket
import stat
import struct
import threading
import time
from pathlib import Path
from typing import Any

import can

from fieldbus.canopen.config import LOCAL_INTERFACE as INTERFACE  # can.Bus(interface="canon_local", ...)

log = logging.getLogger(__name__)

HEADER = struct.Struct("<dIBB")
"""A frame's packet: timestamp (s, the sender's ``time.time()``), arbitration id, flags, DLC; the data
bytes follow."""
EXT, RTR, ERR, FD, BRS, ESI, OWN = (1 << i for i in range(7))
SUFFIX = ".sock"
SEND_BUFFER = 4 * 1024 * 1024
"""Asked for on each connection: a packet costs about 768 bytes of it, so some 5,000 frames
(2.5 s at 2 ms with three drives) may wait for a stalled peer before its frames are dropped."""
RELIST_NS = 100_000_000
"""The directory is listed again while its last change is younger than this (a coarse clock may show
two changes in one tick as one)."""
NAME = re.compile(r"[A-Za-z0-9_.-]{1,64}")
_MAX_PACKET = HEADER.size + 64
_count = itertools.count(1)
_SO_SNDBUFFORCE = getattr(socket, "SO_SNDBUFFORCE", 32)
_SUN_PATH = 108  # sizeof(sockaddr_un.sun_path) on Linux


def bus_root() -> tuple[Path, Path]:
    """Where named channels live: ``$CANON_BUS_DIR``, else ``$XDG_RUNTIME_DIR/canon/bus``, else
    ``/tmp/canon-<uid>/bus``; and the first directory of that path which is canon's own (made private
    with it)."""
    if os.environ.get("CANON_BUS_DIR"):
        root = Path(os.environ["CANON_BUS_DIR"])
        return root, root
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime and os.path.isdir(runtime):
        base = Path(runtime) / "canon"
    else:
        base = Path(f"/tmp/canon-{os.getuid()}")
    return base / "bus", base


def channel_problem(channel: str) -> str | None:
    """What is wrong with ``channel`` as a local bus channel (None: fine)."""
    if channel.startswith("/"):
        return None if len(channel) <= 80 else f"a directory path of at most 80 characters, got {channel!r}"
    if not NAME.fullmatch(channel) or channel in (".", ".."):
        return (f"a name of 1 to 64 letters, digits, '.', '_' and '-' (or a directory's absolute path), "
                f"got {channel!r}")
    return None


def channel_dir(channel: str) -> Path:
    """The directory of ``channel`` (module docstring)."""
    problem = channel_problem(channel)
    if problem:
        raise can.CanInitializationError(f"{INTERFACE} channel: {problem}")
    return Path(channel) if channel.startswith("/") else bus_root()[0] / channel


def _private_dirs(directory: Path) -> None:
    """Make the channel's directory, and for a named channel canon's directories above it, mode 0700;
    refuse one that is not this user's or that others may write to (they could listen to the bus or
    send on it)."""
    root, own = bus_root()
    chain = [own, root, directory] if directory.parent == root else [directory]  # own: root or its parent
    for d in dict.fromkeys(chain):
        with contextlib.suppress(FileExistsError):
            d.mkdir(mode=0o700)
        st = os.lstat(d)
        if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.geteuid() or st.st_mode & 0o022:
            raise can.CanInitializationError(
                f"{INTERFACE}: {d} is not a directory of this user's that only it may write to (a link, "
                f"another user's, or group/other writable): remove it or choose another channel")


def _pack(msg: can.Message, own: bool = False) -> bytes:
    flags = ((EXT if msg.is_extended_id else 0) | (RTR if msg.is_remote_frame else 0)
             | (ERR if msg.is_error_frame else 0) | (FD if msg.is_fd else 0)
             | (BRS if msg.bitrate_switch else 0) | (ESI if msg.error_state_indicator else 0)
             | (OWN if own else 0))
    return HEADER.pack(time.time(), msg.arbitration_id, flags, msg.dlc) + bytes(msg.data or b"")


def _unpack(packet: bytes, channel: str) -> can.Message:
    timestamp, arbitration_id, flags, dlc = HEADER.unpack_from(packet)
    return can.Message(timestamp=timestamp, arbitration_id=arbitration_id, is_extended_id=bool(flags & EXT),
                       is_remote_frame=bool(flags & RTR), is_error_frame=bool(flags & ERR),
                       is_fd=bool(flags & FD), bitrate_switch=bool(flags & BRS),
                       error_state_indicator=bool(flags & ESI), dlc=dlc, data=packet[HEADER.size:],
                       channel=channel, is_rx=not flags & OWN, check=False)


class _Peer:
    """Our connection to another bus's socket, and its drops."""

    __slots__ = ("dropping", "name", "sock")

    def __init__(self, name: str, sock: socket.socket) -> None:
        self.name = name
        self.sock = sock
        self.dropping = 0  # frames dropped in the current stall (0: none)


class LocalBus(can.BusABC):
    """python-can bus ``canon_local`` (module docstring). ``channel``: a name or a directory;
    ``receive_own_messages``: this bus receives what it sends; ``send_buffer``: bytes asked for on
    each connection (:data:`SEND_BUFFER`). Other keyword arguments (``bitrate`` ...) are accepted and
    ignored: the bus has no bit timing. ``send_only``: no socket file of its own, so no peer sends to
    it (a SYNC process, :mod:`fieldbus.canopen.sync_process`, that never reads: peers would fill its
    queue and log it); it receives nothing."""

    def __init__(self, channel: Any = "canon", receive_own_messages: bool = False,
                 send_buffer: int = SEND_BUFFER, can_filters: Any = None, send_only: bool = False,
                 **kwargs: Any) -> None:
        self.channel = str(channel)
        self.dir = channel_dir(self.channel)
        self._dir_path = str(self.dir)  # looked at on every send
        self.channel_info = f"{INTERFACE} bus {self.dir}"
        self.receive_own_messages = receive_own_messages
        self.send_buffer = send_buffer
        self.dropped = 0
        """Frames not delivered to a peer that did not read (its connection's buffer full)."""
        self.name = f"{os.getpid()}-{next(_count)}-{secrets.token_hex(3)}{SUFFIX}"
        self._peers: dict[str, _Peer] = {}
        self._seen: tuple[int, int] = (-1, 0)  # (the directory's mtime, when listed) of the last listing
        self._send_lock = threading.Lock()
        self._recv_lock = threading.Lock()
        self._heads: dict[socket.socket, can.Message] = {}  # one frame read ahead per connection
        self._listener = None if send_only else self._listen()
        self._selector = selectors.DefaultSelector()
        if self._listener is not None:
            self._selector.register(self._listener, selectors.EVENT_READ)
        self._wake, self._waker = socket.socketpair()  # shutdown wakes a recv waiting meanwhile
        self._selector.register(self._wake, selectors.EVENT_READ)
        super().__init__(channel=self.channel, can_filters=can_filters, **kwargs)

    # ------------------------------------------------------------------ the socket files
    def _path(self, name: str) -> str:
        return str(self.dir / name)

    def _listen(self) -> socket.socket:
        """Bind a hidden name, listen, then rename to :attr:`name` (a live peer never refuses)."""
        for attempt in range(3):
            _private_dirs(self.dir)
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_CLOEXEC)
            hidden = self._path("." + self.name)
            try:
                sock.bind(hidden)
                sock.listen(64)
                os.rename(hidden, self._path(self.name))
            except FileNotFoundError:  # the last bus out removed the directory meanwhile: again
                sock.close()
                if attempt < 2:
                    continue
                raise can.CanInitializationError(f"{INTERFACE}: {self.dir} keeps vanishing") from None
            except OSError as exc:
                sock.close()
                with contextlib.suppress(OSError):
                    os.unlink(hidden)
                if len(hidden.encode()) >= _SUN_PATH:
                    raise can.CanInitializationError(
                        f"{INTERFACE}: {hidden} is too long for a socket's address ({_SUN_PATH - 1} bytes "
                        f"at most): a shorter channel name, or set CANON_BUS_DIR to a shorter directory"
                    ) from None
                raise can.CanInitializationError(f"{INTERFACE}: cannot listen in {self.dir}: {exc}") from None
            sock.setblocking(False)
            return sock
        raise AssertionError("unreachable")

    def _connect(self, name: str) -> _Peer | bool | None:
        """A connection to the socket file ``name``; None when it is gone (a file that refuses is a
        dead bus's: removed); False when it does not accept now (its backlog full: tried again)."""
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET | socket.SOCK_CLOEXEC)
        try:
            sock.setsockopt(socket.SOL_SOCKET, _SO_SNDBUFFORCE, self.send_buffer)  # CAP_NET_ADMIN
        except OSError:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.send_buffer)  # up to wmem_max
        sock.setblocking(False)
        try:
            sock.connect(self._path(name))
        except OSError as exc:
            sock.close()
            if exc.errno == errno.ECONNREFUSED:
                log.info("%s: removing %s, left over from a bus that is gone", self.channel_info, name)
                with contextlib.suppress(OSError):
                    os.unlink(self._path(name))
                return None
            if exc.errno == errno.ENOENT:
                return None
            log.debug("%s: cannot connect to %s now: %s", self.channel_info, name, exc)
            return False
        return _Peer(name, sock)

    def _refresh(self) -> None:
        """Connect to new socket files of the directory, drop those gone (module docstring)."""
        try:
            mtime = os.stat(self._dir_path).st_mtime_ns
        except FileNotFoundError:
            return
        seen, listed = self._seen
        if mtime == seen and listed - mtime >= RELIST_NS:
            return
        now = time.time_ns()
        try:
            names = {n for n in os.listdir(self._dir_path) if n.endswith(SUFFIX) and not n.startswith(".")}
        except FileNotFoundError:
            names = set()
        if not self.receive_own_messages:
            names.discard(self.name)
        for name in self._peers.keys() - names:
            self._drop_peer(name)
        retry = False
        for name in names - self._peers.keys():
            peer = self._connect(name)
            if isinstance(peer, _Peer):
                self._peers[name] = peer
            retry = retry or peer is False
        self._seen = (-1, 0) if retry else (mtime, now)

    def _drop_peer(self, name: str) -> None:
        peer = self._peers.pop(name)
        peer.sock.close()

    # ------------------------------------------------------------------ python-can
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send ``msg`` to every other bus of the channel; never waits (module docstring)."""
        if self._is_shutdown:
            raise can.CanOperationError(f"{self.channel_info} is shut down")
        packet = _pack(msg)
        with self._send_lock:
            self._refresh()
            for name, peer in list(self._peers.items()):
                own = name == self.name
                try:
                    peer.sock.send(_pack(msg, own=True) if own else packet, socket.MSG_DONTWAIT)
                except BlockingIOError:
                    self._drop(peer)
                    continue
                except OSError as exc:  # the peer closed (ECONNRESET, EPIPE): its file goes or is dead
                    log.debug("%s: %s gone: %s", self.channel_info, name, exc)
                    self._drop_peer(name)
                    self._seen = (-1, 0)
                    continue
                if peer.dropping:
                    log.warning("%s: %s reads again; %d frames to it were dropped", self.channel_info,
                                name, peer.dropping)
                    peer.dropping = 0

    def _drop(self, peer: _Peer) -> None:
        self.dropped += 1
        peer.dropping += 1
        if peer.dropping == 1:
            log.warning("%s: %s does not read (its queue is full): dropping its frames until it does",
                        self.channel_info, peer.name)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._is_shutdown:
            raise can.CanOperationError(f"{self.channel_info} is shut down")
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._recv_lock:
            while True:
                if self._heads:
                    wait: float | None = 0.0
                else:
                    wait = None if deadline is None else max(0.0, deadline - time.monotonic())
                accepted = False
                for key, _ in self._selector.select(wait):
                    sock = key.fileobj
                    if sock is self._wake:
                        return None, False
                    if sock is self._listener:
                        accepted = self._accept()
                    elif sock not in self._heads:
                        self._read(sock)  # type: ignore[arg-type]
                if self._heads:
                    sock = min(self._heads, key=lambda s: self._heads[s].timestamp)
                    return self._heads.pop(sock), False
                if not accepted and deadline is not None and time.monotonic() >= deadline:
                    return None, False  # (a new connection is looked at once more: its frames wait)

    def _accept(self) -> bool:
        """Take the new connections; True if there was one."""
        took = False
        while True:
            try:
                conn, _ = self._listener.accept()  # type: ignore[union-attr]  (only when listening)
            except (BlockingIOError, InterruptedError):
                return took
            took = True
            conn.setblocking(False)
            self._selector.register(conn, selectors.EVENT_READ)

    def _read(self, sock: socket.socket) -> None:
        try:
            packet = sock.recv(_MAX_PACKET)
        except BlockingIOError:
            return
        except OSError:
            packet = b""
        if len(packet) < HEADER.size:  # end of file: that bus shut down (or died)
            self._selector.unregister(sock)
            sock.close()
            return
        self._heads[sock] = _unpack(packet, self.channel)

    def shutdown(self) -> None:
        if self._is_shutdown:
            return
        super().shutdown()
        with contextlib.suppress(OSError):
            os.unlink(self._path(self.name))
        self._waker.send(b"x")
        with self._send_lock:
            for name in list(self._peers):
                self._drop_peer(name)
        with self._recv_lock:
            for key in list(self._selector.get_map().values()):
                key.fileobj.close()  # type: ignore[union-attr]
            self._selector.close()
            self._heads.clear()
        self._waker.close()
        with contextlib.suppress(OSError):  # the last one out; another bus's file keeps it
            self.dir.rmdir()

    @staticmethod
    def _detect_available_configs() -> list[dict[str, Any]]:
        root = bus_root()[0]
        try:
            names = sorted(p.name for p in root.iterdir() if p.is_dir())
        except OSError:
            names = []
        return [{"interface": INTERFACE, "channel": n} for n in names]
