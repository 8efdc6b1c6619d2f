"""Online control of a running planner: feed override, adaptive feed, feed stop, hold and resume,
abort and quick stop, and the release of a sync point (LinuxCNC's motion inputs of the same names).

Each changes what the queue may do and re-plans the running segment from where it is
(:meth:`~planner.profiles.ProfilesMixin._replan`), so the setpoint stream stays continuous; an abort
drops the queue once the machine is at rest on its path. Kept apart from :mod:`planner.core`, which
feeds and samples, because these are the calls another thread's operator makes (under the cycle's lock).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from planner.segments import MAX_OVERRIDE, PlannerError


class ControlsMixin:
    """Planner state used (set by :class:`~planner.core.Planner`): the switches ``_override``,
    ``_adaptive``, ``_feed_stop``, ``_hold``, ``_abort``, ``_quick``; the queue (``_q``, ``_h``,
    ``_pending``, ``_active``) and where the machine rests (``_end``, ``_rest``, ``_pose``)."""

    _override: float
    _adaptive: float
    _feed_stop: bool
    _hold: bool
    _abort: bool
    _quick: bool
    _active: Any
    _q: list[Any]
    _h: int
    _pending: list[Any]
    _end: list[float]
    _rest: list[float]
    _v_end: float
    _last_chord: Any
    _run: Any
    _started: int
    _pose: list[float]
    _pose_index: list[int]
    _free_t: float
    _k: int
    T: float
    stats: dict[str, int]
    waiting_for: Any

    _stopping: bool  # planner.profiles (a property there)
    _recompute_all: Callable[[], None]  # planner.core
    _replan: Callable[[], None]  # planner.profiles

    def set_feed_override(self, factor: float) -> None:
        """Feed override, 0 to 2 (0 stops on the path as a hold does); takes effect smoothly.

        It scales the feed of G1/G2/G3 moves (rapids keep their speed, as in LinuxCNC, where they
        follow a separate rapid override this planner does not have; 0 stops them too). Moves queued
        while the override is switched off (M49, M50 P0) run at their programmed feed and do not
        stop at 0; the switch is the one in force when the move was fed, as LinuxCNC queues it.
        """
        if not math.isfinite(factor):
            raise PlannerError(f"feed override must be a number, got {factor!r}")
        factor = min(max(factor, 0.0), MAX_OVERRIDE)
        was_stopping = self._stopping
        self._override = factor
        if factor > 0.0:
            self._recompute_all()
        if self._stopping != was_stopping or factor > 0.0:
            self._replan()

    def set_adaptive_feed(self, factor: float) -> None:
        """Adaptive feed input, 0 to 1 (LinuxCNC's ``motion.adaptive-feed``): scales every move, rapids
        included, queued while M52 P1 is in force, on top of the feed override; 0 stops them on the
        path. Each change re-plans the queue (O(queue length)): feed it at a modest rate."""
        if not math.isfinite(factor):
            raise PlannerError(f"adaptive feed must be a number, got {factor!r}")
        factor = min(max(factor, 0.0), 1.0)
        if factor == self._adaptive:
            return
        was_stopping = self._stopping
        self._adaptive = factor
        if factor > 0.0:
            self._recompute_all()
        if self._stopping != was_stopping or factor > 0.0:
            self._replan()

    def set_feed_stop(self, on: bool) -> None:
        """Feed stop input (LinuxCNC's ``motion.feed-hold``): while on, moves queued with M53 P1 in
        force (the default) stop on the path as in a hold; M53 P0 moves ignore it. :meth:`hold` is the
        operator's pause and is not switched by M53."""
        on = bool(on)
        if on == self._feed_stop:
            return
        was_stopping = self._stopping
        self._feed_stop = on
        if self._stopping != was_stopping:
            self._replan()

    def hold(self) -> None:
        """Feed hold: a jerk-limited stop on the path; :meth:`resume` continues from there."""
        if not self._hold:
            self._hold = True
            self._replan()

    def resume(self) -> None:
        if self._hold:
            self._hold = False
            if not self._stopping:
                self._replan()

    def abort(self) -> None:
        """Jerk-limited stop on the path, then the queue is dropped."""
        self._abort = True
        self._replan()
        self._finish_abort_if_at_rest()

    def quick_stop(self) -> None:
        """Stop at each axis's quick-stop deceleration, then drop the queue as :meth:`abort` does."""
        self._abort = True
        self._quick = True
        self._replan()
        self._finish_abort_if_at_rest()

    def release(self) -> None:
        """Continue after the sync point in :attr:`waiting_for` (input read, tool changed, M0 ...)."""
        self.waiting_for = None
        self._free_t = max(self._free_t, self._k * self.T)

    def _finish_abort_if_at_rest(self) -> None:
        if self._active is None and self._abort:
            self._q.clear()
            self._h = 0
            self._pending = []
            self._abort = self._quick = self._hold = False
            self.waiting_for = None
            self._end = list(self._rest)
            self._v_end = 0.0
            self._last_chord = None  # the next line does not continue the dropped ones
            self._run = None
            self._started = self.stats["segments"]
            for i, p in enumerate(self._pose_index):
                self._pose[p] = self._rest[i]
