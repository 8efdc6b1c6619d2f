"""Regenerate the code made from ``telemetry/*.lcm``: ``python -m telemetry.generate``.

Three outputs, all committed, so that an installed canon needs neither ``lcm-gen`` nor a JDK:

* ``telemetry/lcmtypes/canon/*.py``: Python, importable as ``telemetry.lcmtypes.canon``. lcm-gen is
  run with ``--package-prefix telemetry.lcmtypes`` so that the generated modules import each other by
  that full name (which works installed editable and from a wheel); the LCM type names, and so the
  fingerprints on the wire, stay ``canon.*`` (lcm-gen does not hash package names).
* ``telemetry/java/canon/*.java``: Java, package ``canon``, the names lcm-spy shows.
* ``telemetry/canon_types.jar``: those classes compiled with ``javac --release 8`` (the level of the
  wheel's own ``lcm.jar``) against the wheel's ``lcm.jar``, for lcm-spy's CLASSPATH. It holds a stamp,
  ``canon-types.sha256``, the digest of the ``.lcm`` sources it was built from: :func:`types_jar`
  uses the shipped jar while its stamp matches, and otherwise builds one into the user's cache
  (``~/.cache/canon``) when ``javac`` is there. Jar entries get a fixed date and order, so the same
  JDK rebuilds the same bytes.

``python -m telemetry.generate --check`` regenerates into a temporary directory and reports every
file that differs from the committed one (exit status 1), for CI and the tests.
"""

from __future__ import annotations

import argparse
import filecmp
import hashlib
import logging
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

log = logging.getLogger(__name__)

HERE = Path(__file__).resolve().parent
PY_PREFIX = "telemetry.lcmtypes"
LCM_PACKAGE = "canon"
PY_DIR = HERE / "lcmtypes" / LCM_PACKAGE
JAVA_DIR = HERE / "java" / LCM_PACKAGE
JAR = HERE / "canon_types.jar"
STAMP_NAME = "canon-types.sha256"
JAVA_RELEASE = "8"
JAR_DATE = "2000-01-01T00:00:00Z"


class GenerateError(RuntimeError):
    """A tool is missing or failed; the message says which and what to do."""


def lcm_files() -> list[Path]:
    return sorted(HERE.glob("*.lcm"))


def sources_digest(files: list[Path] | None = None) -> str:
    """SHA-256 over the names and contents of the ``.lcm`` files: what the jar stamp records."""
    h = hashlib.sha256()
    for f in files if files is not None else lcm_files():
        h.update(f.name.encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()


def lcm_share_java() -> Path:
    """``share/java`` of the installed lcm wheel (``lcm.jar`` and lcm-spy's libraries)."""
    import lcm

    return (Path(lcm.LCM_BIN_DIR) / ".." / "share" / "java").resolve()


def lcm_tool(name: str) -> Path:
    """A program shipped in the lcm wheel's ``bin`` (lcm-gen, lcm-spy, lcm-logger ...)."""
    import lcm

    path = (Path(lcm.LCM_BIN_DIR) / name).resolve()
    if not path.is_file():
        found = shutil.which(name)
        if found is None:
            raise GenerateError(f"{name} not found (looked in {path.parent} and on PATH): pip install lcm")
        path = Path(found)
    return path


def _run(cmd: list[str], what: str, cwd: Path | None = None) -> None:
    log.debug("running %s", " ".join(cmd))
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, timeout=300)
    if proc.returncode != 0:
        detail = (proc.stderr or proc.stdout).strip()
        raise GenerateError(f"{what} failed (exit {proc.returncode}): {' '.join(cmd)}\n{detail}")


def generate_python(out_dir: Path) -> list[Path]:
    """Run lcm-gen for Python; write the ``canon`` package's modules into ``out_dir``."""
    with tempfile.TemporaryDirectory(prefix="canon-lcm-py-") as tmp:
        _run([str(lcm_tool("lcm-gen")), "--python", "--ppath", tmp, "--package-prefix", PY_PREFIX,
              *map(str, lcm_files())], "lcm-gen --python")
        made = Path(tmp, *PY_PREFIX.split("."), LCM_PACKAGE)
        return _replace_dir(made, out_dir, "*.py")


def generate_java(out_dir: Path) -> list[Path]:
    """Run lcm-gen for Java; write package ``canon``'s sources into ``out_dir``."""
    with tempfile.TemporaryDirectory(prefix="canon-lcm-java-") as tmp:
        _run([str(lcm_tool("lcm-gen")), "--java", "--jpath", tmp, *map(str, lcm_files())],
             "lcm-gen --java")
        return _replace_dir(Path(tmp, LCM_PACKAGE), out_dir, "*.java")


def _replace_dir(src: Path, dst: Path, pattern: str) -> list[Path]:
    """Make ``dst`` hold exactly the ``pattern`` files of ``src`` (stale ones removed)."""
    made = sorted(src.glob(pattern))
    if not made:
        raise GenerateError(f"lcm-gen wrote no {pattern} files into {src}")
    dst.mkdir(parents=True, exist_ok=True)
    names = {f.name for f in made}
    for old in dst.glob(pattern):
        if old.name not in names:
            old.unlink()
    out = []
    for f in made:
        target = dst / f.name
        if not target.exists() or target.read_bytes() != f.read_bytes():
            _atomic_write(target, f.read_bytes())
        out.append(target)
    return out


def _atomic_write(target: Path, data: bytes) -> None:
    tmp = target.with_name(f".{target.name}.tmp{os.getpid()}")
    tmp.write_bytes(data)
    os.replace(tmp, target)


def find_javac() -> str | None:
    return shutil.which("javac")


def build_jar(java_dir: Path, jar_path: Path, digest: str | None = None) -> Path:
    """Compile the generated Java in ``java_dir`` against lcm.jar and pack it into ``jar_path``.

    The jar is written beside its target and renamed into place, so a failed build leaves no
    half-written jar behind.
    """
    javac = find_javac()
    jar_tool = shutil.which("jar")
    if javac is None or jar_tool is None:
        raise GenerateError("javac and jar are needed to build the lcm-spy jar: install a JDK "
                            "(Debian/Ubuntu: apt-get install default-jdk-headless)")
    lcm_jar = lcm_share_java() / "lcm.jar"
    if not lcm_jar.is_file():
        raise GenerateError(f"{lcm_jar} not found: the lcm wheel is incomplete (pip install --force lcm)")
    sources = sorted(java_dir.glob("*.java"))
    if not sources:
        raise GenerateError(f"no Java sources in {java_dir}: run python -m telemetry.generate")
    jar_path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="canon-jar-") as tmp:
        classes = Path(tmp, "classes")
        classes.mkdir()
        _run([javac, "--release", JAVA_RELEASE, "-nowarn", "-encoding", "UTF-8", "-cp", str(lcm_jar),
              "-d", str(classes), *map(str, sources)], "javac")
        (classes / STAMP_NAME).write_text((digest or sources_digest()) + "\n")
        entries = sorted(str(p.relative_to(classes)) for p in classes.rglob("*") if p.is_file())
        partial = jar_path.with_name(f".{jar_path.name}.tmp{os.getpid()}")
        cmd = [jar_tool, "--create", "--file", str(partial), "--no-manifest"]
        if _jar_has_date_option(jar_tool):
            cmd.append(f"--date={JAR_DATE}")
        for entry in entries:
            cmd += ["-C", str(classes), entry]
        try:
            _run(cmd, "jar")
            os.replace(partial, jar_path)
        finally:
            partial.unlink(missing_ok=True)
    return jar_path


def _jar_has_date_option(jar_tool: str) -> bool:
    """``jar --date`` (reproducible timestamps) exists from JDK 17 on."""
    proc = subprocess.run([jar_tool, "--help"], capture_output=True, text=True, timeout=60)
    return "--date" in proc.stdout + proc.stderr


def jar_digest(jar_path: Path) -> str | None:
    """The ``.lcm`` digest stamped into a jar by :func:`build_jar` (None if absent or unreadable)."""
    import zipfile

    try:
        with zipfile.ZipFile(jar_path) as z:
            return z.read(STAMP_NAME).decode().strip()
    except (OSError, KeyError, zipfile.BadZipFile):
        return None


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "canon"


def types_jar(build: bool = True) -> Path:
    """The jar of our types for lcm-spy, matching the ``.lcm`` files of this installation.

    The shipped jar when its stamp matches; else a jar in the cache built earlier for these sources;
    else (``build``) one built now from freshly generated Java. Raises :class:`GenerateError` when no
    matching jar exists and none can be built.
    """
    digest = sources_digest()
    if jar_digest(JAR) == digest:
        return JAR
    cached = cache_dir() / f"canon_types-{digest[:16]}.jar"
    if jar_digest(cached) == digest:
        return cached
    if not build:
        raise GenerateError(f"{JAR} does not match {HERE}/*.lcm and no matching jar is in {cached.parent}")
    if find_javac() is None:
        raise GenerateError(f"{JAR} does not match {HERE}/*.lcm (it was built from other sources) and "
                            "javac is missing to build one: install a JDK (apt-get install "
                            "default-jdk-headless) or run python -m telemetry.generate where one is")
    log.info("building %s for lcm-spy", cached)
    with tempfile.TemporaryDirectory(prefix="canon-java-") as tmp:
        generate_java(Path(tmp))
        return build_jar(Path(tmp), cached, digest)


def check(with_jar: bool = True) -> list[str]:
    """Differences between the committed generated files and what lcm-gen makes now (empty: none)."""
    problems: list[str] = []
    with tempfile.TemporaryDirectory(prefix="canon-check-") as tmp:
        for kind, gen, committed, pattern in (
            ("Python", generate_python, PY_DIR, "*.py"),
            ("Java", generate_java, JAVA_DIR, "*.java"),
        ):
            fresh_dir = Path(tmp, kind)
            fresh = {f.name for f in gen(fresh_dir)}
            have = {f.name for f in committed.glob(pattern)} if committed.is_dir() else set()
            for name in sorted(fresh - have):
                problems.append(f"{committed / name}: missing ({kind} for a .lcm type)")
            for name in sorted(have - fresh):
                problems.append(f"{committed / name}: not generated from any .lcm file (stale)")
            for name in sorted(fresh & have):
                if not filecmp.cmp(fresh_dir / name, committed / name, shallow=False):
                    problems.append(f"{committed / name}: differs from lcm-gen's output (edited by hand, "
                                    "or a .lcm file changed without regenerating)")
    if with_jar and jar_digest(JAR) != sources_digest():
        problems.append(f"{JAR}: missing or built from other .lcm sources")
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m telemetry.generate", description=__doc__.split("\n")[0])
    parser.add_argument("--check", action="store_true",
                        help="change nothing; list generated files that differ from lcm-gen's output")
    parser.add_argument("--no-jar", action="store_true", help="do not build telemetry/canon_types.jar")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        if args.check:
            problems = check(with_jar=not args.no_jar)
            for p in problems:
                print(p, file=sys.stderr)
            if problems:
                print("run: python -m telemetry.generate", file=sys.stderr)
            return 1 if problems else 0
        for f in generate_python(PY_DIR):
            log.info("wrote %s", f.relative_to(HERE.parent))
        for f in generate_java(JAVA_DIR):
            log.info("wrote %s", f.relative_to(HERE.parent))
        if not args.no_jar:
            build_jar(JAVA_DIR, JAR)
            log.info("wrote %s", JAR.relative_to(HERE.parent))
    except GenerateError as exc:
        print(f"telemetry.generate: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
