"""The user M codes (M100-M199) a machine binds, for the interpreter: the keys of ``[io.mcodes]``
(the tables themselves are checked by :func:`motiond.config_io.read_io`). Apart from
:mod:`motiond.config_io` so that ``canon check`` learns them without importing the Modbus stack."""

from __future__ import annotations

import re
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from motiond.config import MachineConfig

MCODE_RE = re.compile(r"^M(1\d\d)$")

DEMO_MCODES: dict[str, dict[str, Any]] = {
    "M101": {"set": [{"coil": 14, "value": 1}], "wait": {"discrete_input": 15}, "timeout_s": 5.0},
    "M102": {"set": [{"coil": 14, "value": 0}]},
}
"""The demo machine's user M codes (docs/wiring.md)."""


def bound_mcodes(machine: MachineConfig) -> frozenset[int]:
    """The user M codes the machine binds (the keys of ``[io.mcodes]``; the demo machine's without a
    machine file)."""
    if machine.path is None or machine.root is None:
        data: Any = DEMO_MCODES
    else:
        io = machine.root.data.get("io")
        data = io.get("mcodes") if isinstance(io, dict) else None
    if not isinstance(data, dict):
        return frozenset()
    return frozenset(int(m.group(1)) for k in data if (m := MCODE_RE.match(k)) is not None)
