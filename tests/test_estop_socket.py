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


def _flood(client: lcm.LCM, n: int, key: bytes) -> float:
    """``n`` forged E-stops in bursts of 20 that the socket's buffer holds; the seconds it took."""
    t0 = time.monotonic()
    for i in range(n):
        client.publish(CANON_COMMAND, make_command("estop", request_id=i, sender="mallory", key=key).encode())
        if i % 20 == 19:
            time.sleep(0.002)
    return time.monotonic() - t0


def _can_rank() -> None:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(3))
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError) as exc:
        pytest.skip(f"SCHED_FIFO not allowed here: {exc}")


def _ranked_server(url: str, cpu_budget: float | None = None):
    lc = lcm.LCM(url)
    decided: list[tuple[str, float]] = []
    notes: list[str] = []
    server = CommandServer(lc, lambda cmd: decided.append((cmd.verb, time.monotonic())) or None,
                           key=TEST_KEY, url=url, on_security=notes.append, estop_thread=_ranked(3),
                           estop_cpu_budget=cpu_budget).start()
    return server, decided, notes


def _listening(server: CommandServer, url: str):
    """The server's E-stop listener once its thread counts (ranked, if it is), and a client to flood it."""
    listener = server.estop_listener
    assert listener is not None, server.estop_socket_refused
    assert wait_for(lambda: listener.budget is not None, 2.0)
    return listener, lcm.LCM(url)


def test_a_thousand_forged_estops_keep_the_estop_thread_real_time() -> None:
    """A flood that costs the ranked E-stop thread a few percent of a CPU: it stays real-time, reads
    them all, and a real E-stop right after them is decided at once."""
    _can_rank()
    url = group_url()
    server, decided, _notes = _ranked_server(url)
    try:
        listener, client = _listening(server, url)
        _flood(client, 1000, b"\x01" * 32)
        t0 = time.monotonic()
        client.publish(CANON_COMMAND, _real_estop())
        assert wait_for(lambda: decided != [], 2.0, step=0.001)
        policy = _policy(listener._thread)
    finally:
        server.stop()
    assert [v for v, _ in decided] == ["estop"]
    assert decided[0][1] - t0 < 0.25, f"E-stop decided {decided[0][1] - t0:.3f} s after it was sent"
    assert listener.budget.floods == 0 and policy == os.SCHED_FIFO


def test_a_flood_past_its_cpu_budget_costs_the_estop_thread_its_rank_until_it_ends() -> None:
    """A flood that takes the E-stop thread past its CPU budget (here 5 ms a second, so that a test can
    reach it: the default is 0.3 s, some 20,000 datagrams a second): it reads the rest at
    ordinary priority, a real E-stop among them is still decided, and a quiet second gives the rank
    back."""
    _can_rank()
    url = group_url()
    server, decided, notes = _ranked_server(url, cpu_budget=0.005)
    try:
        listener, client = _listening(server, url)
        thread = listener._thread
        assert _policy(thread) == os.SCHED_FIFO
        _flood(client, 1000, b"\x01" * 32)
        assert wait_for(lambda: listener.budget.demoted, 2.0, step=0.001)
        assert _policy(thread) == os.SCHED_OTHER
        client.publish(CANON_COMMAND, _real_estop())
        assert wait_for(lambda: decided != [], 5.0)
        # a quiet second gives the rank back
        assert wait_for(lambda: not listener.budget.demoted, 4.0, step=0.01)
        assert _policy(thread) == os.SCHED_FIFO
    finally:
        server.stop()
    assert [v for v, _ in decided] == ["estop"]  # the real one, none of the forged
    assert listener.budget.floods == 1
    assert notes and all("bad MAC" in n for n in notes), notes[:3]


def test_an_unranked_estop_thread_only_counts_a_flood() -> None:
    url = group_url()
    server = CommandServer(lcm.LCM(url), lambda cmd: None, key=TEST_KEY, url=url, on_security=lambda _n: None,
                           estop_cpu_budget=0.005).start()
    try:
        listener, client = _listening(server, url)
        _flood(client, 1000, b"\x02" * 32)
        assert wait_for(lambda: listener.budget.floods == 1, 2.0)
        assert listener.budget.rank is None and _policy(listener._thread) == os.SCHED_OTHER
    finally:
        server.stop()


def _real_estop() -> bytes:
    return make_command("estop", request_id=5000, sender="op", key=TEST_KEY).encode()
