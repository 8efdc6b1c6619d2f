"""The master's boot of each drive: NMT reset, identity, the drive's limits against the configuration,
its DCF and the machine file's SDO writes, canon's own objects and PDO layout, NMT start. Also the SDO
helper every SDO-using part of the master goes through (errors name node, object and abort code)."""

from __future__ import annotations

import logging
import struct
import time

from canopen.sdo import SdoAbortedError, SdoCommunicationError

from fieldbus.canopen import cia402, touch_probe
from fieldbus.canopen.commissioning import LIMIT_OBJECTS, boot_writes, limit_problems, optional_objects
from fieldbus.canopen.master_records import (
    NO_SUCH_OBJECT,
    CanopenError,
    DriveBook,
    MasterCore,
)
from fieldbus.canopen.pdo import DIGITAL_INPUTS

log = logging.getLogger(__name__)


class BootMixin(MasterCore):
    """Boot and SDO access, part of :class:`~fieldbus.canopen.master.CanopenMaster`."""

    def _sdo(self, d: DriveBook, what: str, index: int, sub: int, fmt: str | None = None,
             value: int | None = None, ok_aborts: tuple[int, ...] = (),
             absent: dict[int, int] | None = None) -> int:
        """One SDO read (``value`` None) or write; an abort or timeout is a :class:`CanopenError`
        naming the node, the object and ``what`` it is, except aborts in ``ok_aborts`` (then 0).
        ``absent``: an optional object, whose "does not exist" abort is recorded there (index: abort
        code; then 0)."""
        where = f"0x{index:04X}:{sub:02X} ({what})"
        try:
            with d.sdo_lock:
                if fmt is not None and value is not None:
                    d.node.sdo.download(index, sub, struct.pack("<" + fmt, value))
                    return value
                raw = d.node.sdo.upload(index, sub)
        except SdoAbortedError as exc:
            if exc.code in ok_aborts:
                return 0
            if absent is not None and exc.code in NO_SUCH_OBJECT:
                absent.setdefault(index, exc.code)
                return 0
            raise CanopenError(f"{d.describe()}: SDO {'write' if value is not None else 'read'} of {where} "
                               f"aborted by the drive: 0x{exc.code:08X} {exc}") from None
        except SdoCommunicationError:
            raise CanopenError(f"{d.describe()}: SDO {'write' if value is not None else 'read'} of {where} "
                               f"timed out: no answer in {self.config.sdo_timeout_s:g} s (twice)") from None
        if fmt is None:
            fmt = {1: "B", 2: "H", 4: "I"}.get(len(raw), "I")
        return struct.unpack_from("<" + fmt, raw.ljust(struct.calcsize(fmt), b"\0"))[0]

    def _statusword(self, d: DriveBook) -> int:
        return self._sdo(d, "statusword", 0x6041, 0, "H")

    # ------------------------------------------------------------------ boot
    def boot(self) -> None:
        """Reset communication, check identity, configure by SDO, start: every drive, in order."""
        self.open()
        with self._lock:
            self.streaming = False
            for d in self.drives:
                d.active = False
        for d in self.drives:
            self._boot_drive(d)
        self._boot_spindle()

    def _boot_drive(self, d: DriveBook) -> None:
        cfg, conf = d.cfg, self.config
        node = d.node
        d.booted.clear()
        node.nmt.send_command(0x82)  # reset communication
        if not d.booted.wait(conf.boot_timeout_s):
            raise CanopenError(f"{d.describe()}: no boot-up message within {conf.boot_timeout_s:g} s after "
                               "NMT reset communication (drive off, wrong node id or bitrate?)")
        # identity against the configuration (or, where it names none, against the EDS)
        od = node.object_dictionary
        for sub, name, want in ((1, "vendor id", cfg.vendor_id), (2, "product code", cfg.product_code)):
            if want is None:
                try:
                    want = od[0x1018][sub].default
                except KeyError:
                    continue
            got = self._sdo(d, f"identity {name}", 0x1018, sub, "I")
            if want is not None and got != want:
                raise CanopenError(f"{d.describe()}: identity 0x1018:{sub:02X} {name} is 0x{got:08X}, "
                                   f"the configuration expects 0x{want:08X} (wrong drive on this node id?)")
        self._check_limits(d)
        if cfg.touch_probe:
            touch_probe.check_objects(self, d)  # type: ignore[arg-type]
        self._load_dcf(d)
        for index, sub, code, value, where in cfg.sdo:
            self._sdo(d, f"{where} in the machine file", index, sub, code, value)
        steps = boot_writes(conf, cfg)
        for p in self.layout.unused_pdos():
            # COB-ID bit 31; a drive without that PDO has nothing to disable
            self._sdo(d, f"{p.name} COB-ID (disable)", p.comm_index, 1, "I",
                      0x80000000 | p.cob_id(cfg.node_id), ok_aborts=NO_SUCH_OBJECT)
        optional = optional_objects(self.layout.name)
        d.has_inputs = self._read_optional(d, "digital inputs", 0x60FD, 0, "I") is not None
        p = self.layout.carrying(DIGITAL_INPUTS, tpdo=True)
        disable = (f"{p.name} COB-ID (disable)", p.comm_index, 1, "I", 0x80000000 | p.cob_id(cfg.node_id))
        # a drive with fewer TPDOs has no room for its inputs: as a drive without 0x60FD
        self._sdo(d, *disable, absent=d.missing, ok_aborts=() if d.has_inputs else NO_SUCH_OBJECT)
        if not d.has_inputs or p.comm_index in d.missing:
            lacks = 0x60FD if not d.has_inputs else p.comm_index
            d.has_inputs = False
            steps = [s for s in steps if s[1] not in (p.comm_index, p.mapping_index)]
            what = "digital inputs" if lacks == 0x60FD else p.name
            self.warn(cfg.node_id, f"has no object 0x{lacks:04X} ({what}"
                                   f"; SDO abort 0x{d.missing[lacks]:08X}): canon does not see its limit "
                                   "switches (0x60FD), only the drive's own reaction to them stops the axis")
        for what, index, sub, fmt, value in steps:
            before = len(d.missing)
            self._sdo(d, what, index, sub, fmt, value, absent=d.missing if index in optional else None)
            if len(d.missing) > before:
                self.warn(cfg.node_id, f"has no object 0x{index:04X} ({what}; SDO abort "
                                       f"0x{d.missing[index]:08X}): {optional[index]}")
        mode = self._sdo(d, "modes of operation display", 0x6061, 0, "b")
        if mode != cia402.MODE_CSP:
            raise CanopenError(f"{d.describe()}: modes of operation display is {mode}, not 8 (cyclic "
                               "synchronous position) after writing 0x6060 = 8")
        node.nmt.send_command(0x01)  # start
        deadline = time.monotonic() + conf.boot_timeout_s
        while d.nmt_state != 5:
            if time.monotonic() > deadline:
                raise CanopenError(f"{d.describe()}: did not report NMT Operational within "
                                   f"{conf.boot_timeout_s:g} s after NMT start (heartbeat state "
                                   f"{d.nmt_state})")
            time.sleep(0.002)
        d.heartbeat_at = time.monotonic()
        self._restore_outputs(d)  # type: ignore[attr-defined]  (OutputsMixin)
        log.info("%s booted", d.describe())

    def _load_dcf(self, d: DriveBook) -> None:
        """The values of the axis's DCF (its ParameterValue entries) written to the drive by canopen's
        own configuration loader (``RemoteNode.load_configuration``: PDO records first, then every
        writable object with a value). An EDS has no values: nothing is written. canon's own objects
        (the cycle, the quick stop, the PDO layout, heartbeats) are written afterwards and win."""
        od = d.node.object_dictionary
        values = [v for obj in od.values() for v in (obj.values() if hasattr(obj, "values") else [obj])
                  if getattr(v, "value", None) is not None]
        if not values:
            return
        log.info("%s: writing %d values of %s", d.describe(), len(values), d.cfg.eds_path)
        try:
            d.node.load_configuration()
        except SdoAbortedError as exc:
            raise CanopenError(f"{d.describe()}: writing the values of {d.cfg.eds_path}: SDO abort "
                               f"0x{exc.code:08X} ({exc}); the drive refused one of the file's values "
                               "(the object is in the log)") from None
        except SdoCommunicationError as exc:
            raise CanopenError(f"{d.describe()}: writing the values of {d.cfg.eds_path}: no SDO answer "
                               f"({exc})") from None

    def _read_optional(self, d: DriveBook, what: str, index: int, sub: int, fmt: str) -> int | None:
        """An optional object's value, or None (remembered in ``d.missing``) when the drive lacks it."""
        before = len(d.missing)
        value = self._sdo(d, what, index, sub, fmt, absent=d.missing)
        return None if len(d.missing) > before or index in d.missing else value

    def _check_limits(self, d: DriveBook) -> None:
        """The drive's capabilities and limits against the configuration, before anything is written:
        CSP among its supported modes (0x6502); max_velocity within the max motor speed (0x6080, rpm,
        with the counts per revolution from the configuration or 0x608F); max_acceleration within
        0x60C5 and 0x60C6; the soft-limit range within the software position limits (0x607D). Each
        object only where the drive has it. A configuration asking more is refused, naming the key,
        the object and both values."""
        cfg = d.cfg
        d.missing = {}
        d.limits = {}
        for index, sub, fmt, what in LIMIT_OBJECTS:
            d.limits[(index, sub)] = self._read_optional(d, what, index, sub, fmt)
        problems, notes = limit_problems(cfg, d.limits)
        if problems:
            raise CanopenError(f"{d.describe()}: {problems[0]}")
        for note in notes:
            self.warn(cfg.node_id, note)

