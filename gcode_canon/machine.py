"""What the interpreter asks the machine side, and a stand-in for running without a machine.

The interpreter yields a synchronising command (:class:`~gcode_canon.commands.WaitInput`,
:class:`~gcode_canon.commands.Probe`, a stop or a tool change) and calls the matching method when the
consumer resumes the generator, i.e. after the consumer has had the chance to execute everything
before it. The answer is stored in the parameters (#5399, #5061-#5070) or the current position.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Protocol, runtime_checkable

from gcode_canon.commands import Pose, Probe, WaitInput


@runtime_checkable
class MachineCallbacks(Protocol):
    def wait_input(self, cmd: WaitInput) -> float:
        """The value of the input (digital 0/1, analog value), or -1.0 on timeout."""
        ...

    def probe(self, cmd: Probe) -> tuple[Pose, bool]:
        """Where the probe stopped (machine coordinates, mm/deg) and whether it tripped."""
        ...

    def current_position(self) -> Pose | None:
        """The machine position (machine coordinates) at the start of a program or MDI line and
        after a stop (M0/M1/M60), a tool change or a probe move; None: where the interpreter last
        commanded it (after a probe: where the probe tripped)."""
        ...

    def print_text(self, text: str) -> None:
        """Output of (PRINT,...) comments."""
        ...


class DryRunMachine:
    """No machine: inputs read 0, a probe trips at its end point, nothing moves unexpectedly."""

    def __init__(self, print_stream=None) -> None:
        self.print_stream = print_stream

    def wait_input(self, cmd: WaitInput) -> float:
        return 0.0

    def probe(self, cmd: Probe) -> tuple[Pose, bool]:
        return cmd.end, True

    def current_position(self) -> Pose | None:
        return None

    def print_text(self, text: str) -> None:
        stream = self.print_stream if self.print_stream is not None else sys.stderr
        print(text, file=stream)


class Resume:
    """Placeholder in the interpreter's output for a line: run ``fn`` (ask the machine, store its
    answer) when the consumer asks for what follows; never handed to the consumer."""

    __slots__ = ("fn",)

    def __init__(self, fn: Callable[[], None]) -> None:
        self.fn = fn
