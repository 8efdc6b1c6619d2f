"""``canon ctl VERB [ARGS...]``: send one command to the running daemon over LCM and print its reply.

The arguments after the verb are split as the verb takes them (docs/telemetry.md): its text
arguments first (program file, MDI line, axis letters), then its numbers. ``canon ctl mdi G0 X10``
joins the words into one MDI line. The command is checked here before it is sent, so a typo gets the
list of verbs at once rather than a refusal from the daemon.

The daemon carries out ``enable``, ``disable``, ``estop_reset``, ``reset`` and ``home`` on a thread
of its own (they talk to the drives for up to tens of seconds, and its command channel must stay free
for an E-stop): it replies that it accepted them, and reports the result as an event. ``canon ctl``
waits for that result (``--wait``, 120 s by default) and prints it, so ``canon ctl home`` still says
whether the machine homed.

Every command is signed with the daemon's command key (docs/telemetry.md), read from ``--key-file``,
``$CANON_KEY``, ``$CANON_KEY_FILE``, the ``--config`` file's ``[telemetry] key_file`` or the default
places, never from the command line (``--token`` is refused and says so).

Exit status: 0 the daemon accepted the command (and, for the verbs above, carried it out), 1 it
refused it or the operation failed (or the command line is wrong), 3 no reply within ``--timeout``
(the daemon is not running, or listens on another URL), or no result within ``--wait``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

from motiond.control_client import RESULT_TIMEOUT_S, SERVICE_VERBS
from telemetry.commands import VERBS
from telemetry.url import DEFAULT_URL

EXIT_OK = 0
EXIT_REFUSED = 1
EXIT_NO_REPLY = 3

# How each verb is written on the command line (telemetry.commands.VERBS holds the rules).
SYNOPSIS: dict[str, str] = {
    "run": "FILE [LINE]",
    "mdi": "'G-CODE LINE'",
    "feed_override": "FACTOR",
    "home": "[AXIS ...]",
    "jog": "AXIS VELOCITY [DISTANCE]",
    "single_block": "1|0",
    "optional_stop": "1|0",
    "block_delete": "1|0",
}
_SWITCH_WORDS = {"on": 1.0, "off": 0.0, "true": 1.0, "false": 0.0, "yes": 1.0, "no": 0.0}


def synopsis(verb: str) -> str:
    """``VERB ARGS`` as typed after ``canon ctl``."""
    if verb in SYNOPSIS:
        return f"{verb} {SYNOPSIS[verb]}"
    spec = VERBS[verb]
    words = ["TEXT"] * spec.strings[0] + ["[TEXT]"] * (spec.strings[1] - spec.strings[0])
    words += ["NUMBER"] * spec.values[0] + ["[NUMBER]"] * (spec.values[1] - spec.values[0])
    return " ".join([verb, *words])


def verbs_table() -> str:
    """Every verb with its arguments and what it does, one per line."""
    rows = [(synopsis(v), spec.help) for v, spec in VERBS.items()]
    width = max(len(s) for s, _ in rows)
    return "\n".join(f"  {s:<{width}}  {h}" for s, h in rows)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = ("verbs:\n" + verbs_table() + "\n\nexit status: 0 accepted (and done, for "
                     f"{', '.join(sorted(SERVICE_VERBS))}), 1 refused, failed or a wrong command line, 3 no "
                     "reply within --timeout or no result within --wait")
    parser.add_argument("verb", nargs="?", metavar="VERB", help="what to do (listed below)")
    parser.add_argument("arguments", nargs="*", metavar="ARGS", help="the verb's arguments")
    parser.add_argument("--config", metavar="machine.toml",
                        help="take the URL and the token from its [telemetry] table")
    parser.add_argument("--url", help=f"LCM URL of the daemon (default: [telemetry] url, else {DEFAULT_URL})")
    parser.add_argument("--key-file", metavar="FILE",
                        help="the daemon's command key file (default: $CANON_KEY, $CANON_KEY_FILE, the "
                             "--config file's [telemetry] key_file, ~/.local/state/canon/command.key, "
                             "/var/lib/canon/command.key); never the key itself on the command line")
    parser.add_argument("--token", help=argparse.SUPPRESS)  # removed: refused with the new way
    parser.add_argument("--timeout", type=float, default=5.0, metavar="S",
                        help="seconds to wait for the reply (default 5)")
    parser.add_argument("--wait", type=float, default=RESULT_TIMEOUT_S, metavar="S",
                        help=f"seconds to wait for the result of {', '.join(sorted(SERVICE_VERBS))} "
                             f"(default {RESULT_TIMEOUT_S:g}; 0: print that it was accepted and return)")
    parser.add_argument("--json", action="store_true", help="print the reply as JSON")


def _usage_error(message: str, verb: str | None = None) -> Exception:
    from motiond.cli import UserError

    if verb in VERBS:
        return UserError(f"{message}\nusage: canon ctl {synopsis(verb)}   ({VERBS[verb].help})")
    return UserError(f"{message}\nusage: canon ctl VERB [ARGS...]; verbs:\n{verbs_table()}")


def split_arguments(verb: str, words: list[str]) -> tuple[list[str], list[float]]:
    """The command-line words after ``verb`` as the command's ``strings`` and ``values``.

    Raises ``UserError`` (with the verb's usage) for an unknown verb, a word that should be a number
    and is not, or the wrong number of arguments.
    """
    spec = VERBS.get(verb)
    if spec is None:
        raise _usage_error(f"unknown verb {verb!r}", verb)
    if verb == "mdi":
        return ([" ".join(words)] if words else []), []
    n_strings = min(len(words), spec.strings[1])
    strings, rest = words[:n_strings], words[n_strings:]
    values: list[float] = []
    for word in rest:
        if verb in ("single_block", "optional_stop", "block_delete") and word.lower() in _SWITCH_WORDS:
            values.append(_SWITCH_WORDS[word.lower()])
            continue
        try:
            value = float(word)
        except ValueError:
            raise _usage_error(f"{verb}: {word!r} is not a number", verb) from None
        if not math.isfinite(value):
            raise _usage_error(f"{verb}: {word!r} is not a finite number", verb)
        values.append(value)
    lo, hi = spec.strings
    if not lo <= len(strings) <= hi or not spec.values[0] <= len(values) <= spec.values[1]:
        raise _usage_error(f"{verb}: wrong number of arguments ({len(words)} given)", verb)
    if verb == "run" and values and (values[0] < 1 or values[0] != int(values[0])):
        # the daemon would truncate 2.5 to 2: a start line is a whole line number, said here at once
        raise _usage_error(f"run: the start line must be a line number (1 or more), got {rest[0]!r}", verb)
    return strings, values


def resolve(args: argparse.Namespace) -> tuple[str, bytes]:
    """The URL (``--url``, else the ``--config`` file's, else the default) and the command key
    (``--key-file``, else :func:`telemetry.auth.client_key`: ``$CANON_KEY``, ``$CANON_KEY_FILE``, the
    ``--config`` file's ``key_file``, the default places)."""
    from motiond.cli import UserError
    from telemetry.auth import ENV_KEY_FILE, CommandKeyError, client_key, read_key

    if args.token is not None:
        raise UserError("--token is no longer accepted (a secret on the command line is visible to every "
                        "user): commands are signed with the daemon's command key; give its file with "
                        f"--key-file FILE, ${ENV_KEY_FILE} or --config (docs/telemetry.md)")
    url, config_key_file = args.url, None
    if getattr(args, "config", None):
        from motiond.config import load_machine
        from telemetry.config import TelemetryConfig

        cfg = TelemetryConfig.from_table(load_machine(args.config).telemetry)
        url = url if url is not None else cfg.url
        config_key_file = cfg.key_file or None
    try:  # --key-file, else $CANON_KEY, $CANON_KEY_FILE, the machine file's, the default places
        key = read_key(args.key_file) if args.key_file else client_key(config_key_file)
    except CommandKeyError as exc:
        raise UserError(str(exc)) from None
    return (url or DEFAULT_URL), key


def run(args: argparse.Namespace) -> int:
    from motiond.cli import UserError
    from motiond.control_client import (
        CommandError,
        NoReply,
        NoResult,
        client_lcm,
        no_answer_message,
        send_command,
    )
    from telemetry.publisher import TelemetryUnavailable

    if args.verb is None:
        raise _usage_error("which verb?")
    strings, values = split_arguments(args.verb, list(args.arguments))
    if not (math.isfinite(args.timeout) and args.timeout > 0):
        raise UserError(f"--timeout must be a number of seconds > 0, got {args.timeout:g}")
    if not (math.isfinite(args.wait) and args.wait >= 0):
        raise UserError(f"--wait must be a number of seconds >= 0, got {args.wait:g}")
    url, key = resolve(args)
    try:
        lc = client_lcm(url)
    except TelemetryUnavailable as exc:
        raise UserError(str(exc)) from None
    try:
        reply = send_command(lc, args.verb, strings, values, key, args.timeout, wait_result=args.wait)
    except CommandError as exc:
        raise _usage_error(str(exc), args.verb) from None
    except NoReply:
        print(f"canon ctl: {no_answer_message(f'reply to {args.verb!r}', url, args.timeout)}",
              file=sys.stderr)
        return EXIT_NO_REPLY
    except NoResult as exc:
        print(f"canon ctl: {exc}", file=sys.stderr)
        return EXIT_NO_REPLY
    if args.json:
        print(json.dumps(reply.to_dict()))
    elif reply.ok:
        accepted_only = args.verb in SERVICE_VERBS and args.wait == 0
        print(f"{reply.verb}: {'accepted' if accepted_only else 'ok'}")
    if not reply.ok:
        if not args.json:
            print(f"canon ctl: {reply.verb}: {reply.error}", file=sys.stderr)
        return EXIT_REFUSED
    return EXIT_OK
