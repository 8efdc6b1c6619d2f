"""The TOML helpers every configuration section is read with: errors name the file and the key."""

from __future__ import annotations

import pytest

from motiond.configkit import ConfigError, Table, in_range, load_toml, one_of, positive


def test_error_names_file_and_dotted_key() -> None:
    t = Table({"axes": {"x": {"max_velocity": -5}}}, "m.toml")
    x = t.table("axes").table("x")
    with pytest.raises(ConfigError) as err:
        x.get("max_velocity", float, check=positive)
    assert str(err.value) == "m.toml: axes.x.max_velocity: must be > 0, got -5.0"
    assert err.value.key == "axes.x.max_velocity"


def test_type_errors_and_int_as_float() -> None:
    t = Table({"a": 3, "b": "x", "c": True, "d": float("nan")}, "f.toml")
    assert t.get("a", float) == 3.0
    with pytest.raises(ConfigError, match=r"b: must be float, got str"):
        t.get("b", float)
    with pytest.raises(ConfigError, match=r"c: must be int, got bool"):
        t.get("c", int)
    with pytest.raises(ConfigError, match=r"d: must be a finite number"):
        t.get("d", float)


def test_missing_required_and_default() -> None:
    t = Table({}, "f.toml", "canopen")
    assert t.get("bitrate", int, 500000) == 500000
    with pytest.raises(ConfigError, match=r"canopen.channel: missing \(required\)"):
        t.get("channel", str)


def test_unknown_key_is_reported() -> None:
    t = Table({"max_velocty": 1.0, "max_jerk": 2.0}, "f.toml", "axes.x")
    t.get("max_jerk", float)
    with pytest.raises(ConfigError, match=r"axes.x.max_velocty: unknown key"):
        t.check_unknown()


def test_checks() -> None:
    assert in_range(1, 10)(11) == "must be between 1 and 10"
    assert in_range(1, 10)(5) is None
    assert one_of("a", "b")("c") == "must be one of a, b"


def test_array_of_tables_paths() -> None:
    t = Table({"devices": [{"port": 1}, {"port": "x"}]}, "f.toml", "modbus")
    items = t.array_of_tables("devices")
    with pytest.raises(ConfigError, match=r"modbus.devices\[1\].port: must be int"):
        items[1].get("port", int)


def test_load_toml_errors(tmp_path) -> None:
    with pytest.raises(ConfigError, match="no such file"):
        load_toml(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[axes\nx = 1\n")
    with pytest.raises(ConfigError, match=r"bad.toml: not valid TOML"):
        load_toml(bad)
    good = tmp_path / "good.toml"
    good.write_text("[machine]\ncycle_ms = 2\n")
    assert load_toml(good) == {"machine": {"cycle_ms": 2}}
