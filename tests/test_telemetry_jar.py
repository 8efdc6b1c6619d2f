"""The Java side: the jar for lcm-spy builds, holds our classes, and Java decodes what Python encodes."""

from __future__ import annotations

import re
import shutil
import subprocess
import zipfile
from pathlib import Path

import pytest
from test_telemetry_types import full_status

from telemetry import generate
from telemetry.lcmtypes.canon import reply

needs_jdk = pytest.mark.skipif(shutil.which("javac") is None or shutil.which("jar") is None
                               or shutil.which("java") is None,
                               reason="needs a JDK (javac, jar, java): apt-get install default-jdk-headless")


def struct_names() -> set[str]:
    return {m for f in generate.lcm_files() for m in re.findall(r"^struct (\w+)", f.read_text(), re.M)}


def test_shipped_jar_holds_a_class_per_lcm_struct_and_the_stamp() -> None:
    with zipfile.ZipFile(generate.JAR) as z:
        names = set(z.namelist())
    assert {f"canon/{s}.class" for s in struct_names()} <= names
    assert generate.STAMP_NAME in names


@needs_jdk
def test_jar_builds_from_the_generated_java(tmp_path: Path) -> None:
    jar = generate.build_jar(generate.JAVA_DIR, tmp_path / "out" / "types.jar")
    with zipfile.ZipFile(jar) as z:
        names = set(z.namelist())
        stamp = z.read(generate.STAMP_NAME).decode().strip()
    assert {f"canon/{s}.class" for s in struct_names()} <= names
    assert stamp == generate.sources_digest()
    assert not list(jar.parent.glob(".*tmp*")), "no partial jar left behind"


@needs_jdk
def test_java_decodes_what_python_encodes_and_back(tmp_path: Path) -> None:
    """What lcm-spy does with our messages: the Java classes read Python's bytes, and vice versa."""
    (tmp_path / "status.bin").write_bytes(full_status().encode())
    src = tmp_path / "Probe.java"
    src.write_text("""
import java.nio.file.*;
public class Probe {
    public static void main(String[] a) throws Exception {
        canon.status s = new canon.status(Files.readAllBytes(Paths.get(a[0], "status.bin")));
        System.out.println(s.machine + "|" + s.num_axes + "|" + s.commanded[2] + "|"
            + s.drives[0].statusword + "|" + s.drives[2].error + "|" + s.gcodes[6] + "|"
            + s.digital_inputs[3] + "|" + s.analog_outputs[2] + "|" + s.last_error + "|" + s.events_dropped);
        canon.reply r = new canon.reply();
        r.request_id = 99; r.sender = "java"; r.verb = "abort"; r.ok = true; r.error = "";
        java.io.ByteArrayOutputStream bytes = new java.io.ByteArrayOutputStream();
        r.encode(new java.io.DataOutputStream(bytes));
        Files.write(Paths.get(a[0], "reply.bin"), bytes.toByteArray());
    }
}
""")
    lcm_jar = generate.lcm_share_java() / "lcm.jar"
    cp = f"{generate.JAR}:{lcm_jar}:{tmp_path}"
    javac = subprocess.run(["javac", "-nowarn", "-cp", cp, "-d", str(tmp_path), str(src)], timeout=120,
                           capture_output=True, text=True)
    assert javac.returncode == 0, javac.stderr
    proc = subprocess.run(["java", "-cp", cp, "Probe", str(tmp_path)], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == ("demo mill|3|0.125|46647|following error|G94|true|-3.25"
                                   "|drive z: following error|7")
    back = reply.decode((tmp_path / "reply.bin").read_bytes())
    assert (back.request_id, back.sender, back.verb, back.ok) == (99, "java", "abort", True)


@needs_jdk
def test_types_jar_builds_into_the_cache_when_the_shipped_one_is_stale(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(generate, "JAR", tmp_path / "missing.jar")
    built = generate.types_jar()
    assert built.parent == tmp_path / "cache" / "canon"
    assert generate.jar_digest(built) == generate.sources_digest()
    mtime = built.stat().st_mtime_ns
    assert generate.types_jar() == built and built.stat().st_mtime_ns == mtime  # reused, not rebuilt


def test_types_jar_uses_the_shipped_jar_when_it_matches(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(generate, "find_javac", lambda: None)
    assert generate.types_jar() == generate.JAR


def test_types_jar_without_javac_says_what_to_install(tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(generate, "JAR", tmp_path / "missing.jar")
    monkeypatch.setattr(generate, "find_javac", lambda: None)
    with pytest.raises(generate.GenerateError, match=r"javac is missing.*default-jdk-headless"):
        generate.types_jar()
