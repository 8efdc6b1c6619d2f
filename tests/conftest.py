"""Shared pytest set-up.

Tests marked ``multicast`` join multicast groups; they run only inside the private network namespace
that ``tests/run`` makes (CANON_NETNS=1), and otherwise skip with that reason.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PROGRAMS = Path(__file__).resolve().parent / "programs"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if os.environ.get("CANON_NETNS") == "1":
        return
    skip = pytest.mark.skip(
        reason="joins a multicast group: run through tests/run as root (private network namespace)"
    )
    for item in items:
        if "multicast" in item.keywords:
            item.add_marker(skip)
