"""Publishers, URL rules, signed commands and the command server, on memq:// (no network)."""

from __future__ import annotations

import itertools
import threading
import time
from typing import Any

import lcm
import pytest
from keys import TEST_KEY

from telemetry import publisher
from telemetry.auth import (
    REORDER,
    CommandKeyError,
    RateLimiter,
    Verifier,
    client_key,
    load_or_create_key,
    next_seq,
    sign,
)
from telemetry.commands import VERBS, CommandServer, check_command, make_command
from telemetry.config import TelemetryConfig
from telemetry.lcmtypes.canon import command, event, reply, status
from telemetry.publisher import (
    CANON_COMMAND,
    CANON_EVENT,
    CANON_REPLY,
    CANON_STATUS,
    EventPublisher,
    StatusPublisher,
    TelemetryUnavailable,
    open_lcm,
)
from telemetry.url import DEFAULT_URL, parse_url, url_leaves_host

REAL_LCM = lcm.LCM
LOCAL = "udpm://239.255.76.67:7667?ttl=0"
REMOTE = "udpm://239.255.76.67:7667?ttl=1"


# ---- URLs ---------------------------------------------------------------------------------------

@pytest.mark.parametrize(("url", "leaves"), [
    (DEFAULT_URL, False),
    ("udpm://239.255.76.67:7667", False),          # LCM's TTL defaults to 0
    ("udpm://239.255.76.67:7667?ttl=0&recv_buf_size=2097152", False),
    ("udpm://239.255.76.67:7667?recv_buf_size=2097152&ttl=1", True),
    ("udpm://239.1.2.3:7000?ttl=32", True),
    ("mpudpm://239.255.76.67:7667?ttl=0", False),
    ("mpudpm://239.255.76.67:7667?ttl=2", True),
    ("memq://", False),
    ("file:///tmp/x.log?mode=r", False),
    ("tcpq://127.0.0.1:7700", True),                # the hub may take other hosts
    ("tcpq://10.0.0.5:7700", True),
])
def test_url_leaves_host(url: str, leaves: bool) -> None:
    assert url_leaves_host(url) is leaves


@pytest.mark.parametrize(("url", "complaint"), [
    ("239.255.76.67:7667", "not an LCM URL"),
    ("udp://239.255.76.67:7667", "unknown LCM provider 'udp'"),
    ("udpm://10.1.2.3:7667?ttl=0", "not a multicast address"),
    ("udpm://239.255.76.300:7667", "not an IPv4 address"),
    ("udpm://239.255.76.67:port", "port must be a number"),
    ("udpm://239.255.76.67:7667?ttl=256", "ttl must be a number from 0 to 255"),
    ("udpm://239.255.76.67:7667?ttl=-1", "ttl must be a number from 0 to 255"),
])
def test_bad_urls_say_what_is_wrong(url: str, complaint: str) -> None:
    with pytest.raises(ValueError, match=complaint):
        parse_url(url)


def test_empty_url_means_lcm_default_url_env_then_ours(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("LCM_DEFAULT_URL", raising=False)
    assert parse_url("").url == DEFAULT_URL
    monkeypatch.setenv("LCM_DEFAULT_URL", "udpm://239.9.9.9:9999?ttl=3")
    parsed = parse_url("")
    assert (parsed.group, parsed.port, parsed.ttl, parsed.leaves_host) == ("239.9.9.9", 9999, 3, True)


def test_config_checks_its_keys() -> None:
    assert TelemetryConfig().url == DEFAULT_URL and TelemetryConfig().status_hz == 50
    assert TelemetryConfig(url=REMOTE).leaves_host
    with pytest.raises(ValueError, match=r"telemetry\.url: unknown LCM provider"):
        TelemetryConfig(url="udp://x")
    with pytest.raises(ValueError, match=r"telemetry\.status_hz: must be > 0"):
        TelemetryConfig(status_hz=0)


# ---- signed commands (telemetry.auth) ------------------------------------------------------------

class Clock:
    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def signed(verb: str = "pause", *, key: bytes = TEST_KEY, seq: int | None = None, sender: str = "hmi",
           utime: int | None = None, **kw: Any) -> tuple[Any, bytes]:
    cmd = make_command(verb, sender=sender, **kw)
    if utime is not None:
        cmd.utime = utime
    sign(cmd, key, seq)
    return cmd, cmd.encode()


def test_verifier_accepts_a_signed_command_once() -> None:
    v = Verifier(TEST_KEY)
    cmd, data = signed()
    assert v.check(cmd, data) is None
    again = v.check(command.decode(data), data)
    assert again and again.startswith("replayed command")


def test_verifier_refuses_unsigned_wrong_key_and_altered_commands() -> None:
    v = Verifier(TEST_KEY)
    unsigned = make_command("estop", sender="x")
    assert "unsigned" in (v.check(unsigned, unsigned.encode()) or "")
    cmd, data = signed("estop", key=bytes(32))
    assert "bad MAC" in (v.check(cmd, data) or "")
    cmd, data = signed("feed_override", values=[0.5])
    altered = command.decode(data)
    altered.values = [2.0]
    assert "bad MAC" in (v.check(altered, altered.encode()) or "")
    forged = command.decode(data)
    forged.sender = "someone else"  # the sender (the client id) is covered too
    assert "bad MAC" in (v.check(forged, forged.encode()) or "")


def test_verifier_refuses_stale_and_future_commands() -> None:
    clock = Clock(1_000_000.0)
    v = Verifier(TEST_KEY, window_s=5.0, clock=clock)
    old, data = signed(utime=int((clock.t - 6.0) * 1e6))
    assert (v.check(old, data) or "").startswith("stale command: its time is -6.0 s")
    future, data = signed(utime=int((clock.t + 6.0) * 1e6))
    assert (v.check(future, data) or "").startswith("stale command")
    ok, data = signed(utime=int((clock.t - 4.0) * 1e6))
    assert v.check(ok, data) is None


def test_verifier_sequence_is_per_sender_and_survives_forgetting() -> None:
    clock = Clock(1_000_000.0)
    v = Verifier(TEST_KEY, window_s=5.0, clock=clock)
    now = int(clock.t * 1e6)
    a5, da5 = signed(seq=5, sender="a", utime=now)
    assert v.check(a5, da5) is None
    b1, db1 = signed(seq=1, sender="b", utime=now)
    assert v.check(b1, db1) is None  # another sender's numbers are its own
    a5again, da5again = signed(seq=5, sender="a", utime=now)
    assert "seq 5 from 'a' was seen already" in (v.check(a5again, da5again) or "")
    a4, da4 = signed(seq=4, sender="a", utime=now)
    assert v.check(a4, da4) is None  # taken out of order (an E-stop overtook it): not seen yet
    for seq in range(100, 100 + REORDER):
        c, d = signed(seq=seq, sender="a", utime=now)
        assert v.check(c, d) is None
    a3, da3 = signed(seq=3, sender="a", utime=now)  # below the oldest remembered (5)
    assert "older than the last" in (v.check(a3, da3) or "")
    clock.t += 20.0  # "a" is forgotten; its old message is stale now, so still refused
    assert (v.check(a5, da5) or "").startswith("stale")


def test_next_seq_strictly_increases() -> None:
    seqs = [next_seq() for _ in range(1000)]
    assert all(b > a for a, b in itertools.pairwise(seqs))


def test_key_file_is_created_0640_and_read_back(tmp_path: Any) -> None:
    path = tmp_path / "command.key"
    key = load_or_create_key(path)
    assert len(key) == 32 and oct(path.stat().st_mode & 0o777) == "0o640"
    assert load_or_create_key(path) == key  # the second start reads it
    assert [p.name for p in tmp_path.iterdir()] == ["command.key"]  # no temporary file left


def test_key_file_open_to_others_or_malformed_is_refused(tmp_path: Any) -> None:
    path = tmp_path / "command.key"
    path.write_text(TEST_KEY.hex())
    path.chmod(0o644)
    with pytest.raises(CommandKeyError, match=r"open to other users \(mode 0644\).*chmod 640"):
        load_or_create_key(path)
    path.chmod(0o600)
    path.write_text("not a key\n")
    with pytest.raises(CommandKeyError, match=r"command\.key: not a command key"):
        load_or_create_key(path)


def test_client_key_from_the_environment_or_a_file(tmp_path: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "k"
    path.write_text(bytes(range(32)).hex())
    monkeypatch.setenv("CANON_KEY", TEST_KEY.hex())
    assert client_key(path) == TEST_KEY
    monkeypatch.delenv("CANON_KEY")
    assert client_key(path) == bytes(range(32))
    monkeypatch.setenv("CANON_KEY_FILE", str(path))
    assert client_key() == bytes(range(32))
    monkeypatch.delenv("CANON_KEY_FILE")
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "nowhere"))
    monkeypatch.setattr("telemetry.auth.SYSTEM_KEY_FILE", tmp_path / "none")
    with pytest.raises(CommandKeyError, match=r"no command key.*CANON_KEY_FILE"):
        client_key()


def test_rate_limiter_bucket() -> None:
    clock = Clock(0.0)
    rl = RateLimiter(10.0, 5.0, clock=clock)
    assert [rl.allow("a") for _ in range(7)] == [True] * 5 + [False] * 2
    assert rl.allow("b")  # per key
    clock.t += 0.1
    assert rl.allow("a") and not rl.allow("a")


# ---- command arguments --------------------------------------------------------------------------

def test_every_verb_of_the_issue_is_known() -> None:
    assert set(VERBS) == {"run", "mdi", "pause", "resume", "feed_override", "abort", "estop", "estop_reset",
                          "enable", "disable", "home", "jog", "single_block", "optional_stop",
                          "block_delete", "reset"}


@pytest.mark.parametrize(("verb", "strings", "values", "ok"), [
    ("run", ["part.ngc"], [], True),
    ("run", [], [], False),
    ("mdi", ["G0 X1"], [], True),
    ("feed_override", [], [1.5], True),
    ("feed_override", [], [], False),
    ("feed_override", [], [float("nan")], False),
    ("jog", ["x"], [-5.0], True),
    ("jog", ["x"], [-5.0, 1.0], True),
    ("jog", [], [1.0], False),
    ("home", [], [], True),
    ("home", ["x", "y"], [], True),
    ("single_block", [], [1], True),
    ("pause", ["now"], [], False),
    ("fly", [], [], False),
])
def test_check_command(verb: str, strings: list[str], values: list[float], ok: bool) -> None:
    assert (check_command(make_command(verb, strings, values)) is None) is ok


# ---- open_lcm -----------------------------------------------------------------------------------

def test_open_lcm_memq() -> None:
    assert isinstance(open_lcm("memq://"), lcm.LCM)


def _lcm_fails(monkeypatch: pytest.MonkeyPatch) -> None:
    """As on a host without a multicast route, seen past our own route check."""
    real = lcm.LCM

    def fake(url: str | None = None) -> lcm.LCM:
        if url and url.startswith("udpm"):
            raise RuntimeError("Couldn't create LCM")
        return real(url)

    monkeypatch.setattr(publisher.lcm, "LCM", fake)
    monkeypatch.setattr(publisher, "_multicast_route_problem", lambda parsed: None)


def test_lcm_runtime_error_becomes_a_clear_message_with_the_fix(monkeypatch: pytest.MonkeyPatch) -> None:
    _lcm_fails(monkeypatch)
    with pytest.raises(TelemetryUnavailable) as info:
        open_lcm(DEFAULT_URL)
    text = str(info.value)
    assert DEFAULT_URL in text
    assert "ip link set lo multicast on" in text and "ip route add 224.0.0.0/4 dev lo" in text
    assert 'url = "memq://"' in text


def test_fallbacks_for_canon_run(monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    _lcm_fails(monkeypatch)
    with caplog.at_level("WARNING"):
        memq = open_lcm(DEFAULT_URL, fallback="memq")
        none = open_lcm(DEFAULT_URL, fallback="none")
    assert isinstance(memq, REAL_LCM) and none is None
    assert "ip route add 224.0.0.0/4 dev lo" in caplog.text and "memq://" in caplog.text
    assert "without telemetry" in caplog.text


def test_bad_url_is_telemetry_unavailable_naming_the_problem() -> None:
    with pytest.raises(TelemetryUnavailable, match="not a multicast address"):
        open_lcm("udpm://127.0.0.1:7667")
    assert open_lcm("udpm://127.0.0.1:7667", fallback="none") is None


# ---- status publisher ---------------------------------------------------------------------------

class Receiver:
    """Subscribes on a memq:// instance and handles it on a thread, collecting decoded messages."""

    def __init__(self, lc: lcm.LCM, channel: str, cls: Any) -> None:
        self.lc, self.cls = lc, cls
        self.messages: list[Any] = []
        self.times: list[float] = []
        self.sub = lc.subscribe(channel, self._on)
        self.sub.set_queue_capacity(10_000)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _on(self, channel: str, data: bytes) -> None:
        self.messages.append(self.cls.decode(data))
        self.times.append(time.monotonic())

    def _loop(self) -> None:
        while not self._stop.is_set():
            self.lc.handle_timeout(20)

    def wait_for(self, n: int, timeout: float = 5.0) -> None:
        end = time.monotonic() + timeout
        while len(self.messages) < n and time.monotonic() < end:
            time.sleep(0.01)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)


@pytest.fixture
def memq() -> lcm.LCM:
    return lcm.LCM("memq://")


def snapshot(seq: int) -> status:
    s = status()
    s.seq = seq
    s.state = "running"
    return s


@pytest.mark.parametrize("rate_hz", [10.0, 50.0])
def test_status_published_at_the_configured_rate(memq: lcm.LCM, rate_hz: float) -> None:
    rx = Receiver(memq, CANON_STATUS, status)
    pub = StatusPublisher(memq, rate_hz)
    pub.update(snapshot(1))
    try:
        with pub:
            time.sleep(1.0)
    finally:
        rx.wait_for(pub.published, 1.0)
        rx.close()
    n = len(rx.messages)
    # a generous band: the machine is shared; what matters is that the count follows the rate
    assert 0.5 * rate_hz <= n <= 1.2 * rate_hz + 2, n
    assert all(m.seq == 1 for m in rx.messages)
    gaps = [b - a for a, b in zip(rx.times, rx.times[1:], strict=False)]
    assert sorted(gaps)[len(gaps) // 2] == pytest.approx(1 / rate_hz, rel=0.5)


def test_nothing_published_before_the_first_snapshot(memq: lcm.LCM) -> None:
    rx = Receiver(memq, CANON_STATUS, status)
    with StatusPublisher(memq, 100) as pub:
        time.sleep(0.2)
    rx.close()
    assert pub.published == 0 and rx.messages == []


def test_latest_snapshot_wins(memq: lcm.LCM) -> None:
    rx = Receiver(memq, CANON_STATUS, status)
    with StatusPublisher(memq, 100) as pub:
        for seq in range(1, 2001):
            pub.update(snapshot(seq))
        deadline = time.monotonic() + 3
        while (not rx.messages or rx.messages[-1].seq != 2000) and time.monotonic() < deadline:
            time.sleep(0.01)
    rx.close()
    seqs = [m.seq for m in rx.messages]
    assert seqs and seqs[-1] == 2000
    assert seqs == sorted(seqs)         # never an older snapshot after a newer one
    assert len(seqs) < 2000             # snapshots between two periods are skipped, not queued


class BlockingLCM:
    """An LCM stand-in whose publish hangs until released: a stalled network."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.calls = 0

    def publish(self, channel: str, data: bytes) -> None:
        self.calls += 1
        self.release.wait(5)


def test_update_never_blocks_even_when_publishing_hangs() -> None:
    lc = BlockingLCM()
    pub = StatusPublisher(lc, 200)  # type: ignore[arg-type]
    pub.update(snapshot(0))
    pub.start()
    try:
        deadline = time.monotonic() + 2
        while lc.calls == 0 and time.monotonic() < deadline:
            time.sleep(0.005)
        assert lc.calls == 1  # the thread is stuck in publish
        t0 = time.perf_counter()
        for seq in range(1, 10_001):
            pub.update(snapshot(seq))
        elapsed = time.perf_counter() - t0
        assert elapsed < 1.0  # 10,000 swaps; a blocking update would take 10,000 x 5 s
        assert pub.latest.seq == 10_000
    finally:
        lc.release.set()
        pub.stop()


def test_a_bad_snapshot_is_counted_and_the_thread_goes_on(memq: lcm.LCM,
                                                         caplog: pytest.LogCaptureFixture) -> None:
    rx = Receiver(memq, CANON_STATUS, status)
    bad = snapshot(1)
    bad.num_axes = 2  # arrays are empty
    with caplog.at_level("ERROR"), StatusPublisher(memq, 100) as pub:
        pub.update(bad)
        time.sleep(0.1)
        pub.update(snapshot(2))
        rx.wait_for(1, 2.0)
    rx.close()
    assert pub.errors >= 1 and caplog.text.count("cannot publish status") == 1
    assert rx.messages and rx.messages[-1].seq == 2


def test_rate_is_checked() -> None:
    with pytest.raises(ValueError, match="status rate"):
        StatusPublisher(None, 0)


def test_publishers_without_lcm_do_nothing() -> None:
    with StatusPublisher(None) as sp, EventPublisher(None) as ep:
        sp.update(snapshot(1))
        assert ep.emit(event.INFO, "hello") is False
    assert sp.published == 0 and ep.published == 0


# ---- event publisher ----------------------------------------------------------------------------

def test_events_published_in_order_with_seq_and_source_line(memq: lcm.LCM) -> None:
    rx = Receiver(memq, CANON_EVENT, event)
    with EventPublisher(memq) as pub:
        for i in range(1, 51):
            assert pub.emit(event.WARNING, f"event {i}", kind="message", source="gcode", file="a.ngc", line=i)
        rx.wait_for(50)
    rx.close()
    assert [m.seq for m in rx.messages] == list(range(1, 51))
    last = rx.messages[-1]
    assert (last.severity, last.kind, last.source, last.file, last.line, last.text) == (
        event.WARNING, "message", "gcode", "a.ngc", 50, "event 50")
    assert abs(last.utime / 1e6 - time.time()) < 60


def test_full_event_queue_drops_and_counts_without_blocking() -> None:
    lc = BlockingLCM()
    pub = EventPublisher(lc, maxsize=10).start()  # type: ignore[arg-type]
    try:
        t0 = time.perf_counter()
        results = [pub.emit(event.INFO, f"e{i}") for i in range(100)]
        elapsed = time.perf_counter() - t0
    finally:
        lc.release.set()
        pub.stop()
    assert elapsed < 1.0
    # one event is held by the stuck publish call, ten wait in the queue, the rest are dropped
    assert pub.dropped == results.count(False)
    assert 100 - 11 <= pub.dropped <= 100 - 10


# ---- command server -----------------------------------------------------------------------------

def test_command_server_answers_signed_commands_on_memq(memq: lcm.LCM) -> None:
    seen: list[str] = []

    def handler(cmd: Any) -> str | None:
        seen.append(cmd.verb)
        return "not homed" if cmd.verb == "run" else None

    replies = Receiver(memq, CANON_REPLY, reply)
    replies.close()  # the server's thread handles this instance
    server = CommandServer(memq, handler, key=TEST_KEY, url="memq://").start()
    try:
        for i, (verb, strings, values) in enumerate([("pause", [], []), ("run", ["p.ngc"], []),
                                                     ("fly", [], []), ("feed_override", [], [0.5])]):
            cmd = make_command(verb, strings, values, request_id=i + 1, sender="t", key=TEST_KEY)
            memq.publish(CANON_COMMAND, cmd.encode())
        replies.wait_for(4)
    finally:
        server.stop()
    got = {r.request_id: (r.verb, r.ok, r.error, r.sender) for r in replies.messages}
    assert got[1] == ("pause", True, "", "t")
    assert got[2] == ("run", False, "not homed", "t")
    assert got[3][1] is False and "unknown verb" in got[3][2]
    assert got[4][:2] == ("feed_override", True)
    assert sorted(seen) == ["feed_override", "pause", "run"]  # urgent verbs take their own way


def test_command_server_refuses_unauthenticated_commands_with_a_security_event(memq: lcm.LCM) -> None:
    calls: list[Any] = []
    notes: list[str] = []
    server = CommandServer(memq, calls.append, key=TEST_KEY, url="memq://", on_security=notes.append)
    refused = server.answer(make_command("estop", request_id=5, sender="lan"))
    accepted = server.answer(make_command("estop", request_id=6, sender="op", key=TEST_KEY))
    assert (refused.ok, accepted.ok) == (False, True)
    assert refused.error.startswith("refused: unsigned command") and server.refused == 1
    assert len(calls) == 1 and len(notes) == 1 and "'lan'" in notes[0]


def test_command_server_rate_limits_refusal_replies(memq: lcm.LCM) -> None:
    notes: list[str] = []
    server = CommandServer(memq, lambda c: None, key=TEST_KEY, on_security=notes.append, refusal_rate=5)
    answered = [server.answer(make_command("estop", request_id=i, key=bytes(32))) for i in range(100)]
    sent = [r for r in answered if r is not None]
    assert 10 <= len(sent) <= 12 and server.refused == 100  # a burst of 2 s worth, then the rate
    assert server.unanswered == 100 - len(sent) and len(notes) == len(sent)


def test_command_server_ignores_foreign_messages(memq: lcm.LCM) -> None:
    server = CommandServer(memq, lambda c: None, key=TEST_KEY, url="memq://")
    server.on_message(CANON_COMMAND, reply().encode())
    assert server.bad_messages == 1 and server.replies == 0


def test_config_from_a_table_names_file_and_key() -> None:
    from motiond.configkit import ConfigError, Table

    cfg = TelemetryConfig.from_table(Table({"url": "memq://", "status_hz": 20, "key_file": "k.key"},
                                           "/m/m.toml", "telemetry"))
    assert (cfg.url, cfg.status_hz, cfg.key_file, cfg.event_queue) == ("memq://", 20.0, "/m/k.key", 1000)
    with pytest.raises(ConfigError, match=r"^m\.toml: telemetry\.token: no longer used: commands are signed"):
        TelemetryConfig.from_table(Table({"token": "s3cret"}, "m.toml", "telemetry"))
    assert TelemetryConfig.from_table(Table({}, "m.toml", "telemetry")) == TelemetryConfig()
    with pytest.raises(ConfigError, match=r"^m\.toml: telemetry\.status_hz: must be > 0"):
        TelemetryConfig.from_table(Table({"status_hz": -1}, "m.toml", "telemetry"))
    with pytest.raises(ConfigError, match=r"^m\.toml: telemetry\.rate: unknown key"):
        TelemetryConfig.from_table(Table({"rate": 5}, "m.toml", "telemetry"))


def test_command_server_survives_an_lcm_error() -> None:
    """A failure inside LCM handling is counted and logged; the server thread keeps serving."""
    import time

    from telemetry.commands import CommandServer

    class FlakyLcm:
        def __init__(self) -> None:
            self.calls = 0

        def subscribe(self, channel: str, callback: object) -> object:
            return object()

        def unsubscribe(self, sub: object) -> None:
            pass

        def handle_timeout(self, ms: int) -> int:
            self.calls += 1
            if self.calls == 1:
                raise OSError("lcm_handle_timeout() returned -1")
            time.sleep(ms / 1000)
            return 0

    lc = FlakyLcm()
    server = CommandServer(lc, lambda cmd: None, key=TEST_KEY, url="memq://").start()
    try:
        deadline = time.monotonic() + 5
        while lc.calls < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert server.errors == 1
        assert lc.calls >= 3
        assert server._thread is not None and server._thread.is_alive()
    finally:
        server.stop()


def test_with_receive_buffer_caps_at_the_kernel_limit(tmp_path: Any) -> None:
    from telemetry.url import with_receive_buffer

    rmem = tmp_path / "rmem_max"
    rmem.write_text("212992\n")
    assert with_receive_buffer(LOCAL, rmem_max_file=str(rmem)) == LOCAL + "&recv_buf_size=212992"
    assert with_receive_buffer(LOCAL, 1000, rmem_max_file=str(rmem)) == LOCAL + "&recv_buf_size=1000"
    given = LOCAL + "&recv_buf_size=5"
    assert with_receive_buffer(given, rmem_max_file=str(rmem)) == given
    assert with_receive_buffer("memq://") == "memq://"


def test_estop_and_urgent_verbs_never_wait_behind_other_commands(memq: lcm.LCM) -> None:
    """A handler stuck on an ordinary verb (a slow 'run') holds neither the E-stop nor a feed hold."""
    release = threading.Event()
    done: list[str] = []

    def handler(cmd: Any) -> str | None:
        if cmd.verb == "run":
            release.wait(10)
        done.append(cmd.verb)
        return None

    replies = Receiver(memq, CANON_REPLY, reply)
    replies.close()
    server = CommandServer(memq, handler, key=TEST_KEY).start()
    try:
        for i, (verb, strings) in enumerate([("run", ["a.ngc"]), ("mdi", ["G0 X1"]), ("pause", []),
                                             ("estop", [])]):
            memq.publish(CANON_COMMAND, make_command(verb, strings, request_id=i + 1, sender="c",
                                                     key=TEST_KEY).encode())
        replies.wait_for(2)
        first = sorted(r.verb for r in replies.messages)
        release.set()
        replies.wait_for(4)
    finally:
        release.set()
        server.stop()
    # while run (and mdi behind it) were still waiting
    assert first == ["estop", "pause"], [(r.verb, r.error) for r in replies.messages]
    assert done[-2:] == ["run", "mdi"]


def test_ordinary_verbs_are_rate_limited_per_sender_with_a_reply(memq: lcm.LCM) -> None:
    from telemetry.commands import COMMANDS_PER_S

    calls: list[str] = []
    server = CommandServer(memq, lambda c: calls.append(c.sender), key=TEST_KEY)
    replies = Receiver(memq, CANON_REPLY, reply)
    try:
        server.subscribe()
        n = int(4 * COMMANDS_PER_S)
        for i in range(n):
            for sender in ("a", "b"):
                memq.publish(CANON_COMMAND, make_command("single_block", values=[1], request_id=i,
                                                         sender=sender, key=TEST_KEY).encode())
        for i in range(40):  # urgent verbs are never rate-limited (40: fewer than a lane holds)
            memq.publish(CANON_COMMAND, make_command("feed_override", values=[1], request_id=1000 + i,
                                                     sender="a", key=TEST_KEY).encode())
        replies.wait_for(2 * n + 40)
    finally:
        server.stop()
        replies.close()
    limited = [r for r in replies.messages if r.error.startswith("refused: rate limit")]
    assert {r.sender for r in limited} == {"a", "b"} and all(r.verb == "single_block" for r in limited)
    assert len(replies.messages) == 2 * n + 40  # every command answered
    assert all(r.ok for r in replies.messages if r.verb == "feed_override")
