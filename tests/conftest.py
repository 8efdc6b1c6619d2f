"""Shared pytest set-up.

Tests marked ``multicast`` join multicast groups; they run only inside the private network namespace
that ``tests/run`` makes (CANON_NETNS=1), and otherwise skip with that reason.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from keys import TEST_KEY

ROOT = Path(__file__).resolve().parent.parent
os.environ["CANON_KEY"] = TEST_KEY.hex()  # clients sign with it; the daemons under test get it given
PROGRAMS = Path(__file__).resolve().parent / "programs"


def pytest_configure(config: pytest.Config) -> None:
    # canon run and canon daemon lock their machine in the state directory: tests (and their
    # subprocesses) get a private one, so that runs elsewhere on this host do not refuse theirs
    import tempfile

    os.environ.pop("STATE_DIRECTORY", None)
    os.environ["XDG_STATE_HOME"] = tempfile.mkdtemp(prefix="canon-test-state-")
    _take_ctrl_c_as_a_terminal_would()


def _take_ctrl_c_as_a_terminal_would() -> None:
    """Give this process (and so every ``canon`` it starts) SIGINT as a terminal's foreground job has it.

    A shell without job control starts background commands with SIGINT ignored (POSIX), and Python
    then keeps it ignored instead of raising KeyboardInterrupt; its children inherit that. The suite
    run that way (``tests/run ... &`` in a script) saw every Ctrl-C test fail: ``canon run`` ran its
    program to the end, as it should when SIGINT is ignored. The tests check what Ctrl-C does, so
    they set it up as Ctrl-C comes: handled here, and so at its default in every child (exec resets a
    handled signal to its default)."""
    import signal

    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if os.environ.get("CANON_NETNS") == "1":
        return
    skip = pytest.mark.skip(
        reason="joins a multicast group: run through tests/run as root (private network namespace)"
    )
    for item in items:
        if "multicast" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def rig() -> Iterator[Callable[..., Any]]:
    """``rig(n, sims=None, up=True, **config)``: simulated drives and a master on a fresh virtual
    channel (``canopen_helpers.Rig``), booted and enabled unless ``up`` is False; closed at the end."""
    from canopen_helpers import Rig, make_config

    rigs: list[Any] = []

    def make(n: int = 3, sims: list[Any] | None = None, up: bool = True, **kw: object) -> Any:
        r = Rig(make_config(n, **kw), sims)
        rigs.append(r)
        return r.up() if up else r

    yield make
    for r in rigs:
        r.close()


@pytest.fixture
def local_rig() -> Iterator[Callable[..., Any]]:
    """``make(n, **config)``: n simulated drives and a master on a fresh canon_local channel, the SYNC
    from a SYNC process, and a listener on the channel; closed after the test."""
    from canopen_helpers import LocalListener, Rig, make_config, unique_channel

    from fieldbus.canopen.config import CanBusConfig

    made: list[tuple[Rig, LocalListener]] = []

    def make(n: int, **kw: object) -> tuple[Rig, LocalListener]:
        channel = unique_channel()
        config = make_config(n, bus=CanBusConfig("canon_local", channel), sync="process", **kw)
        listener = LocalListener(channel)
        rig = Rig(config, check_budget=False)
        made.append((rig, listener))
        return rig, listener

    yield make
    for rig, listener in made:
        try:
            rig.close()
        finally:
            listener.close()
