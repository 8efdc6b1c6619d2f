"""``canon status``: watch the machine's status and events from LCM, as a live table until Ctrl-C.

``--once`` prints one snapshot and exits; ``--json`` prints snapshots as JSON (one line each, the
form of :func:`motiond.status_view.decode_status`), with ``--once`` just one. Exit status: 0, or 3
when no snapshot arrives within ``--timeout`` with ``--once`` (the daemon is not running, or publishes
on another URL). Ctrl-C ends the watch with status 0.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from typing import TYPE_CHECKING

from motiond.cmd_spy import resolve_url
from telemetry.url import DEFAULT_URL

if TYPE_CHECKING:
    from motiond.status_view import StatusWatcher

EXIT_NO_STATUS = 3
REFRESH_S = 0.1  # the live table is redrawn at most this often (the daemon publishes at 50 Hz)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="machine.toml", help="take the URL from its [telemetry] url")
    parser.add_argument("--url", help=f"LCM URL to watch (default: [telemetry] url, else {DEFAULT_URL})")
    parser.add_argument("--once", action="store_true", help="print one snapshot and exit")
    parser.add_argument("--json", action="store_true",
                        help="print snapshots as JSON, one line each (with --once: one)")
    parser.add_argument("--timeout", type=float, default=3.0, metavar="S",
                        help="with --once: seconds to wait for a snapshot before giving up with exit "
                             "status 3 (default 3); live: when to say that none has come")
    parser.add_argument("--events", type=int, default=8, metavar="N",
                        help="how many of the last events to show (default 8)")


def _once(watcher: StatusWatcher, url: str, args: argparse.Namespace) -> int:
    from motiond.control_client import no_answer_message
    from motiond.status_view import render_status, to_json

    snap = watcher.wait_for_status(args.timeout)
    if snap is None:
        print(f"canon status: {no_answer_message('status', url, args.timeout)}", file=sys.stderr)
        return EXIT_NO_STATUS
    if args.json:
        print(to_json(snap))
    else:
        from rich.console import Console

        Console().print(render_status(snap, list(watcher.events), url=url))
    return 0


def _stream_json(watcher: StatusWatcher) -> None:
    from motiond.status_view import to_json

    seen = watcher.received
    while True:
        watcher.poll(0.2)
        if watcher.received != seen:
            seen = watcher.received
            snap = watcher.snapshot()
            if snap is not None:
                print(to_json(snap), flush=True)


def _live(watcher: StatusWatcher, url: str, timeout: float) -> None:
    from rich.console import Console
    from rich.live import Live

    from motiond.control_client import no_answer_message
    from motiond.status_view import render_status

    started = time.monotonic()

    def view() -> object:
        if watcher.snapshot() is None and time.monotonic() - started > timeout:
            waiting = no_answer_message("status", url, timeout) + "; still waiting (Ctrl-C to quit)"
        else:
            waiting = f"waiting for status on {url} (Ctrl-C to quit)"
        return render_status(watcher.snapshot(), list(watcher.events), url=url, age=watcher.age(),
                             waiting=waiting)

    with Live(view(), console=Console(), auto_refresh=False, redirect_stderr=False) as live:
        next_draw = time.monotonic() + REFRESH_S
        while True:
            watcher.poll(max(0.001, next_draw - time.monotonic()))
            if time.monotonic() >= next_draw:
                live.update(view(), refresh=True)
                next_draw = time.monotonic() + REFRESH_S


def run(args: argparse.Namespace) -> int:
    from motiond.cli import UserError
    from motiond.control_client import client_lcm
    from motiond.status_view import StatusWatcher
    from telemetry.publisher import TelemetryUnavailable

    if not (math.isfinite(args.timeout) and args.timeout > 0):
        raise UserError(f"--timeout must be a number of seconds > 0, got {args.timeout:g}")
    if not 0 <= args.events <= 1000:
        raise UserError(f"--events must be between 0 and 1000, got {args.events}")
    url = resolve_url(args)
    try:
        lc = client_lcm(url)
    except TelemetryUnavailable as exc:
        raise UserError(str(exc)) from None
    with StatusWatcher(lc, max_events=args.events) as watcher:
        if args.once:
            return _once(watcher, url, args)
        try:
            if args.json:
                _stream_json(watcher)
            else:
                _live(watcher, url, args.timeout)
        except KeyboardInterrupt:
            return 0  # Ctrl-C is how a watch ends
    return 0
