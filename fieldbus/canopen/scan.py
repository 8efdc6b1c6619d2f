"""Read what each configured drive says about itself, against the configuration: ``canon drives scan``.

Read only: SDO uploads of identity, names, supported modes, limits, the digital inputs (0x60FD: the
limit and home switches canon watches), the touch probe (0x60B8-0x60BB) and the presence of the
objects boot would write; no NMT, no SDO download, so a scan never changes a drive. The comparison is
the master's own (:mod:`fieldbus.canopen.commissioning`), so a scan with no mismatch means the boot will
accept the drive.
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass, field
from typing import Any

import canopen
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from fieldbus.canopen import touch_probe
from fieldbus.canopen.commissioning import LIMIT_OBJECTS, boot_writes, limit_problems, optional_objects
from fieldbus.canopen.config import CanopenConfig, DriveConfig

log = logging.getLogger(__name__)

_NO_SUCH_OBJECT = (0x06020000, 0x06090011)
IDENTITY = ((1, "vendor id"), (2, "product code"), (3, "revision number"), (4, "serial number"))
NAMES = ((0x1008, "device name"), (0x1009, "hardware version"), (0x100A, "software version"))
#: objects the cycle itself needs (beyond what boot writes)
CYCLIC = ((0x6040, 0), (0x6041, 0), (0x6061, 0), (0x6064, 0), (0x607A, 0), (0x60F4, 0))


@dataclass
class DriveScan:
    """One drive: what it said (``None``: it lacks the object) and what does not fit the configuration."""

    axis: str
    node: int
    answered: bool = False
    identity: dict[str, int | None] = field(default_factory=dict)
    expected: dict[str, int | None] = field(default_factory=dict)
    names: dict[str, str | None] = field(default_factory=dict)
    limits: dict[tuple[int, int], int | None] = field(default_factory=dict)
    optional_absent: list[int] = field(default_factory=list)
    #: 0x60FD now (None: the drive has no digital inputs object)
    digital_inputs: int | None = None
    #: the touch probes (1, 2) whose objects (function, status, both latched positions) the drive has
    touch_probes: list[int] = field(default_factory=list)
    mismatches: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {"axis": self.axis, "node": self.node, "answered": self.answered, "identity": self.identity,
                "expected_identity": self.expected, "names": self.names,
                "limits": {f"0x{i:04X}:{s:02X}": v for (i, s), v in self.limits.items()},
                "optional_absent": [f"0x{i:04X}" for i in self.optional_absent],
                "digital_inputs": self.digital_inputs, "touch_probes": self.touch_probes,
                "mismatches": self.mismatches, "notes": self.notes}


class _Absent(Exception):
    pass


def _upload(node: canopen.RemoteNode, index: int, sub: int) -> bytes:
    try:
        return node.sdo.upload(index, sub)
    except SdoAbortedError as exc:
        if exc.code in _NO_SUCH_OBJECT:
            raise _Absent from None
        raise


def _number(node: canopen.RemoteNode, index: int, sub: int, fmt: str) -> int | None:
    try:
        raw = _upload(node, index, sub)
    except _Absent:
        return None
    return struct.unpack_from("<" + fmt, raw.ljust(struct.calcsize(fmt), b"\0"))[0]


def scan_drive(conf: CanopenConfig, cfg: DriveConfig, node: canopen.RemoteNode) -> DriveScan:
    out = DriveScan(cfg.axis, cfg.node_id)
    try:
        out.identity = {name: _number(node, 0x1018, sub, "I") for sub, name in IDENTITY}
    except SdoCommunicationError:
        out.mismatches.append("no SDO answer: drive off, wrong node id or bitrate?")
        return out
    except SdoAbortedError as exc:
        out.mismatches.append(f"identity 0x1018 refused: SDO abort 0x{exc.code:08X}")
        return out
    out.answered = True
    od = node.object_dictionary
    for sub, name, want in ((1, "vendor id", cfg.vendor_id), (2, "product code", cfg.product_code)):
        source = "the configuration" if want is not None else "the EDS"
        if want is None:
            try:
                want = od[0x1018][sub].default
            except KeyError:
                want = None
        out.expected[name] = want
        got = out.identity.get(name)
        if want is not None and got is not None and got != want:
            out.mismatches.append(f"identity 0x1018:{sub:02X} {name} is 0x{got:08X}, {source} expects "
                                  f"0x{want:08X}")
    for index, name in NAMES:
        try:
            out.names[name] = _upload(node, index, 0).rstrip(b"\0").decode("latin-1").strip()
        except (_Absent, SdoAbortedError):
            out.names[name] = None
    for index, sub, fmt, _what in LIMIT_OBJECTS:
        out.limits[(index, sub)] = _number(node, index, sub, fmt)
    problems, notes = limit_problems(cfg, out.limits)
    out.mismatches += problems
    out.notes += notes
    _inputs_and_probe(cfg, node, out)
    optional = optional_objects(conf.pdo_layout)
    seen: set[tuple[int, int]] = set()
    checks = [(index, sub, what) for what, index, sub, _f, _v in boot_writes(conf, cfg)]
    checks += [(index, sub, "used by the cycle") for index, sub in CYCLIC]
    checks += [(index, sub, where) for index, sub, _c, _v, where in cfg.sdo]
    for index, sub, what in checks:
        if (index, sub) in seen:
            continue
        seen.add((index, sub))
        try:
            _upload(node, index, sub)
        except _Absent:
            if index in optional:
                if index not in out.optional_absent:
                    out.optional_absent.append(index)
                    out.notes.append(f"no 0x{index:04X} ({what}): {optional[index]}")
            else:
                out.mismatches.append(f"lacks 0x{index:04X}:{sub:02X} ({what}), which canon needs")
        except SdoAbortedError:
            pass  # exists, but not readable (write-only): fine for a scan
    return out


def _inputs_and_probe(cfg: DriveConfig, node: canopen.RemoteNode, out: DriveScan) -> None:
    """0x60FD and the touch probes, as the boot takes them: without 0x60FD a note (canon does not see
    the switches); a configured touch probe whose objects (or 0x60FD, whose PDO carries its status)
    the drive lacks, a mismatch (the boot refuses it)."""
    key = f"canopen.axes.{cfg.axis}.touch_probe = {cfg.touch_probe}"
    out.digital_inputs = _number(node, 0x60FD, 0, "I")
    if out.digital_inputs is None:
        out.notes.append("no 0x60FD (digital inputs): canon does not see its limit and home switches, only "
                         "the drive's own reaction to them stops the axis")
        if cfg.touch_probe:
            out.mismatches.append(f"{key} needs 0x60FD (digital inputs): the touch probe status travels in "
                                  "its PDO")
    for probe in touch_probe.POSITIONS:
        absent = []
        for index, what in touch_probe.objects(probe):
            try:
                _upload(node, index, 0)
            except _Absent:
                absent.append(f"0x{index:04X} ({what})")
            except SdoAbortedError:
                pass  # exists, not readable
        if not absent:
            out.touch_probes.append(probe)
        elif probe == cfg.touch_probe:
            out.mismatches.append(f"{key}, but the drive lacks {', '.join(absent)}")


def scan(conf: CanopenConfig, network: canopen.Network, timeout_s: float = 0.5) -> list[DriveScan]:
    """Every configured drive, in axis order, on an already connected ``network``."""
    results = []
    for cfg in conf.drives:
        node = canopen.RemoteNode(cfg.node_id, cfg.eds_path)
        node.sdo.RESPONSE_TIMEOUT = timeout_s
        node.sdo.MAX_RETRIES = 2  # one retry (0 would retry forever)
        network.add_node(node)
        results.append(scan_drive(conf, cfg, node))
    return results
