"""One background thread per telemetry object: start, stop, and use as a context manager.

The status publisher, the event publisher and the command server each own one daemon thread that
runs ``_run`` until ``_stop`` is set; this base holds that life cycle once.
"""

from __future__ import annotations

import threading
from typing import Self


class Worker:
    """Owns one daemon thread running ``self._run()`` until ``self._stop`` is set."""

    thread_name = "canon-worker"

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _run(self) -> None:  # pragma: no cover - every subclass defines it
        raise NotImplementedError

    def _start_thread(self) -> None:
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
            self._thread.start()

    def start(self) -> Self:
        self._start_thread()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        """Ask the thread to end and wait up to ``timeout`` seconds for it."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
