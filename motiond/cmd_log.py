"""``canon log FILE [--url URL]``: record canon's LCM traffic into an LCM log file with lcm-logger.

The file is an ordinary LCM event log: ``lcm-logplayer --lcm-url=URL FILE`` publishes it again with
the original timing, and ``canon spy --url URL`` shows the replayed run as it showed the live one;
``lcm.EventLog(FILE)`` reads it from Python. Recording stops on Ctrl-C, or after ``--duration``.
"""

from __future__ import annotations

import argparse
import collections
import signal
import subprocess
import sys
from pathlib import Path

from motiond.cmd_spy import resolve_url
from telemetry.url import DEFAULT_URL

MAX_SUMMARY_BYTES = 200_000_000  # larger logs are not read back for the summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE", help="LCM log file to write")
    parser.add_argument("--config", metavar="machine.toml", help="take the URL from its [telemetry] url")
    parser.add_argument("--url", help=f"LCM URL to record (default: [telemetry] url, else {DEFAULT_URL})")
    parser.add_argument("--channels", default=".*", metavar="REGEX",
                        help="record the channels matching this regular expression (default: all; "
                             "'CANON_.*' for canon's own)")
    parser.add_argument("--duration", type=float, metavar="SECONDS",
                        help="stop after this many seconds (default: at Ctrl-C)")
    parser.add_argument("-f", "--force", action="store_true", help="overwrite FILE if it exists")


def _stop(proc: subprocess.Popen[bytes]) -> None:
    """Ask lcm-logger to finish (SIGINT: it flushes and closes the log), kill it if it will not."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=5)


def summarize(path: Path) -> str:
    """``N messages (CHANNEL n, ...)`` for a log file, read with lcm.EventLog."""
    import lcm

    if path.stat().st_size > MAX_SUMMARY_BYTES:
        return f"{path.stat().st_size} bytes"
    counts: collections.Counter[str] = collections.Counter()
    log = lcm.EventLog(str(path), "r")
    try:
        for event in log:
            counts[event.channel] += 1
    finally:
        log.close()
    detail = ", ".join(f"{ch} {n}" for ch, n in sorted(counts.items()))
    return f"{sum(counts.values())} messages" + (f" ({detail})" if detail else "")


def run(args: argparse.Namespace) -> int:
    from motiond.cli import UserError
    from telemetry.generate import GenerateError, lcm_tool
    from telemetry.publisher import TelemetryUnavailable, preflight

    path = Path(args.file)
    try:
        parsed = preflight(resolve_url(args))
        logger = lcm_tool("lcm-logger")
    except (TelemetryUnavailable, GenerateError) as exc:
        raise UserError(str(exc)) from None
    if args.duration is not None and not args.duration > 0:
        raise UserError(f"--duration must be > 0, got {args.duration}")
    if path.is_dir():
        raise UserError(f"{path}: is a directory")
    if not path.parent.is_dir():
        raise UserError(f"{path}: directory {path.parent} does not exist")
    if path.exists() and not args.force:
        raise UserError(f"{path}: exists (use --force to overwrite it)")

    cmd = [str(logger), "--quiet", f"--lcm-url={parsed.url}", f"--channel={args.channels}"]
    if args.force:
        cmd.append("--force")
    cmd.append(str(path))
    print(f"recording {parsed.url} into {path}"
          + (f" for {args.duration:g} s" if args.duration else "; Ctrl-C stops"), file=sys.stderr)
    proc = subprocess.Popen(cmd)
    stopped = False
    try:
        proc.wait(timeout=args.duration)
    except subprocess.TimeoutExpired:
        stopped = True
    except KeyboardInterrupt:
        stopped = True  # the terminal sent SIGINT to lcm-logger too
    finally:
        _stop(proc)
    if not stopped and proc.returncode != 0:
        raise UserError(f"lcm-logger failed (exit status {proc.returncode}): {' '.join(cmd)}")
    if not path.exists():
        raise UserError(f"{path}: lcm-logger wrote no file")
    print(f"{path}: {summarize(path)}", file=sys.stderr)
    print(f"replay: lcm-logplayer --lcm-url='{parsed.url}' {path}   (watch: canon spy --url '{parsed.url}')",
          file=sys.stderr)
    return 0
