"""``canon spy [--url URL]``: watch canon's LCM traffic in lcm-spy, with our types decoded.

lcm-spy (Java, shipped in the ``lcm`` wheel) decodes a message when a class with the message's
fingerprint is on its CLASSPATH. This command puts ``telemetry/canon_types.jar`` (or one built into
``~/.cache/canon`` when the ``.lcm`` files changed since it was built, see ``telemetry.generate``)
and the wheel's ``lcm.jar`` there, and replaces itself with lcm-spy.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys

from telemetry.url import DEFAULT_URL


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="machine.toml", help="take the URL from its [telemetry] url")
    parser.add_argument("--url", help=f"LCM URL to watch (default: [telemetry] url, else {DEFAULT_URL})")


def spy_command(url: str) -> tuple[list[str], dict[str, str]]:
    """The lcm-spy command line and environment for ``url``; raises ``UserError`` on a problem."""
    from motiond.cli import UserError
    from telemetry.generate import GenerateError, lcm_share_java, lcm_tool, types_jar
    from telemetry.publisher import TelemetryUnavailable, preflight

    try:
        parsed = preflight(url)
    except TelemetryUnavailable as exc:
        raise UserError(str(exc)) from None
    if shutil.which("java") is None:
        raise UserError("lcm-spy needs a Java runtime and `java` is not on PATH "
                        "(Debian/Ubuntu: apt-get install default-jre)")
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise UserError("lcm-spy opens a window and there is no display (DISPLAY is not set): run it in a "
                        "desktop session, through ssh -X, or under xvfb-run")
    try:
        spy = lcm_tool("lcm-spy")
        jar = types_jar()
    except GenerateError as exc:
        raise UserError(str(exc)) from None
    env = dict(os.environ)
    classpath = [str(jar), str(lcm_share_java() / "lcm.jar")]
    if env.get("CLASSPATH"):
        classpath.append(env["CLASSPATH"])
    env["CLASSPATH"] = os.pathsep.join(classpath)
    return [str(spy), f"--lcm-url={parsed.url}"], env


def resolve_url(args: argparse.Namespace) -> str:
    """``--url``, else ``[telemetry] url`` of ``--config``, else the default URL."""
    if args.url:
        return str(args.url)
    if getattr(args, "config", None):
        from motiond.config import load_machine
        from telemetry.config import TelemetryConfig

        return TelemetryConfig.from_table(load_machine(args.config).telemetry).url
    return DEFAULT_URL


def run(args: argparse.Namespace) -> int:
    argv, env = spy_command(resolve_url(args))
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(argv[0], argv, env)
    return 0  # not reached
