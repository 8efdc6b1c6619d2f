"""The machine's status as ``canon status`` shows it: decoded to plain data, and rendered with rich.

* :func:`decode_status` turns a ``canon.status`` (the message or its bytes) into a dict that
  ``json.dumps`` takes: the LCM field names, except that the per-axis arrays become one ``axes`` list
  of dicts and each drive gets ``statusword_hex``. :func:`decode_event` does the same for
  ``canon.event`` (with the severity's name).
* :func:`render_status` makes one rich renderable of a decoded snapshot and the last events, for a
  terminal (``rich.live``) or a recording console in tests.
* :class:`StatusWatcher` subscribes to ``CANON_STATUS`` and ``CANON_EVENT`` on an LCM instance and
  keeps the latest snapshot and the last few events; the caller handles LCM through :meth:`poll`.

Decoding happens when a snapshot is asked for, not at each of the 50 messages a second.
"""

from __future__ import annotations

import collections
import json
import math
import time
from collections.abc import Sequence
from datetime import datetime
from typing import Any

from telemetry.publisher import CANON_EVENT, CANON_STATUS

__all__ = ["SEVERITIES", "StatusWatcher", "decode_event", "decode_status", "render_status", "to_json"]

SEVERITIES = ("DEBUG", "INFO", "WARNING", "ERROR", "FATAL")
_SEVERITY_STYLE = {"DEBUG": "dim", "INFO": "", "WARNING": "yellow", "ERROR": "bold red", "FATAL": "bold red"}
_STATE_STYLE = {"idle": "green", "running": "bold green", "paused": "yellow", "homing": "cyan",
                "jogging": "cyan", "estop": "bold white on red", "fault": "bold red", "disabled": "dim"}
_CIA402_STYLE = {"operation_enabled": "green", "fault": "bold red", "fault_reaction_active": "bold red",
                 "quick_stop_active": "yellow", "switch_on_disabled": "dim"}
_NMT_SHORT = {"OPERATIONAL": "OP", "PRE-OPERATIONAL": "PRE-OP", "INITIALISING": "INIT"}
STALE_AFTER_S = 1.0  # a snapshot older than this is flagged: the daemon may have stopped


# ---- decoding ------------------------------------------------------------------------------------

_EXTENSION_OFF = frozenset({"G15", "G50", "G69", "G23"})  # the gcode-canon transform groups at rest


def status_gcodes(codes: Sequence[str], dialect: Any) -> tuple[str, ...]:
    """The active G codes as the status shows them in ``dialect`` (a ``gcode_canon.dialect.Dialect``).

    In the gcode-canon dialect, every group as the interpreter lists it. In the LinuxCNC dialect (and
    Grbl's), what LinuxCNC would show: no lathe radius mode G8 (LinuxCNC reports the lathe group on a
    lathe only; G7 stays, a program asked for it), and the gcode-canon transform groups (polar,
    scaling, rotation, mirroring: codes LinuxCNC does not know) only while a program has one on.
    """
    from gcode_canon.dialect import Dialect

    if dialect is Dialect.GCODE_CANON:
        return tuple(codes)
    return tuple(c for c in codes if c != "G8" and c not in _EXTENSION_OFF)


def _as_status(msg: Any) -> Any:
    if isinstance(msg, bytes | bytearray | memoryview):
        from telemetry.lcmtypes.canon import status

        return status.decode(bytes(msg))
    return msg


def _drive(d: Any) -> dict[str, Any]:
    return {
        "axis": d.axis, "node_id": int(d.node_id), "nmt_state": d.nmt_state,
        "heartbeat_ok": bool(d.heartbeat_ok), "statusword": int(d.statusword),
        "statusword_hex": f"0x{int(d.statusword) & 0xFFFF:04X}", "cia402_state": d.cia402_state,
        "mode_display": int(d.mode_display), "position_actual": int(d.position_actual),
        "following_error": int(d.following_error), "emcy_code": int(d.emcy_code), "error": d.error,
    }


def decode_status(msg: Any) -> dict[str, Any]:
    """A ``canon.status`` (decoded message or its encoded bytes) as a JSON-ready dict."""
    s = _as_status(msg)
    n = int(s.num_axes)
    axes = [{"name": s.axis_names[i], "homed": bool(s.homed[i]), "commanded": float(s.commanded[i]),
             "actual": float(s.actual[i]), "following_error": float(s.following_error[i]),
             "velocity": float(s.velocity[i])}
            for i in range(n)]
    return {
        "utime": int(s.utime), "seq": int(s.seq), "machine": s.machine,
        "state": s.state, "mode": s.mode, "estop": bool(s.estop), "enabled": bool(s.enabled),
        "program": s.program, "line": int(s.line), "block": s.block,
        "single_block": bool(s.single_block), "optional_stop": bool(s.optional_stop),
        "block_delete": bool(s.block_delete),
        "axes": axes,
        "path_velocity": float(s.path_velocity), "feed_rate": float(s.feed_rate),
        "feed_override": float(s.feed_override), "rapid_override": float(s.rapid_override),
        "spindle_override": float(s.spindle_override),
        "drives": [_drive(d) for d in s.drives[:int(s.num_drives)]],
        "gcodes": list(s.gcodes[:int(s.num_gcodes)]), "mcodes": list(s.mcodes[:int(s.num_mcodes)]),
        "tool": int(s.tool), "tool_prepared": int(s.tool_prepared),
        "tool_length_offset": float(s.tool_length_offset),
        "spindle_direction": int(s.spindle_direction), "spindle_speed": float(s.spindle_speed),
        "mist": bool(s.mist), "flood": bool(s.flood),
        "io_ok": bool(s.io_ok),
        "digital_inputs": [bool(b) for b in s.digital_inputs[:int(s.num_digital_inputs)]],
        "digital_outputs": [bool(b) for b in s.digital_outputs[:int(s.num_digital_outputs)]],
        "analog_inputs": [float(v) for v in s.analog_inputs[:int(s.num_analog_inputs)]],
        "analog_outputs": [float(v) for v in s.analog_outputs[:int(s.num_analog_outputs)]],
        "last_error": s.last_error, "last_error_utime": int(s.last_error_utime),
        "events_dropped": int(s.events_dropped),
    }


def decode_event(msg: Any) -> dict[str, Any]:
    """A ``canon.event`` (decoded message or its bytes) as a JSON-ready dict, severity by name."""
    if isinstance(msg, bytes | bytearray | memoryview):
        from telemetry.lcmtypes.canon import event

        msg = event.decode(bytes(msg))
    sev = int(msg.severity)
    return {"utime": int(msg.utime), "seq": int(msg.seq),
            "severity": SEVERITIES[sev] if 0 <= sev < len(SEVERITIES) else str(sev),
            "kind": msg.kind, "source": msg.source, "file": msg.file, "line": int(msg.line), "text": msg.text}


def _json_safe(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None  # JSON has no NaN or infinity
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_json_safe(v) for v in value]
    return value


def to_json(data: dict[str, Any]) -> str:
    """``data`` as one line of strict JSON (a NaN or infinite number becomes null)."""
    return json.dumps(_json_safe(data), allow_nan=False)


# ---- rendering -----------------------------------------------------------------------------------

def _clock(utime: int) -> str:
    if utime <= 0:
        return "-"
    return datetime.fromtimestamp(utime / 1e6).strftime("%H:%M:%S.%f")[:-3]


def _yes(flag: bool, on: str = "on", off: str = "off") -> str:
    return on if flag else off


def _bits(bits: Sequence[bool]) -> str:
    """``0:1 1:0 ...``: index first, so that the bit of M64 P5 is easy to find."""
    if not bits:
        return "-"
    return " ".join(f"{i}:{int(b)}" for i, b in enumerate(bits))


def _numbers(values: Sequence[float]) -> str:
    return " ".join(f"{i}:{v:g}" for i, v in enumerate(values)) if values else "-"


def _percent(factor: float) -> str:
    return f"{factor * 100:.0f} %" if math.isfinite(factor) else str(factor)


def render_status(snapshot: dict[str, Any] | None, events: Sequence[dict[str, Any]] = (), *,
                  url: str = "", age: float | None = None, waiting: str = "") -> Any:
    """One rich renderable: the snapshot's tables and the last ``events`` below them.

    ``snapshot`` None shows ``waiting`` (e.g. "waiting for status on URL"). ``age`` (seconds since
    the snapshot arrived) above :data:`STALE_AFTER_S` adds a warning that the daemon may have stopped.
    """
    from rich import box
    from rich.console import Group
    from rich.table import Table
    from rich.text import Text

    parts: list[Any] = []
    if snapshot is None:
        parts.append(Text(waiting or f"waiting for {CANON_STATUS}" + (f" on {url}" if url else ""),
                          style="yellow"))
    else:
        s = snapshot
        head = Table.grid(padding=(0, 2))
        for _ in range(4):
            head.add_column()
        state = Text(s["state"] or "?", style=_STATE_STYLE.get(s["state"], ""))
        head.add_row("machine", Text(s["machine"] or "-", style="bold"), "state", state)
        head.add_row("mode", s["mode"] or "-", "estop",
                     Text("ACTIVE", style="bold red") if s["estop"] else "off")
        head.add_row("drives", _yes(s["enabled"], "enabled", "disabled"), "seq", str(s["seq"]))
        program = f"{s['program']}:{s['line']}" if s["program"] else "-"
        head.add_row("program", program, "time", _clock(s["utime"]))
        if s["block"]:
            head.add_row("block", s["block"], "", "")
        head.add_row("single block", _yes(s["single_block"]), "optional stop", _yes(s["optional_stop"]))
        parts.append(head)

        axes = Table(title="axes", title_justify="left", box=box.SIMPLE_HEAD)
        for col in ("axis", "homed", "commanded", "actual", "following error", "velocity"):
            axes.add_column(col, justify="left" if col in ("axis", "homed") else "right")
        for a in s["axes"]:
            axes.add_row(a["name"], _yes(a["homed"], "yes", "no"), f"{a['commanded']:.4f}",
                         f"{a['actual']:.4f}", f"{a['following_error']:.4f}", f"{a['velocity']:.3f}")
        parts.append(axes)

        if s["drives"]:
            drives = Table(title="drives (CiA 402)", title_justify="left", box=box.SIMPLE_HEAD)
            for col in ("axis", "node", "NMT", "HB", "state", "statusword", "mode", "EMCY"):
                drives.add_column(col, no_wrap=True)
            for d in s["drives"]:
                nmt = _NMT_SHORT.get(d["nmt_state"], d["nmt_state"] or "-")
                drives.add_row(d["axis"], str(d["node_id"]), nmt,
                               Text("ok") if d["heartbeat_ok"] else Text("LOST", style="bold red"),
                               Text(d["cia402_state"] or "-", style=_CIA402_STYLE.get(d["cia402_state"], "")),
                               d["statusword_hex"], str(d["mode_display"]),
                               f"0x{d['emcy_code'] & 0xFFFF:04X}" if d["emcy_code"] else "-")
            parts.append(drives)
            for d in s["drives"]:
                if d["error"]:
                    parts.append(Text(f"drive {d['axis']} (node {d['node_id']}): {d['error']}", style="red"))

        machine = Table.grid(padding=(0, 2))
        for _ in range(4):
            machine.add_column()
        machine.add_row("feed", f"F{s['feed_rate']:g}  path {s['path_velocity']:.3f}/s",
                        "feed override", _percent(s["feed_override"]))
        machine.add_row("rapid override", _percent(s["rapid_override"]),
                        "spindle override", _percent(s["spindle_override"]))
        direction = {1: "M3 cw", -1: "M4 ccw"}.get(s["spindle_direction"], "M5 stopped")
        machine.add_row("spindle", f"{direction}  S{s['spindle_speed']:g}",
                        "coolant", f"mist {_yes(s['mist'])}, flood {_yes(s['flood'])}")
        machine.add_row("tool", f"T{s['tool']} (prepared T{s['tool_prepared']})",
                        "length offset", f"{s['tool_length_offset']:g}")
        machine.add_row("G codes", " ".join(s["gcodes"]) or "-", "M codes", " ".join(s["mcodes"]) or "-")
        machine.add_row("I/O", Text("ok", style="green") if s["io_ok"] else Text("FAULT", style="bold red"),
                        "", "")
        machine.add_row("digital in", _bits(s["digital_inputs"]), "digital out", _bits(s["digital_outputs"]))
        machine.add_row("analog in", _numbers(s["analog_inputs"]),
                        "analog out", _numbers(s["analog_outputs"]))
        parts.append(machine)

        if s["last_error"]:
            when = f" ({_clock(s['last_error_utime'])})" if s["last_error_utime"] > 0 else ""
            parts.append(Text(f"last error{when}: {s['last_error']}", style="bold red"))
        if s["events_dropped"]:
            parts.append(Text(f"{s['events_dropped']} events dropped by the daemon", style="yellow"))
        if age is not None and age > STALE_AFTER_S:
            parts.append(Text(f"no status for {age:.1f} s: the daemon may have stopped"
                              + (f" (listening on {url})" if url else ""), style="bold yellow"))

    if events:
        table = Table(title="events", title_justify="left", box=box.SIMPLE_HEAD)
        for col in ("time", "severity", "source", "kind", "where", "text"):
            table.add_column(col)
        for e in events:
            where = f"{e['file']}:{e['line']}" if e["file"] else (str(e["line"]) if e["line"] else "")
            severity = Text(e["severity"], style=_SEVERITY_STYLE.get(e["severity"], ""))
            table.add_row(_clock(e["utime"]), severity, e["source"], e["kind"], where, e["text"])
        parts.append(table)
    return Group(*parts)


# ---- watching ------------------------------------------------------------------------------------

class StatusWatcher:
    """Keeps the latest ``canon.status`` and the last ``max_events`` events seen on ``lc``.

    Call :meth:`poll` to handle LCM traffic (it is the only place ``lc`` is handled); messages that
    do not decode as our types are counted in ``bad_messages`` and ignored.
    """

    def __init__(self, lc: Any, *, max_events: int = 8, status_channel: str = CANON_STATUS,
                 event_channel: str = CANON_EVENT) -> None:
        self.lc = lc
        self.received = 0
        self.bad_messages = 0
        self.events: collections.deque[dict[str, Any]] = collections.deque(maxlen=max_events)
        self._latest: Any = None
        self._latest_dict: dict[str, Any] | None = None
        self._received_at: float | None = None
        self._subs = [lc.subscribe(status_channel, self._on_status),
                      lc.subscribe(event_channel, self._on_event)]

    def _on_status(self, _channel: str, data: bytes) -> None:
        from telemetry.lcmtypes.canon import status

        try:
            msg = status.decode(data)
        except Exception:
            self.bad_messages += 1
            return
        self._latest, self._latest_dict = msg, None
        self._received_at = time.monotonic()
        self.received += 1

    def _on_event(self, _channel: str, data: bytes) -> None:
        try:
            self.events.append(decode_event(data))
        except Exception:
            self.bad_messages += 1

    def poll(self, timeout: float) -> None:
        """Handle LCM traffic for up to ``timeout`` seconds (returns early after a message)."""
        from motiond.control_client import handle_one

        handle_one(self.lc, timeout)

    def wait_for_status(self, timeout: float) -> dict[str, Any] | None:
        """The first snapshot arriving within ``timeout`` seconds (or one already here), else None."""
        deadline = time.monotonic() + timeout
        while self._latest is None:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            self.poll(min(left, 0.1))
        return self.snapshot()

    def snapshot(self) -> dict[str, Any] | None:
        """The latest snapshot decoded (None before the first)."""
        if self._latest is not None and self._latest_dict is None:
            self._latest_dict = decode_status(self._latest)
        return self._latest_dict

    def age(self) -> float | None:
        """Seconds since the latest snapshot arrived (None before the first)."""
        return None if self._received_at is None else time.monotonic() - self._received_at

    def close(self) -> None:
        for sub in self._subs:
            self.lc.unsubscribe(sub)
        self._subs = []

    def __enter__(self) -> StatusWatcher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
