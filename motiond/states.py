"""The machine's operating states and the rules for moving between them.

A serious controller refuses a command that does not fit the state it is in, and says why, rather
than queueing it: a ``run`` while faulted, a ``jog`` while a program runs, anything that moves before
the drives are enabled. This module holds only those rules (no I/O), so the daemon, its tests and its
status publisher agree on them.

States::

    ESTOP --estop_reset--> IDLE (drives disabled) --enable--> IDLE (enabled)
    IDLE --run/mdi--> RUNNING --pause--> PAUSED --resume--> RUNNING
    RUNNING/PAUSED --abort or program end--> IDLE
    any --fault--> FAULTED --reset--> IDLE (drives disabled: re-enable explicitly)
    any --estop--> ESTOP (drives disabled)

Starting in ESTOP is what LinuxCNC and every drive safety chain do: power-up never moves a machine.
"""

from __future__ import annotations

import enum
import threading
from collections.abc import Callable
from dataclasses import dataclass, field


class State(enum.Enum):
    ESTOP = "estop"
    IDLE = "idle"
    RUNNING = "running"
    PAUSED = "paused"
    FAULTED = "faulted"


class Mode(enum.Enum):
    MANUAL = "manual"  # jog, home
    AUTO = "auto"  # a program file
    MDI = "mdi"  # single lines typed by the operator


class CommandRefused(Exception):
    """The command does not fit the current state; the message says why."""


@dataclass(frozen=True)
class Snapshot:
    state: State
    mode: Mode
    enabled: bool
    fault: str
    """Reason of the last fault (empty when none since the last reset)."""


Listener = Callable[[Snapshot, Snapshot], None]


@dataclass
class MachineStates:
    """Thread-safe holder of the state, applying the transition rules above.

    Every method either performs the transition and returns the new :class:`Snapshot`, or raises
    :class:`CommandRefused` and changes nothing. Listeners are called after each change (outside
    the lock) with the old and new snapshot, for events and telemetry.
    """

    state: State = State.ESTOP
    mode: Mode = Mode.MANUAL
    enabled: bool = False
    fault_reason: str = ""
    _lock: threading.RLock = field(default_factory=threading.RLock, repr=False)
    _listeners: list[Listener] = field(default_factory=list, repr=False)

    def snapshot(self) -> Snapshot:
        with self._lock:
            return Snapshot(self.state, self.mode, self.enabled, self.fault_reason)

    def subscribe(self, listener: Listener) -> None:
        self._listeners.append(listener)

    def _change(self, **changes: object) -> Snapshot:
        with self._lock:
            before = self.snapshot()
            for name, value in changes.items():
                setattr(self, name, value)
            after = self.snapshot()
        if after != before:
            for listener in list(self._listeners):
                listener(before, after)
        return after

    def _require(self, allowed: tuple[State, ...], what: str) -> None:
        if self.state not in allowed:
            names = " or ".join(s.value for s in allowed)
            detail = f" ({self.fault_reason})" if self.state is State.FAULTED and self.fault_reason else ""
            raise CommandRefused(f"cannot {what} while {self.state.value}{detail}: needs {names}")

    def _require_enabled(self, what: str) -> None:
        if not self.enabled:
            raise CommandRefused(f"cannot {what}: drives are disabled (send 'enable' first)")

    # --- operator commands --------------------------------------------------------------------

    def estop(self) -> Snapshot:
        """Always accepted, from any state."""
        return self._change(state=State.ESTOP, enabled=False, mode=Mode.MANUAL)

    def estop_reset(self) -> Snapshot:
        with self._lock:
            self._require((State.ESTOP,), "reset the estop")
            return self._change(state=State.IDLE, enabled=False, fault_reason="")

    def enable(self) -> Snapshot:
        with self._lock:
            self._require((State.IDLE,), "enable the drives")
            return self._change(enabled=True)

    def disable(self) -> Snapshot:
        with self._lock:
            self._require((State.IDLE, State.FAULTED), "disable the drives")
            return self._change(enabled=False)

    def start(self, mode: Mode) -> Snapshot:
        """``run`` (AUTO) or ``mdi`` (MDI): from IDLE with the drives enabled."""
        if mode is Mode.MANUAL:
            raise ValueError("start() is for AUTO or MDI; use manual() for jog and home")
        with self._lock:
            self._require((State.IDLE,), f"start {'a program' if mode is Mode.AUTO else 'an MDI line'}")
            self._require_enabled("start")
            return self._change(state=State.RUNNING, mode=mode)

    def manual(self, what: str) -> Snapshot:
        """Check that a jog or a home may start (IDLE, enabled); the state stays IDLE."""
        with self._lock:
            self._require((State.IDLE,), what)
            self._require_enabled(what)
            return self._change(mode=Mode.MANUAL)

    def pause(self) -> Snapshot:
        with self._lock:
            self._require((State.RUNNING,), "pause")
            return self._change(state=State.PAUSED)

    def resume(self) -> Snapshot:
        with self._lock:
            self._require((State.PAUSED,), "resume")
            return self._change(state=State.RUNNING)

    def abort(self) -> Snapshot:
        """Stop the program: RUNNING or PAUSED back to IDLE (IDLE stays IDLE)."""
        with self._lock:
            self._require((State.RUNNING, State.PAUSED, State.IDLE), "abort")
            return self._change(state=State.IDLE)

    def finished(self) -> Snapshot:
        """The program or MDI line ended normally."""
        with self._lock:
            if self.state in (State.RUNNING, State.PAUSED):
                return self._change(state=State.IDLE)
            return self.snapshot()

    def fault(self, reason: str) -> Snapshot:
        """Any layer reports a fault: motion has been stopped by the caller; ESTOP stays ESTOP."""
        with self._lock:
            if self.state is State.ESTOP:
                return self._change(fault_reason=reason)
            return self._change(state=State.FAULTED, enabled=False, fault_reason=reason)

    def reset(self) -> Snapshot:
        """Acknowledge a fault: FAULTED to IDLE with the drives disabled."""
        with self._lock:
            self._require((State.FAULTED,), "reset")
            return self._change(state=State.IDLE, enabled=False, fault_reason="")

    @property
    def may_move(self) -> bool:
        with self._lock:
            return self.enabled and self.state in (State.IDLE, State.RUNNING, State.PAUSED)
