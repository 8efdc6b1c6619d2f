"""The command key the tests sign with (``telemetry.auth``); ``conftest`` puts it in ``$CANON_KEY`` so
that clients (``send_command``, ``canon ctl`` run as a process) find it as an operator's would."""

from __future__ import annotations

import os
from pathlib import Path

TEST_KEY = bytes(range(0x40, 0x60))


def write_key_file(path: Path, key: bytes = TEST_KEY) -> Path:
    """A key file as the daemon makes one (mode 0640)."""
    path.write_text(key.hex() + "\n")
    os.chmod(path, 0o640)
    return path
