"""What can go wrong on the Modbus side, as values (reported to the daemon) and as exceptions."""

from __future__ import annotations

import enum
import time
from dataclasses import dataclass, field

from pymodbus.constants import ExcCodes

_EXC_TEXT = {
    ExcCodes.ILLEGAL_FUNCTION: "illegal function",
    ExcCodes.ILLEGAL_ADDRESS: "illegal data address",
    ExcCodes.ILLEGAL_VALUE: "illegal data value",
    ExcCodes.DEVICE_FAILURE: "server device failure",
    ExcCodes.ACKNOWLEDGE: "acknowledge",
    ExcCodes.DEVICE_BUSY: "server device busy",
    ExcCodes.NEGATIVE_ACKNOWLEDGE: "negative acknowledge",
    ExcCodes.MEMORY_PARITY_ERROR: "memory parity error",
    ExcCodes.GATEWAY_PATH_UNAVIABLE: "gateway path unavailable",
    ExcCodes.GATEWAY_NO_RESPONSE: "gateway target device failed to respond",
}


def exception_name(code: int) -> str:
    """``2`` -> ``"exception 2 ILLEGAL_ADDRESS (illegal data address)"``."""
    try:
        exc = ExcCodes(code)
    except ValueError:
        return f"exception {code} (not a standard Modbus exception code)"
    return f"exception {code} {exc.name} ({_EXC_TEXT.get(exc, exc.name.lower())})"


class FaultKind(enum.Enum):
    LINK_LOST = "link_lost"
    """The connection dropped or the device stopped answering (after the bounded retries)."""
    EXCEPTION = "exception"
    """The device answered a request with a Modbus exception response."""
    REJECTED = "rejected"
    """An output could not be sent at all: link down, unmapped number, value out of range."""


@dataclass(frozen=True, slots=True)
class ModbusFault:
    """One fault, as the daemon receives it (``IoExecutor.on_fault``) and telemetry reports it."""

    kind: FaultKind
    device: str
    where: str
    message: str
    table: str | None = None
    address: int | None = None
    t: float = field(default_factory=time.monotonic)

    def __str__(self) -> str:
        return f"Modbus device {self.device!r} at {self.where}: {self.message}"


class IoError(Exception):
    """A request the I/O side cannot carry out (unmapped number, value out of range, wrong mode)."""


class ModbusConnectError(IoError):
    """A device could not be reached at start; the message names it with host and port."""


class LinkDownError(IoError):
    """The link to the device holding an input or output is down (a fault has been reported)."""


class WaitAborted(IoError):
    """``wait_input`` was cancelled (program aborted, executor stopped)."""
