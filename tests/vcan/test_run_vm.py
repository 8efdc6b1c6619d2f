"""``tests/vcan/run-vm`` itself, on the host, with a stand-in for virtme-ng: what it asks the VM to run
(the vcan suite, or with ``--bench`` the socketcan bench) and that the VM's exit status and output come
back. The suite and the bench inside the VM are ``tests/vcan/test_vcan.py``'s."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent.parent

pytestmark = pytest.mark.skipif(not list(Path("/boot").glob("vmlinuz-*")),
                                reason="no kernel in /boot: run-vm stops before the VM")

FAKE_VNG = """#!/bin/sh
# virtme-ng's stand-in: the --exec command and the results directory, as run-vm passes them
while [ "$#" -gt 0 ]; do
    case "$1" in
        --exec) inner=$2; shift ;;
        --rwdir) out=$2; shift ;;
    esac
    shift
done
printf '%s\\n' "$inner" > "$out/pytest.log"
echo 3 > "$out/rc"
"""


def run_vm(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    vng = tmp_path / "vng"
    vng.write_text(FAKE_VNG)
    vng.chmod(0o755)
    env = {**os.environ, "VNG": str(vng), "PYTHON": sys.executable}
    return subprocess.run(["bash", str(ROOT / "tests" / "vcan" / "run-vm"), *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=60)


def test_run_vm_bench_runs_the_socketcan_bench_on_vcan0_with_its_arguments(tmp_path: Path) -> None:
    res = run_vm(tmp_path, "--bench", "--seconds", "3", "--drives", "2", "--periods-ms", "10")
    assert res.returncode == 3, res.stderr  # the VM's exit status comes back
    inner = res.stdout
    assert "modprobe vcan && ip link add dev vcan0 type vcan && ip link set up vcan0" in inner
    run = f"{sys.executable} bench/fieldbus.py --bus socketcan --seconds 3 --drives 2 --periods-ms 10"
    assert run in inner and "-m pytest" not in inner
    assert f"cd {ROOT} " in inner


def test_run_vm_without_bench_runs_the_vcan_suite(tmp_path: Path) -> None:
    res = run_vm(tmp_path, "-k", "kernel sync")
    assert res.returncode == 3, res.stderr
    assert "-m pytest" in res.stdout and "-m vcan tests/vcan" in res.stdout
    assert "bench/fieldbus.py" not in res.stdout
    assert "-k kernel\\ sync" in res.stdout  # quoted for the VM's shell
