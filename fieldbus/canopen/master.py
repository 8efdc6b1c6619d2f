"""The CANopen CiA 402 master: boots the drives, streams a target per drive per cycle, stops on faults.

Life of a master (the daemon's loop thread calls :meth:`CanopenMaster.cycle` once per cycle)::

    master = CanopenMaster(config)          # refuses a bus load over config.max_bus_load
    master.open(); master.boot(); master.enable()
    master.sync()                           # at the cycle's deadline: the SYNC, first
    fb = master.cycle(positions)            # an RPDO per drive (its target for the next SYNC)
    ...                                     # on a fault: master.fault, drives quick-stopped
    master.reset_faults(); master.enable()  # and stream again from master.positions()
    master.shutdown()

Design choices:

* Boot and enable use SDO (0x6040/0x6041) before streaming starts; once streaming, the controlword
  travels by PDO (with the target in the standard layout, in its own RPDO on a change in the compact
  one: :mod:`fieldbus.canopen.pdo`), so an SDO write could not override it.
* Every PDO a drive has beyond the layout's is disabled at boot: a factory mapping adds no traffic.
* SYNC first, then the RPDOs for the next SYNC: at each deadline the SYNC goes out at once
  (:meth:`CanopenMaster.sync`, or first thing in :meth:`CanopenMaster.cycle`), then the cycle's checks
  and every drive's RPDO, which the drives latch at the next SYNC (one cycle of latency, as with the
  kernel's SYNC, :mod:`fieldbus.canopen.sync`). All RPDOs of a cycle go out between the same two SYNCs,
  so the targets of every drive land in the same SYNC period; the work of a cycle never delays its
  SYNC.
* Counts are converted from absolute positions each cycle (``AxisScale``): no drift.
* Quick stop (on any fault, or asked for): every drive gets the CiA 402 quick-stop controlword at once
  and no new target is streamed; the drives decelerate on their own 0x6085 ramp. The quick stop option
  boot writes to 0x605A depends on the layout (:func:`~fieldbus.canopen.config.quick_stop_option`):
  ``compact`` 6, the drives stay in Quick stop active holding position (a vertical axis does not drop);
  ``standard`` 2, the drives end in Switch on disabled, because its cyclic controlword 0x0F would
  otherwise re-enable a drive that stopped itself (transition 16). The master keeps the last commanded
  positions; the planner restarts from :meth:`positions` after :meth:`reset_faults` and :meth:`enable`.
* A drive that leaves Operation enabled by itself (its own quick stop, disabled, fault) is seen in the
  first statusword after it (every SYNC in ``standard``, on the change in ``compact``): the machine
  stops, the fault names node, state and reason, and the master never re-enables it.
* Limit switches (0x60FD bits 0/1, in TPDO4 on change): a switch that becomes active while the drive
  is streamed to, or a target that moves toward an active one, stops the machine (quick stop, as any
  fault), naming axis, node and switch. After a reset the axis may move off the switch, not onto it.
* The spindle drive (``[canopen.spindle]``, :mod:`~fieldbus.canopen.master_spindle`), in a velocity
  mode, is booted, enabled, stopped and parked with the axes; its RPDO goes out with the axes', after
  each SYNC for the next one.
* The drives' digital outputs (0x60FE, :mod:`~fieldbus.canopen.master_outputs`): :meth:`set_output`
  never blocks; its own thread writes them by SDO.
* Faults are reported once (the first, which caused the stop) in :attr:`fault`; later ones go to
  :attr:`fault_log`.

The master is one class in parts, by concern: this module holds the bus set-up and the cyclic
exchange; :mod:`~fieldbus.canopen.master_boot` the boot and SDO access,
:mod:`~fieldbus.canopen.master_states` the CiA 402 state machine (enable, disable, reset, homing,
shutdown), :mod:`~fieldbus.canopen.master_supervision` the faults and the checks of the feedback,
:mod:`~fieldbus.canopen.master_records` the errors, faults, feedback and per-drive book-keeping,
:mod:`~fieldbus.canopen.master_setpoints` the RPDOs handed to the SYNC process ahead of their SYNC.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Sequence

import can
import canopen

from fieldbus.canopen import cia402
from fieldbus.canopen.busload import BusLoad, alternatives, bus_load
from fieldbus.canopen.busopen import open_bus
from fieldbus.canopen.config import CanopenConfig
from fieldbus.canopen.master_boot import BootMixin
from fieldbus.canopen.master_outputs import OutputsMixin
from fieldbus.canopen.master_records import (
    INPUT_BITS,
    NEGATIVE_LIMIT,
    POSITIVE_LIMIT,
    BusBudgetError,
    CanopenError,
    DriveBook,
    DriveFeedback,
    DriveState,
    Fault,
    input_names,
)
from fieldbus.canopen.master_setpoints import SetpointsMixin
from fieldbus.canopen.master_spindle import SpindleBook, SpindleFeedback, SpindleMixin
from fieldbus.canopen.master_states import StateMachineMixin
from fieldbus.canopen.master_supervision import ErrorFrameListener, SupervisionMixin
from fieldbus.canopen.sync import SYNC_COB_ID, KernelSync, SyncError
from fieldbus.canopen.sync_process import SyncProcess, SyncProcessError

__all__ = ["INPUT_BITS", "NEGATIVE_LIMIT", "POSITIVE_LIMIT", "BusBudgetError", "CanopenError",
           "CanopenMaster", "DriveFeedback", "DriveState", "Fault", "SpindleFeedback", "input_names"]

log = logging.getLogger(__name__)


class CanopenMaster(BootMixin, StateMachineMixin, SupervisionMixin, SpindleMixin, OutputsMixin,
                    SetpointsMixin):
    """Master of the configured drives on one bus. ``bus``: an open python-can bus to use (else one is
    made from ``config.bus``). ``check_budget=False`` only reports the bus load (benchmarks on the
    virtual bus, which has no bitrate)."""

    def __init__(self, config: CanopenConfig, bus: can.BusABC | None = None, *,
                 check_budget: bool = True) -> None:
        self.config = config
        self.layout = config.layout
        hb = (config.heartbeat_producer_ms, config.heartbeat_producer_ms)
        # a spindle drive's frames (two cyclic TPDOs, one RPDO) count as one more drive's
        n_drives = len(config.drives) + (config.spindle is not None)
        self.load: BusLoad = bus_load(n_drives, config.cycle_s, config.bus.bitrate, *hb,
                                      self.layout)
        if check_budget and self.load.fraction > config.max_bus_load:
            fits = alternatives(len(config.drives), config.cycle_s, config.bus.bitrate, config.max_bus_load,
                                *hb, config.status_refresh_ms)
            raise BusBudgetError(
                f"bus load {100 * self.load.fraction:.1f} % is over the {100 * config.max_bus_load:.0f} % "
                f"allowed: {len(config.drives)} drives every {1000 * config.cycle_s:g} ms in the "
                f"{self.layout.name} PDO layout (following error every {config.following_error_every} "
                f"SYNC) make {self.load.describe()}; "
                + (f"[canopen] settings that fit: {'; '.join(fits)}" if fits else
                   "fewer drives on this bus or a higher bitrate"))
        log.info("CANopen bus load: %s", self.load.describe())
        self._bus = bus
        self._own_bus = bus is None
        self.network: canopen.Network | None = None
        self.drives: list[DriveBook] = []
        self.spindle: SpindleBook | None = None
        self.fault: Fault | None = None
        self.fault_log: list[Fault] = []
        self.cycles = 0
        self.streaming = False
        self._lock = threading.RLock()
        self._heartbeat_task: canopen.network.PeriodicMessageTask | None = None
        self._stream_t0 = 0.0  # first cycle with a drive streamed to: TPDO ages count from there
        self._last_sent = 0.0  # the last cycle's frames sent while streaming to a drive (0: none yet)
        self._rpdo_syncs = -1
        self._synced = False  # this cycle's SYNC is out (or, kernel SYNC, counted): :meth:`sync`
        self._sync_at = 0.0  # when the master last sent a SYNC
        self._reader_sync_at = 0.0
        #: who times the SYNC: "kernel" (the broadcast manager, :mod:`fieldbus.canopen.sync`), "process"
        #: (a SYNC process, :mod:`fieldbus.canopen.sync_process`: the kernel's structure on buses without
        #: it) or "master"
        self.sync_mode = config.sync_source
        self._kernel_sync: KernelSync | None = None
        #: kernel SYNC: SYNCs that found no new RPDO since the previous one while streaming (the drives
        #: held their last target); with the master's SYNC a stalled cycle delays the SYNC instead
        self.missed_setpoints = 0
        #: ``sync = "process"``: the SYNC process also sends the RPDOs, computed up to this many SYNCs
        #: ahead (:mod:`fieldbus.canopen.setpoint_buffer`); else 1 (sent by the cycle, for the next SYNC)
        self.setpoint_lead = config.setpoint_lead if self.sync_mode == "process" else 1
        self._setpoints: SyncProcess | None = None  # the SYNC process that sends the RPDOs
        self._next_tag = 0  # the SYNC the next set of RPDOs is for (0: from the next one seen)
        self._generation = 0  # raised at each stop: a set pushed before it is void
        self._frames: list[tuple[int, bytes]] | None = None  # the cycle's RPDOs, while it gathers them
        self.last_set_tag = 0
        self._fault_listeners: list[Callable[[Fault], None]] = []
        self._warning_listeners: list[Callable[[Fault], None]] = []
        self.warnings: list[Fault] = []

    # ------------------------------------------------------------------ set-up
    def open(self) -> None:
        """Connect to the bus, add the drives' nodes, start the master's heartbeat."""
        if self.network is not None:
            return
        bus = self._bus or open_bus(self.config.bus)
        self._bus = bus
        net = canopen.Network(bus)
        net.listeners.append(ErrorFrameListener(self))
        net.NOTIFIER_SHUTDOWN_TIMEOUT = 2.0
        net.connect()
        if self.sync_mode != "master":
            try:
                self._start_kernel_sync(net, bus)
            except CanopenError:
                self._release(net)
                raise
        self.network = net
        for cfg in self.config.drives:
            node = canopen.RemoteNode(cfg.node_id, cfg.eds_path)
            node.sdo.RESPONSE_TIMEOUT = self.config.sdo_timeout_s
            node.sdo.MAX_RETRIES = 2  # one retry (0 would retry forever)
            net.add_node(node)
            d = DriveBook(cfg, node, self.layout)
            self.drives.append(d)
            node.nmt.add_heartbeat_callback(lambda state, d=d: self._on_heartbeat(d, state))
            node.emcy.add_callback(lambda entry, d=d: self._on_emcy(d, entry))
            for p in self.layout.tpdos:
                net.subscribe(p.cob_id(cfg.node_id), self._tpdo_reader(d, p))
        self._open_spindle(net)
        if self.config.heartbeat_producer_ms > 0:
            self._heartbeat_task = net.send_periodic(
                0x700 + self.config.master_node_id, [0x05], self.config.heartbeat_producer_ms / 1000.0)

    def _release(self, net: canopen.Network) -> None:
        """Let go of the bus: closed if the master opened it, else only its reader stopped."""
        if self._own_bus:
            net.disconnect()
            self._bus = None
        elif net.notifier is not None:
            net.notifier.stop(2.0)

    def _start_kernel_sync(self, net: canopen.Network, bus: can.BusABC) -> None:
        """The kernel's periodic SYNC, ready: it starts with the first cycle (or wait for a tick) and
        runs until :meth:`shutdown`. The bus reader notes each SYNC it sees (TPDO ages count in SYNCs
        the reader has seen: a stall of the reader is not a drive's silence)."""
        net.subscribe(SYNC_COB_ID, self._on_sync)
        c = self.config
        timer = None
        try:
            if self.sync_mode == "process":
                timer = SyncProcess(dataclasses.asdict(c.bus), c.cycle_s, SYNC_COB_ID, c.realtime_priority,
                                    tuple(c.cpu_affinity))
            ks = KernelSync(bus, c.bus.bus_kwargs(), c.cycle_s, timer=timer)
            ks.open()
            self._setpoints = timer
        except (SyncError, SyncProcessError) as exc:
            if timer is not None:
                timer.stop()
            raise CanopenError(f"[canopen] sync = \"{c.sync}\": {exc}") from None
        self._kernel_sync = ks

    def _stop_kernel_sync(self) -> None:
        self._setpoints = None
        ks, self._kernel_sync = self._kernel_sync, None
        if ks is not None:
            ks.stop()

    def stop_sync(self) -> None:
        """The cycle has stopped for good (the machine is closing): the kernel's or the SYNC process's
        SYNC stops too, as the master's own stops with its cycle. Otherwise the drives, still enabled
        until :meth:`shutdown` parks them, see SYNCs with no new target: measured, 24 in 50 ms at
        2 ms, each a missed setpoint to a drive, and a fault to one that watches its RPDOs (EMCY
        0x8250). Safe twice; :meth:`shutdown` does it too."""
        self._stop_kernel_sync()

    def _on_sync(self, cob_id: int, data: bytearray, timestamp: float) -> None:
        self._reader_sync_at = time.monotonic()

    @property
    def sync_tick(self) -> Callable[[float], tuple[float, float, int] | None] | None:
        """With the kernel's SYNC: what paces the cycle thread (``PeriodicRunner(tick=...)``): wait for
        the next SYNC seen, so the RPDOs go out right after it. None with the master's own SYNC (the
        runner keeps its absolute deadlines)."""
        ks = self._kernel_sync
        return ks.wait if ks is not None else None

    # ------------------------------------------------------------------ the cycle
    def sync(self) -> None:
        """The start of a cycle, at its deadline: the master's SYNC goes out now, before the cycle's
        work (the planner's setpoint, the checks, the RPDOs), so that work never delays it; the RPDOs
        :meth:`cycle` sends afterwards are for the *next* SYNC. With the kernel's SYNC nothing is sent
        (the kernel sent it; the cycle runs right after it). Either way :attr:`cycles` counts it now.
        :meth:`cycle` does the same itself when this was not called since the last cycle."""
        with self._lock:
            if self.network is not None and not self._synced:
                self._sync_locked()

    def _sync_locked(self) -> None:
        self.cycles += 1
        self._synced = True
        if self._kernel_sync is not None:
            return
        try:
            self.network.sync.transmit()  # type: ignore[union-attr]
        except (can.CanError, OSError) as exc:
            self.raise_fault(0, f"bus error: {exc}")
        self._sync_at = time.monotonic()

    def cycle(self, positions: Sequence[float] | None = None) -> DriveFeedback:
        """One cycle: the SYNC (unless :meth:`sync` sent it already), then check the drives' feedback
        and send one RPDO per drive with ``positions`` (machine units, axis order; ``None`` holds), which
        the drives latch at the next SYNC. Faulted or not enabled: the SYNC only.

        SYNC first, RPDOs for the next one: the structure of the kernel's SYNC (:attr:`sync_mode`
        "kernel", where no SYNC is sent here and the cycle is best called right after one:
        :attr:`sync_tick`), with the master's SYNC at the cycle's deadline. A stall of the cycle then
        delays the SYNC only by what came before it, never by the setpoint's work; every SYNC still
        finds the RPDOs of the cycle before it (one thread sends both, in that order).

        With the SYNC process (:attr:`sync_mode` "process") the RPDOs are gathered into one set and
        handed to it for the next SYNC not yet given one, and only while its buffer has room
        (:meth:`setpoints_wanted`; ``positions`` is not taken when it is full): :attr:`last_set_tag`
        says for which SYNC."""
        now = time.monotonic()
        with self._lock:
            if self.network is None:  # not open, or shut down: nothing to send
                return self.feedback()
            if not self._synced:
                self._sync_locked()
            self._synced = False
            ks = self._kernel_sync
            if ks is not None:
                try:
                    ks.poll()
                except SyncError as exc:
                    self.raise_fault(0, f"bus error: {exc}")
            active = [d for d in self.drives if d.active]
            if active:
                if self._stream_t0 == 0.0:
                    self._stream_t0 = now
                self._check(now, active)
            timer = self._setpoints
            if timer is not None and timer.unfed:
                # SYNCs the SYNC process found no set for; counted while drives were streamed to
                if active:
                    self.missed_setpoints += timer.unfed
                timer.unfed = 0
            # with the SYNC process: only while its buffer has room (the caller runs
            # setpoints_wanted() cycles), the RPDOs gathered and pushed as one set
            send = timer is None or self.setpoints_wanted() > 0
            self.last_set_tag = 0
            try:
                self._frames = [] if timer is not None else None
                if send and self.streaming and positions is not None:
                    self._set_targets(positions)
                for d in self.drives:
                    if send and d.active and not d.homing:
                        self._cyclic(d.rpdo_id, d.cyclic_rpdo())
                self._spindle_cycle(now, send)
                frames, self._frames = self._frames, None
                if frames:
                    self._push(frames)
                if any(d.active for d in self.drives) and send:
                    # the latest SYNC (the master's: TPDO ages count to it) or, with the kernel's, when
                    # the setpoints went out
                    self._last_sent = self._sync_at if ks is None else time.monotonic()
                    if ks is not None and timer is None:
                        self._count_setpoints(ks, self._last_sent)
            except (can.CanError, OSError) as exc:
                self._frames = None
                self.raise_fault(0, f"bus error: {exc}")
            except SyncProcessError as exc:
                self._frames = None
                self.raise_fault(0, str(exc))
            return self.feedback()

    def _count_setpoints(self, ks: KernelSync, done: float) -> None:
        """Kernel SYNC: the RPDOs just sent (all out at ``done``) are for the next SYNC. Found without a
        new target: each SYNC seen more than one since the last RPDOs, and each the kernel's period made
        due before these were all out. The latter are counted now from the clock, not when the
        listener reads them: a late cycle, or one whose sending straddles a SYNC, must not pass as on
        time because the listening socket is itself behind (seen in the emulated VM: the drives counted
        up to 38 misses in 1.5 s while the SYNCs read said none)."""
        seen = ks.seen
        if self._rpdo_syncs >= 0 and seen - self._rpdo_syncs > 1:
            self.missed_setpoints += seen - self._rpdo_syncs - 1
        due = int((done - ks.last_at) / ks.period_s) if ks.last_at and self._rpdo_syncs >= 0 else 0
        self.missed_setpoints += due
        self._rpdo_syncs = max(self._rpdo_syncs, seen + due)

    def _set_targets(self, positions: Sequence[float]) -> None:
        if len(positions) != len(self.drives):
            raise ValueError(f"{len(positions)} positions for {len(self.drives)} drives")
        for d, p in zip(self.drives, positions, strict=True):
            lo, hi = d.cfg.min_position, d.cfg.max_position
            if (lo is not None and p < lo) or (hi is not None and p > hi):
                self.raise_fault(d.cfg.node_id, f"commanded position {p:g} beyond the soft limits "
                                                f"[{lo}, {hi}]")
                return
            try:
                counts = d.scale.to_counts(p)
            except OverflowError as exc:
                self.raise_fault(d.cfg.node_id, str(exc))
                return
            toward = ((NEGATIVE_LIMIT if counts < d.target else 0)
                      | (POSITIVE_LIMIT if counts > d.target else 0))
            if d.inputs & toward:
                self._limit_fault(d, d.inputs & toward, "the target moves toward it")
                return
            d.target = counts

    def feedback(self) -> DriveFeedback:
        return DriveFeedback(
            self.cycles,
            tuple(d.scale.to_units(d.actual) for d in self.drives),
            tuple(d.following_error / d.scale.scale for d in self.drives),
            tuple(cia402.decode(d.statusword) for d in self.drives),
            self.fault,
            tuple(d.inputs for d in self.drives),
        )

    @property
    def state(self) -> list[DriveState]:
        return [DriveState(d.cfg.axis, d.cfg.node_id, cia402.decode(d.statusword), d.statusword,
                           d.scale.to_units(d.actual), d.following_error / d.scale.scale, d.actual,
                           d.scale.to_units(d.target), d.inputs) for d in self.drives]

    def positions(self) -> tuple[float, ...]:
        """The commanded (held) position of every axis, machine units: where the planner resumes."""
        return tuple(d.scale.to_units(d.target) for d in self.drives)

    def __enter__(self) -> CanopenMaster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

