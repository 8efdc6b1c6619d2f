"""Logging for the ``canon`` command: canon's own messages at INFO, the libraries' at WARNING.

``-v`` adds canon's debug messages, ``-vv`` the libraries' too (pymodbus, canopen, python-can, lcm).
pymodbus appends a hex dump of the last 20 frames to each of its error messages when its debug
logging is off; those dumps bury the fault reason, so they are cut off below ``-vv`` (the message's
first line stays).
"""

from __future__ import annotations

import logging
import sys
from typing import Any

CANON = ("gcode_canon", "planner", "fieldbus", "telemetry", "motiond")
LIBRARIES = ("pymodbus", "canopen", "can", "lcm")
FORMAT = "%(levelname)s %(name)s: %(message)s"


class FrameDumpFilter(logging.Filter):
    """Cuts pymodbus's frame dump (``\\n>>>>> send: 0x..``) off its records' messages."""

    MARK = "\n>>>>> "

    def __init__(self) -> None:
        super().__init__()
        self.active = True

    def filter(self, record: logging.LogRecord) -> bool:
        if not self.active or not record.name.startswith("pymodbus"):
            return True
        message = record.getMessage()
        cut = message.find(self.MARK)
        if cut >= 0:
            record.msg = message[:cut]
            record.args = None
        return True


class _Stderr(logging.StreamHandler):  # type: ignore[type-arg]
    """Writes to whatever ``sys.stderr`` is at the time (it may be replaced after set-up)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property  # type: ignore[override]
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, _value: Any) -> None:
        pass


def setup_logging(verbose: int) -> None:
    """Levels by ``-v`` count; one stderr handler on the root logger (added once)."""
    root = logging.getLogger()
    handler = next((h for h in root.handlers if isinstance(h, _Stderr)), None)
    if handler is None and not root.handlers:  # as basicConfig: an embedding program's handlers stay
        handler = _Stderr()
        handler.setFormatter(logging.Formatter(FORMAT))
        root.addHandler(handler)
    for h in root.handlers:
        f = next((f for f in h.filters if isinstance(f, FrameDumpFilter)), None)
        if f is None:
            f = FrameDumpFilter()
            h.addFilter(f)
        f.active = verbose < 2
    root.setLevel(logging.DEBUG if verbose >= 2 else logging.WARNING)
    for name in CANON:
        logging.getLogger(name).setLevel(logging.DEBUG if verbose >= 1 else logging.INFO)
    for name in LIBRARIES:
        logging.getLogger(name).setLevel(logging.DEBUG if verbose >= 2 else logging.WARNING)
    # canon's master reports a failed SDO itself (node, object, what it is for); the library's own line
    # for an attempt that a retry then saved is noise on a loaded machine
    logging.getLogger("canopen.sdo.client").setLevel(logging.NOTSET if verbose else logging.CRITICAL)
