"""``canon`` logging levels: canon's own at INFO, the libraries' at WARNING, ``-v``/``-vv`` more;
pymodbus's frame dumps kept out of error messages below ``-vv``. Each case in a fresh interpreter."""

from __future__ import annotations

import subprocess
import sys

import pytest

SCRIPT = """
import logging, sys
from motiond.logsetup import setup_logging
from pymodbus.logging import Log
setup_logging(int(sys.argv[1]))
logging.getLogger("motiond.runtime").info("canon info")
logging.getLogger("fieldbus.canopen.master").debug("canon debug")
logging.getLogger("canopen.sdo.client").info("library info")
logging.getLogger("can.interfaces.virtual").debug("library debug")
Log.transport_dump(Log.SEND_DATA, b"\\x00\\x01\\x00\\x00\\x00\\x06\\x01\\x05", b"")
Log.error("modbus link lost {}", "io")
"""


def run(verbose: int) -> str:
    r = subprocess.run([sys.executable, "-c", SCRIPT, str(verbose)], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stderr


@pytest.mark.parametrize(("verbose", "shown", "hidden"), [
    (0, ["canon info", "modbus link lost io"], ["canon debug", "library info", "library debug", ">>>>>"]),
    (1, ["canon info", "canon debug", "modbus link lost io"], ["library info", "library debug", ">>>>>"]),
    (2, ["canon info", "canon debug", "library info", "library debug", "send: 0x0"], []),
])
def test_levels(verbose: int, shown: list[str], hidden: list[str]) -> None:
    err = run(verbose)
    for text in shown:
        assert text in err, err
    for text in hidden:
        assert text not in err, err
