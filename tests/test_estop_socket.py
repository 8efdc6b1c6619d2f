"""The E-stop's own socket (telemetry.estop_socket): the kernel hands it E-stop commands only, so an
E-stop is decided while the ordinary command socket's reader is held up, once, and still through
the server's checks. Joins multicast groups: ``multicast`` (tests/run's namespace)."""

from __future__ import annotations

import os
import random
import threading
import time

import lcm
import pytest
from canopen_helpers import wait_for
from keys import TEST_KEY
from test_telemetry_multicast import Listener

from telemetry.commands import CommandServer, make_command
from telemetry.estop_socket import estop_filter, lcm_payload, open_estop_socket
from telemetry.lcmtypes.canon import command, reply
from telemetry.publisher import CANON_COMMAND, CANON_REPLY
from telemetry.url import parse_url

pytestmark = pytest.mark.multicast


def group_url() -> str:
    group = f"239.79.{random.randint(1, 250)}.{random.randint(1, 250)}"
    return f"udpm://{group}:{random.randint(20000, 60000)}?ttl=0"


def test_the_filter_passes_estop_commands_on_the_channel_and_nothing_else() -> None:
    url = parse_url(group_url())
    sock, why = open_estop_socket(url, CANON_COMMAND, command._get_packed_fingerprint())
    assert sock is not None, why
    sock.settimeout(0.3)
    lc = lcm.LCM(url.url)
    seen: list[tuple[str, str]] = []
    try:
        sends = [
            (CANON_COMMAND, make_command("feed_override", values=[0.5], sender="hmi", key=TEST_KEY).encode()),
            (CANON_COMMAND, make_command("abort", sender="hmi", key=TEST_KEY).encode()),
            (CANON_COMMAND, make_command("estop_reset", sender="hmi", key=TEST_KEY).encode()),
            ("CANON_COMMANDS", make_command("estop", sender="hmi", key=TEST_KEY).encode()),  # other channel
            (CANON_COMMAND, b"\0" * 8 + make_command("estop", sender="hmi").encode()[8:]),  # other type
            (CANON_COMMAND, b"estop"),
            (CANON_COMMAND, make_command("estop", sender="hmi", key=TEST_KEY).encode()),
            (CANON_COMMAND, make_command("estop", sender="x" * 1000, key=TEST_KEY).encode()),
            (CANON_COMMAND, make_command("estop", sender="", key=TEST_KEY).encode()),
        ]
        for channel, data in sends:
            lc.publish(channel, data)
        for _ in range(len(sends)):  # bounded: one read per datagram sent
            try:
                datagram = sock.recv(65536)
            except TimeoutError:
                break
            payload = lcm_payload(datagram, CANON_COMMAND)
            assert payload is not None
            cmd = command.decode(payload)
            seen.append((cmd.verb, cmd.sender))
    finally:
        sock.close()
    assert seen == [("estop", "hmi"), ("estop", "x" * 1000), ("estop", "")]


def test_the_filter_is_a_short_program_with_forward_jumps_only() -> None:
    program = estop_filter(CANON_COMMAND, command._get_packed_fingerprint())
    assert program[-2:] == [(0x06, 0, 0, 0xFFFF), (0x06, 0, 0, 0)]
    for i, (code, jt, jf, _k) in enumerate(program[:-2]):
        assert code != 0x06  # only the last two return
        assert i + 1 + max(jt, jf) < len(program)
    with pytest.raises(ValueError, match="too long"):
        estop_filter("C" * 1000, command._get_packed_fingerprint())


def test_an_estop_is_decided_while_the_command_sockets_reader_is_held_up() -> None:
    """The ordinary socket's reader is stuck in a slow handler for a second (as a reader that fell behind
    a flood would be): an E-stop sent meanwhile is decided at once from its own socket, once."""
    url = group_url()
    lc = lcm.LCM(url)
    decided: list[tuple[str, float]] = []
    notes: list[str] = []
    server = CommandServer(lc, lambda cmd: decided.append((cmd.verb, time.monotonic())) or None,
                           key=TEST_KEY, url=url, on_security=notes.append)
    held = threading.Event()

    def hold(_channel: str, _data: bytes) -> None:
        held.set()
        time.sleep(1.0)

    lc.subscribe("HOLD", hold)
    server.start()
    assert server.estop_listener is not None, server.estop_socket_refused
    client = lcm.LCM(url)
    replies = Listener(url, {CANON_REPLY: reply})
    try:
        time.sleep(0.1)
        client.publish("HOLD", b"x")
        assert held.wait(5)
        for i in range(50):  # queued behind the held reader
            client.publish(CANON_COMMAND, make_command("single_block", values=[0], request_id=100 + i,
                                                       sender="flood", key=TEST_KEY).encode())
        t0 = time.monotonic()
        client.publish(CANON_COMMAND, make_command("estop", request_id=1, sender="op", key=TEST_KEY).encode())
        wait_for(lambda: any(v == "estop" for v, _ in decided), 0.5, step=0.001)
        estop_at = next((t - t0 for v, t in decided if v == "estop"), None)
        replies.wait(CANON_REPLY, 51, 3.0)  # the held reader catches up, the replies arrive
        time.sleep(0.2)
    finally:
        replies.close()
        server.stop()
    assert estop_at is not None and estop_at < 0.5, f"E-stop decided after {estop_at} s"
    assert [v for v, _ in decided].count("estop") == 1  # decided once, not refused as its own replay
    estop_replies = [r for r in replies.got[CANON_REPLY] if r.sender == "op"]
    assert [(r.verb, r.ok) for r in estop_replies] == [("estop", True)]
    assert server.estop_listener is None  # stopped with the server
    assert notes == [], "the second copy of the E-stop was refused (a replay) instead of skipped"


def test_a_forged_estop_on_its_own_socket_is_refused_with_the_reason() -> None:
    url = group_url()
    lc = lcm.LCM(url)
    decided: list[str] = []
    notes: list[str] = []
    server = CommandServer(lc, lambda cmd: decided.append(cmd.verb) or None, key=TEST_KEY, url=url,
                           on_security=notes.append).start()
    client = lcm.LCM(url)
    try:
        client.publish(CANON_COMMAND, make_command("estop", sender="mallory", key=b"\x01" * 32).encode())
        wait_for(lambda: notes != [], 1.0)
    finally:
        server.stop()
    assert decided == []
    assert len(notes) == 1 and "bad MAC" in notes[0]


def test_without_its_url_the_server_takes_estops_from_its_lcm_instance() -> None:
    lc = lcm.LCM("memq://")
    decided: list[str] = []
    server = CommandServer(lc, lambda cmd: decided.append(cmd.verb) or None, key=TEST_KEY).start()
    try:
        assert server.estop_listener is None and "URL" in server.estop_socket_refused
        lc.publish(CANON_COMMAND, make_command("estop", sender="op", key=TEST_KEY).encode())
        wait_for(lambda: decided != [], 1.0)
    finally:
        server.stop()
    assert decided == ["estop"]
    memq = CommandServer(lcm.LCM("memq://"), lambda cmd: None, key=TEST_KEY, url="memq://")
    memq.subscribe()
    try:
        assert memq.estop_listener is None and "udpm" in memq.estop_socket_refused
    finally:
        memq.stop()


def _ranked(priority: int):
    """A thread wrapper that runs the body at SCHED_FIFO ``priority``, as the daemon's stop path does."""
    def wrap(body):
        def run() -> None:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            body()
        return run
    return wrap


def _policy(thread: threading.Thread) -> int:
    assert thread.native_id is not None
    return os.sched_getscheduler(thread.native_id)


def test_a_flood_of_forged_estops_costs_the_estop_thread_its_real_time_rank_until_it_ends() -> None:
    """1,000 forged E-stops in well under a second (an attacker on the LAN): the E-stop socket's thread,
    ranked real-time, reads them at ordinary priority from the 201st on, so the flood does not hold a CPU
    at real-time priority; a real E-stop in the flood is still decided; a quiet second gives the rank
    back."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(3))
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError) as exc:
        pytest.skip(f"SCHED_FIFO not allowed here: {exc}")
    url = group_url()
    lc = lcm.LCM(url)
    decided: list[str] = []
    notes: list[str] = []
    server = CommandServer(lc, lambda cmd: decided.append(cmd.verb) or None, key=TEST_KEY, url=url,
                           on_security=notes.append, estop_thread=_ranked(3)).start()
    listener = server.estop_listener
    assert listener is not None, server.estop_socket_refused
    thread = listener._thread
    client = lcm.LCM(url)
    try:
        assert wait_for(lambda: listener.budget is not None, 2.0)
        assert _policy(thread) == os.SCHED_FIFO
        forged = [make_command("estop", request_id=i, sender="mallory", key=b"\x01" * 32).encode()
                  for i in range(1000)]
        t0 = time.monotonic()
        for i, data in enumerate(forged):
            client.publish(CANON_COMMAND, data)
            if i % 20 == 19:  # in bursts that the socket's buffer holds (a loaded reader keeps up)
                time.sleep(0.002)
        sent_in = time.monotonic() - t0
        assert wait_for(lambda: listener.budget.demoted, 2.0, step=0.001)
        assert _policy(thread) == os.SCHED_OTHER
        real = make_command("estop", request_id=5000, sender="op", key=TEST_KEY)
        client.publish(CANON_COMMAND, real.encode())
        assert wait_for(lambda: "estop" in decided, 3.0)
        # a quiet second gives the rank back
        assert wait_for(lambda: not listener.budget.demoted, 4.0, step=0.01)
        assert _policy(thread) == os.SCHED_FIFO
    finally:
        server.stop()
    assert sent_in < 1.0, f"the flood took {sent_in:.2f} s to send: not a flood"
    assert decided == ["estop"]  # the real one, none of the forged
    assert listener.budget.floods == 1
    assert notes and all("bad MAC" in n or "refus" in n for n in notes), notes[:3]


def test_an_unranked_estop_thread_only_counts_a_flood() -> None:
    url = group_url()
    lc = lcm.LCM(url)
    server = CommandServer(lc, lambda cmd: None, key=TEST_KEY, url=url, on_security=lambda _n: None)
    server.start()
    listener = server.estop_listener
    assert listener is not None, server.estop_socket_refused
    client = lcm.LCM(url)
    try:
        assert wait_for(lambda: listener.budget is not None, 2.0)
        for i in range(400):
            forged = make_command("estop", request_id=i, sender="m", key=b"\x02" * 32)
            client.publish(CANON_COMMAND, forged.encode())
            if i % 20 == 19:
                time.sleep(0.002)
        assert wait_for(lambda: listener.budget.floods == 1, 2.0)
        assert listener.budget.rank is None and _policy(listener._thread) == os.SCHED_OTHER
    finally:
        server.stop()
