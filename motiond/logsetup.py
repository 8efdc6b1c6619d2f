"""Logging for the ``canon`` command: canon's own messages at INFO, the libraries' at WARNING.

``-v`` adds canon's debug messages, ``-vv`` the libraries' too (pymodbus, canopen, python-can, lcm).
pymodbus appends a hex dump of the last 20 frames to each of its error messages when its debug
logging is off; those dumps bury the fault reason, so they are cut off below ``-vv`` (the message's
first line stays).
"""

from __future__ import annotations

import logging

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


def setup_logging(verbose: int) -> None:
    """Levels by ``-v`` count; one stderr handler on the root logger (added once)."""
    root = logging.getLogger()
    handler = next((h for h in root.handlers if getattr(h, "_canon", False)), None)
    if handler is None:
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter(FORMAT))
        handler._canon = True  # type: ignore[attr-defined]
        handler.addFilter(FrameDumpFilter())
        root.addHandler(handler)
    for f in handler.filters:
        if isinstance(f, FrameDumpFilter):
            f.active = verbose < 2
    root.setLevel(logging.DEBUG if verbose >= 2 else logging.WARNING)
    for name in CANON:
        logging.getLogger(name).setLevel(logging.DEBUG if verbose >= 1 else logging.INFO)
    for name in LIBRARIES:
        logging.getLogger(name).setLevel(logging.DEBUG if verbose >= 2 else logging.WARNING)
