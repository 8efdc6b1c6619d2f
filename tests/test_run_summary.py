"""The run summary judges itself: late cycles against a real drive's tolerance, and where the time
went when the run took longer than its motion."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from motiond.cmd_run import time_breakdown, timing_verdict

ROOT = Path(__file__).resolve().parent.parent
T = 0.002


def test_on_time_run_is_ok() -> None:
    verdict, words = timing_verdict([], T, 0.05, 300)
    assert verdict == "ok" and "happy" in words


def test_late_within_a_period_is_not_noticed() -> None:
    verdict, words = timing_verdict([0.0011, 0.0015, 0.0019], T, 0.05, 300)
    assert verdict == "ok" and "3 cycles late" in words and "worst 1.9 ms" in words


def test_late_by_more_than_a_period_is_rough() -> None:
    verdict, words = timing_verdict([0.0015, 0.004, 0.030], T, 0.05, 300)
    assert verdict == "rough" and words.startswith("2 cycles late by more than one period")


def test_late_within_the_setpoint_lead_is_not_noticed() -> None:
    """With the SYNC process holding setpoints 3 SYNCs ahead, a cycle late by 2.5 periods still found
    its setpoints out in time; past 3 periods it did not."""
    late = [0.0015, 0.004, 0.005]
    assert timing_verdict(late, T, 0.05, 300)[0] == "rough"
    verdict, words = timing_verdict(late, T, 0.05, 300, lead=3)
    assert verdict == "ok" and "less than 3 periods (the setpoint lead)" in words
    verdict, words = timing_verdict([*late, 0.0065], T, 0.05, 300, lead=3)
    assert verdict == "rough" and words.startswith("1 cycle late by more than 3 periods (the setpoint lead)")


@pytest.mark.parametrize(("late", "hb", "beyond"), [
    ([0.003, 0.1656], 300, "late-cycle limit for real drives (50 ms)"),
    ([0.3500], 300, "heartbeat consumer time (300 ms)"),
])
def test_beyond_the_drives_tolerance_is_a_fault(late: list[float], hb: int, beyond: str) -> None:
    verdict, words = timing_verdict(late, T, 0.05, hb)
    assert verdict == "fault" and words.startswith("NOT fit for a real machine") and beyond in words


def test_time_breakdown_adds_up() -> None:
    # 100 s of wall time, 20,000 executed cycles (40 s) of which 15,000 moved (30 s), 2 s to the first
    # setpoint: 8 s standing and 60 s of deadlines that never ran
    r = SimpleNamespace(duration_s=100.0, cycles=20_000, moving_cycles=15_000, first_setpoint_s=2.0)
    tb = time_breakdown(r, T)
    assert tb["moving_s"] == pytest.approx(30.0)
    assert tb["before_first_setpoint_s"] == pytest.approx(2.0)
    assert tb["standing_s"] == pytest.approx(8.0)
    assert tb["skipped_s"] == pytest.approx(60.0)


def test_summary_of_a_real_run_has_verdict_and_time(tmp_path: Path) -> None:
    prog = tmp_path / "dwell.ngc"
    prog.write_text("%\nG21 G90 G94\nG1 X10 F600\nG4 P2\nG1 X0\nM2\n%\n")  # 2 s moving, 2 s dwelling
    r = subprocess.run([sys.executable, "-m", "motiond.cli", "run", "--json", "--no-telemetry", str(prog)],
                       capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["timing"]["verdict"] in ("ok", "rough", "fault") and d["timing"]["text"]
    assert d["timing"]["heartbeat_consumer_ms"] == 300  # the demo's configured value, not the simulation's
    tb = d["time"]
    assert 1.9 < tb["moving_s"] < 2.6  # two 10 mm moves at 10 mm/s with their ramps
    assert tb["standing_s"] + tb["before_first_setpoint_s"] >= 1.9  # the dwell
    parts = tb["moving_s"] + tb["before_first_setpoint_s"] + tb["standing_s"] + tb["skipped_s"]
    assert parts == pytest.approx(tb["total_s"], abs=0.05)


def test_the_drives_own_setpoint_timeout_is_the_limit_when_configured() -> None:
    """With the drives' setpoint timeout configured (8 ms) a 7 ms late cycle (a 9 ms gap between
    setpoints) is a fault that canon's 50 ms limit would have called rough; a 5 ms one (7 ms gap) is not."""
    verdict, words = timing_verdict([0.007], T, 0.05, 300, drive_timeout_ms=8.0)
    assert verdict == "fault" and "the drives' setpoint timeout (8 ms)" in words
    assert timing_verdict([0.007], T, 0.05, 300)[0] == "rough"
    verdict, words = timing_verdict([0.005], T, 0.05, 300, drive_timeout_ms=8.0)
    assert verdict == "rough" and "within the drives' setpoint timeout (8 ms)" in words


def test_drive_setpoint_timeout_is_read_and_checked(tmp_path: Path) -> None:
    from motiond.config import load_machine
    from motiond.config_canopen import canopen_for_machine
    from motiond.config_check import validate_machine
    from motiond.configkit import ConfigErrors

    text = (ROOT / "examples" / "canon.toml").read_text()
    good = tmp_path / "good.toml"
    good.write_text(text.replace("steer_gc = true", "steer_gc = true\ndrive_setpoint_timeout_ms = 6", 1))
    assert canopen_for_machine(load_machine(str(good))).drive_setpoint_timeout_ms == 6.0
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("steer_gc = true", "steer_gc = true\ndrive_setpoint_timeout_ms = -1", 1))
    with pytest.raises(ConfigErrors) as info:
        validate_machine(str(bad))
    assert [e.key for e in info.value.errors] == ["canopen.drive_setpoint_timeout_ms"]
