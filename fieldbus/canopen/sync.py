"""The SYNC timed by the kernel: python-can's periodic send on SocketCAN, and the master's view of it.

``[canopen] sync`` (:attr:`~fieldbus.canopen.config.CanopenConfig.sync`) chooses who times the SYNC:

* ``"master"``: the master's cycle sends the SYNC at its deadline, first, and then every drive's RPDO
  for the next SYNC (:meth:`~fieldbus.canopen.master.CanopenMaster.sync`; the only way on buses
  without kernel timing: ``virtual``, ``udp_multicast``): the same structure as the kernel's, with the
  SYNC from the cycle thread. The cycle's own work (the planner's setpoint, the RPDOs) never delays
  the SYNC, but a stall of the Python process at the deadline still does.
* ``"kernel"``: on SocketCAN, ``bus.send_periodic`` is the kernel's broadcast manager (BCM): a kernel
  timer sends the SYNC every period whatever Python does. The kernel loops the frames it sends back to
  every other socket on the interface, so the master sees each SYNC on a socket of its own
  (:class:`KernelSync`, filtered to the SYNC's COB-ID) and sends each drive's RPDO for the *next*
  SYNC right after it. A stall shorter than a period (less the time the RPDOs take) costs nothing on
  the bus; a longer one costs setpoints (the drives hold the last target), never a SYNC.
* ``"process"``: the same structure on buses without the kernel's timer (``canon_local``,
  ``udp_multicast``): a SYNC process of its own sends it and reports each one on a pipe
  (:mod:`fieldbus.canopen.sync_process`, :attr:`KernelSync.timer`), which the master reads in place
  of the listening socket. It also sends the drives' RPDOs, which the master hands it up to
  ``[canopen] setpoint_lead`` SYNCs ahead (:mod:`fieldbus.canopen.setpoint_buffer`).
* ``"auto"``: ``"kernel"`` on socketcan, else ``"master"``.

With the kernel's SYNC the cycle thread is paced by the SYNCs it sees (:meth:`KernelSync.wait`, the
``tick`` of :class:`~fieldbus.canopen.clock.PeriodicRunner`), not by a clock of its own: the BCM re-arms
its timer from the moment it fired (``ktime_get() + interval`` in ``net/can/bcm.c``), so its period is
the configured one plus the kernel's timer latency, and a loop on absolute deadlines would drift
against it (two setpoints in one SYNC period, or none, every few hundred cycles).

The master prepares the task when it opens the bus (so a bus without kernel timing is refused there)
and the kernel starts sending at the first cycle, as the master's own SYNC starts with its cycle. The
BCM task belongs to its socket: it ends with :meth:`KernelSync.stop` and with the process (the kernel
removes a closed socket's tasks), so no SYNC outlives canon; and the machine stops it when it stops its
cycle (:meth:`~fieldbus.canopen.master.CanopenMaster.stop_sync`), so no SYNC reaches an enabled drive
without a setpoint, as none does with the master's own SYNC.
"""

from __future__ import annotations

import logging
import threading
import time

import can

from fieldbus.canopen.sync_process import SyncProcess, SyncProcessError

log = logging.getLogger(__name__)

SYNC_COB_ID = 0x80


class SyncError(Exception):
    """The kernel's periodic SYNC could not be started on this bus."""


class KernelSync:
    """The SYNC sent by the kernel every ``period_s`` on ``bus`` (python-can's periodic send, which on
    SocketCAN is the broadcast manager), and seen on a socket of its own opened from ``bus_kwargs``
    (python-can's ``can.Bus`` arguments of the same interface and channel).

    :meth:`wait` (the cycle thread) and :meth:`poll` (the master's cycle) both count the SYNCs seen:
    :attr:`seen` is their total, :attr:`last_at` the ``time.monotonic`` time of the latest (from the
    kernel's receive time stamp)."""

    def __init__(self, bus: can.BusABC, bus_kwargs: dict[str, object], period_s: float,
                 cob_id: int = SYNC_COB_ID, timer: SyncProcess | None = None) -> None:
        self.bus = bus
        self.bus_kwargs = bus_kwargs
        self.period_s = period_s
        self.cob_id = cob_id
        #: ``[canopen] sync = "process"``: the process that sends the SYNC in place of the kernel's
        #: broadcast manager (:mod:`fieldbus.canopen.sync_process`), already started and waiting
        self.timer = timer
        self.seen = 0
        self.last_at = 0.0
        self._task: can.broadcastmanager.RestartableCyclicTaskABC | None = None
        self._started = False
        self._listener: can.BusABC | None = None
        self._lock = threading.Lock()  # one reader of the listening socket at a time

    @property
    def running(self) -> bool:
        return self._started

    def open(self) -> None:
        """Open the listening socket and make the kernel's periodic SYNC ready, not yet sending
        (:meth:`start`). :class:`SyncError` when the bus's periodic send is not the kernel's (python-can
        falls back to a Python thread there)."""
        if self._task is not None:
            return
        if self.timer is not None:  # the SYNC process sends it and reports each one on its pipe
            self._task = self.timer  # type: ignore[assignment]
            return
        from can.interfaces.socketcan import CyclicSendTask

        filters = [{"can_id": self.cob_id, "can_mask": 0x7FF, "extended": False}]
        try:
            self._listener = can.Bus(**self.bus_kwargs, can_filters=filters)  # type: ignore[arg-type]
        except (can.CanError, OSError, ValueError) as exc:
            raise SyncError(f"cannot open a socket to see the SYNC on: {exc}") from None
        msg = can.Message(arbitration_id=self.cob_id, data=b"", is_extended_id=False)
        try:
            task = self.bus.send_periodic(msg, self.period_s, store_task=False, autostart=False)
        except (can.CanError, OSError) as exc:
            self._close_listener()
            raise SyncError(f"the kernel's periodic SYNC cannot be set up: {exc}") from None
        if not isinstance(task, CyclicSendTask):
            self._close_listener()
            raise SyncError(f"the {type(self.bus).__name__}'s periodic send is a Python thread, not the "
                            "kernel's broadcast manager: [canopen] sync = \"kernel\" needs socketcan")
        self._task = task

    def start(self) -> None:
        """The kernel sends the SYNC from now on (the BCM's TX_SETUP), until :meth:`stop`. Idempotent."""
        if self._started or self._task is None:
            return
        try:
            self._task.start()
        except (can.CanError, OSError, SyncProcessError) as exc:
            raise SyncError(f"the {self.source}'s periodic SYNC did not start: {exc}") from None
        self._started = True
        by = "kernel's broadcast manager" if self.timer is None else f"SYNC process (pid {self.timer.pid})"
        log.info("SYNC every %g ms by the %s", 1000 * self.period_s, by)

    @property
    def source(self) -> str:
        """Who sends the SYNC: "kernel" (SocketCAN's broadcast manager) or "process" (the SYNC
        process)."""
        return "kernel" if self.timer is None else "process"

    def stop(self) -> None:
        """Stop the SYNC (the BCM task's TX_DELETE), then close the listening socket. Safe twice."""
        task, self._task = self._task, None
        started, self._started = self._started, False
        if self.timer is not None:  # also never started or opened: the process ends here
            self.timer.end()  # no SYNC from now on; its pipe is closed below, once no wait reads it
        elif task is not None and started:
            try:
                task.stop()
            except (can.CanError, OSError) as exc:
                log.error("stopping the kernel's SYNC: %s (it ends with the bus or the process)", exc)
        with self._lock:
            self._close_listener()
            timer, self.timer = self.timer, None
            if timer is not None:
                timer.stop()

    def _close_listener(self) -> None:
        listener, self._listener = self._listener, None
        if listener is not None:
            listener.shutdown()

    @staticmethod
    def _monotonic(msg: can.Message) -> float:
        """The kernel's receive time stamp (wall clock) on the ``time.monotonic`` scale."""
        return msg.timestamp - (time.time() - time.monotonic())

    def _read(self, timeout: float) -> float | None:
        """One SYNC from the listening socket (or the SYNC process's report) within ``timeout`` (0: only
        one already there): its time."""
        if self.timer is not None:
            t = self.timer.read(timeout)
            if t is not None:
                self.seen += 1
                self.last_at = t
            return t
        listener = self._listener
        if listener is None:
            return None
        try:
            msg = listener.recv(timeout)
        except (can.CanError, OSError):
            return None
        if msg is None:
            return None
        t = self._monotonic(msg)
        self.seen += 1
        self.last_at = t
        return t

    def poll(self) -> int:
        """Count the SYNCs seen since the last :meth:`poll` or :meth:`wait`, without waiting; returns how
        many. Skipped while another thread waits (that one counts them)."""
        self.start()
        if not self._lock.acquire(blocking=False):
            return 0
        try:
            return self._drain()[1]
        finally:
            self._lock.release()

    def _drain(self) -> tuple[float, int]:
        """Take the SYNCs already there, up to the first one stamped after the drain began: (the time of
        the last taken, how many). Bounded so: on a machine that reads slower than the SYNCs come (the
        emulated VM: one drain read 299 SYNCs in 4.0 s), "until none is left" held the cycle for
        seconds and the master faulted as stalled while the kernel kept the SYNC going."""
        begun = time.monotonic()
        last, n = 0.0, 0
        while (t := self._read(0.0)) is not None:
            last, n = t, n + 1
            if t >= begun:
                break
        return last, n

    def wait(self, until: float) -> tuple[float, float, int] | None:
        """Wait until ``until`` (``time.monotonic``) for the next SYNC; then take any more already
        there. Returns (time of the first, time of the last, how many), or None when none came."""
        try:
            self.start()
        except SyncError as exc:  # the cycle's poll() makes it a fault; no tick meanwhile
            log.error("%s", exc)
            time.sleep(max(0.0, until - time.monotonic()))
            return None
        with self._lock:
            first = self._read(max(0.0, until - time.monotonic()))
            if first is None:
                # a source that ended (the SYNC process's pipe at EOF, a failed socket) answers at once:
                # the wait still lasts until ``until``, or the cycle would step unpaced, setpoints at CPU
                # speed, and the stall watch would never see the SYNC missing
                rest = until - time.monotonic()
                if rest > 0:
                    time.sleep(rest)
                return None
            last, more = self._drain()
            return first, last if more else first, 1 + more
