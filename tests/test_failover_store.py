"""The session store on a real Redis: checkpoints, hand-over, look-ups, failures, resends.

Servers run in this process on loopback ports; Redis is Debian's ``redis-server`` started for
the module (the tests skip, naming the package, where it is not installed).
"""

from __future__ import annotations

import contextlib
import json
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest
from failover_util import free_port, redis_server
from grpc_health.v1 import health_pb2, health_pb2_grpc
from online_helpers import DriveSpec, drive
from service_util import city, local_config, requests, running, stub

from mapmatch.online import OnlineMatcher
from mapmatch.types import State
from service import convert
from service.client import MapMatchClient
from service.config import ServerConfig, config_from, read_config_file
from service.gen import mapmatch_pb2 as pb
from service.server import start_server
from service.store import pack, session_key, unpack
from service.store_checkpoints import STORE_HEALTH

redis = pytest.importorskip("redis", reason="needs the redis client: pip install 'mapmatch[redis]'")

AMAP = city()
FIXES = drive(AMAP, "abcfedghd", DriveSpec(speed=10.0, dt=1.0, sigma=3.0))  # 40-odd fixes round the city


@pytest.fixture(scope="module")
def redis_port(tmp_path_factory: pytest.TempPathFactory) -> Iterator[int]:
    with redis_server(tmp_path_factory.mktemp("redis")) as port:
        yield port


@pytest.fixture
def db(redis_port: int) -> Iterator[redis.Redis]:
    r = redis.Redis(port=redis_port)
    r.flushall()
    yield r
    r.close()


def store_config(port: int, **kw: object) -> ServerConfig:
    # a look-up bound far above a loaded machine's scheduling delay: these tests are about a
    # store that answers (the bound itself is tested against a store that does not)
    kw.setdefault("store_timeout", 5.0)
    return local_config(session_store=f"redis://127.0.0.1:{port}/0", checkpoint_interval=0.1, **kw)


def reference() -> list[pb.SnapResult]:
    """The drive's answers from one uninterrupted session in process."""
    m = OnlineMatcher(AMAP.graph)
    st = m.new_session()
    return [convert.snap_result_to_proto(m.update(st, f)) for f in FIXES]


def record_time(db: redis.Redis, checksum: str, vid: str) -> float | None:
    data = db.get(session_key(checksum, vid))
    return None if data is None else float(json.loads(unpack(data)[0])["time"])


def wait_until(cond, what: str, timeout: float = 20.0) -> None:  # type: ignore[no-untyped-def]
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"not within {timeout} s: {what}")
        time.sleep(0.02)


def health(port: int, name: str) -> int:
    with grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
        return int(
            health_pb2_grpc.HealthStub(ch)
            .Check(health_pb2.HealthCheckRequest(service=name), timeout=5)
            .status
        )


SERVING = health_pb2.HealthCheckResponse.SERVING
NOT_SERVING = health_pb2.HealthCheckResponse.NOT_SERVING


def stream(port: int, reqs: list[pb.FixRequest]) -> list[pb.SnapResponse]:
    ch, api = stub(port)
    with contextlib.closing(ch):
        return list(api.StreamFixes(iter(reqs), timeout=30))


# ---------------------------------------------------------------------------------- tests
def test_a_stream_hands_its_vehicle_over_and_another_server_resumes_it(db, redis_port):
    half = len(FIXES) // 2
    ref = reference()
    reqs = requests(FIXES, "v1")
    with running(store_config(redis_port), {"city": AMAP.graph}) as (a, pa):
        first = stream(pa, reqs[:half])
        checksum = a.maps.get("city").checksum
        # the stream ended: the session was written and dropped from this process
        wait_until(lambda: a.checkpoints.counters.handed_over == 1, "hand-over")
        assert a.sessions.count() == 0
        assert record_time(db, checksum, "v1") == FIXES[half - 1].time
    with running(store_config(redis_port), {"city": AMAP.graph}) as (b, pb_):
        second = stream(pb_, reqs[half:])
        assert b.checkpoints.counters.restored == 1 and b.checkpoints.counters.misses == 0
    got = [r.result for r in first + second]
    assert all(not r.HasField("error") for r in first + second)
    # the same answers as one uninterrupted session: nothing was lost or started afresh
    assert [r.edge for r in got] == [r.edge for r in ref]
    assert [r.state for r in got] == [r.state for r in ref]


def test_a_server_with_an_open_stream_writes_checkpoints_behind_the_answers(db, redis_port):
    with running(store_config(redis_port), {"city": AMAP.graph}) as (srv, port):
        checksum = srv.maps.get("city").checksum
        ch, api = stub(port)
        with contextlib.closing(ch):
            for f in FIXES[:10]:  # unary calls: no stream end, only the periodic passes
                api.SnapFix(requests([f], "u1")[0], timeout=10)
            # the pass counts its write after Redis answers it: wait for both
            wait_until(
                lambda: (
                    record_time(db, checksum, "u1") == FIXES[9].time and srv.checkpoints.counters.written >= 1
                ),
                "checkpoint",
            )
        ttl = db.pttl(session_key(checksum, "u1"))
        assert 0 < ttl <= srv.config.session_ttl * 1000  # the record lives as long as the session
        c = srv.checkpoints.counters
        assert c.written >= 1 and c.write_failures == 0 and c.lookups == 1 and c.misses == 1
        assert health(port, STORE_HEALTH) == SERVING


def test_end_session_removes_the_record(db, redis_port):
    with running(store_config(redis_port), {"city": AMAP.graph}) as (srv, port):
        checksum = srv.maps.get("city").checksum
        ch, api = stub(port)
        with contextlib.closing(ch):
            api.SnapFix(requests(FIXES[:1], "gone")[0], timeout=10)
            wait_until(lambda: db.exists(session_key(checksum, "gone")) == 1, "checkpoint")
            assert api.EndSession(pb.EndSessionRequest(vehicle_id="gone"), timeout=10).existed
            wait_until(lambda: db.exists(session_key(checksum, "gone")) == 0, "delete")


def test_a_store_that_is_down_fails_no_fix_and_health_says_so(redis_port, tmp_path):
    dead = free_port()  # nothing listens here yet
    cfg = local_config(session_store=f"redis://127.0.0.1:{dead}/0", checkpoint_interval=0.1)
    with running(cfg, {"city": AMAP.graph}) as (srv, port):
        out = stream(port, requests(FIXES[:10], "v-down"))
        assert all(not r.HasField("error") for r in out)
        wait_until(lambda: health(port, STORE_HEALTH) == NOT_SERVING, "store health NOT_SERVING")
        assert health(port, "") == SERVING  # fixes are answered: the server is serving
        c = srv.checkpoints.counters
        assert c.lookup_failures == 1 and c.restored == 0
        wait_until(lambda: srv.checkpoints.counters.write_failures >= 1, "a failed checkpoint")
        assert srv.sessions.count() == 1  # not written, so not handed over: it stays here
        # the store comes up: health follows, and the pass that succeeds writes the session
        with redis_server(tmp_path, port=dead):
            wait_until(lambda: health(port, STORE_HEALTH) == SERVING, "store health SERVING again")
            late = redis.Redis(port=dead)
            checksum = srv.maps.get("city").checksum
            wait_until(lambda: late.exists(session_key(checksum, "v-down")) == 1, "the late checkpoint")
            late.close()


def _stalling_server() -> tuple[socket.socket, threading.Event]:
    """A TCP port that accepts connections and never answers (a hung store)."""
    lst = socket.socket()
    lst.bind(("127.0.0.1", 0))
    lst.listen(16)
    stop = threading.Event()
    held: list[socket.socket] = []

    def run() -> None:
        lst.settimeout(0.1)
        while not stop.is_set():
            with contextlib.suppress(OSError):
                held.append(lst.accept()[0])
        for c in held:
            c.close()

    threading.Thread(target=run, daemon=True).start()
    return lst, stop


@pytest.mark.slow  # waits out a store look-up's timeout
def test_a_look_up_that_times_out_starts_the_session_afresh_and_is_counted():
    lst, stop = _stalling_server()
    port = lst.getsockname()[1]
    cfg = local_config(session_store=f"redis://127.0.0.1:{port}/0", store_timeout=0.05)
    try:
        with running(cfg, {"city": AMAP.graph}) as (srv, sp):
            out = stream(sp, requests(FIXES[:5], "v-slow"))
            assert all(not r.HasField("error") for r in out) and len(out) == 5
            assert srv.checkpoints.counters.timeouts == 1 and srv.checkpoints.counters.restored == 0
    finally:
        stop.set()
        lst.close()


def test_a_bad_record_starts_the_session_afresh(db, redis_port):
    with running(store_config(redis_port), {"city": AMAP.graph}) as (srv, port):
        checksum = srv.maps.get("city").checksum
        db.set(session_key(checksum, "bad1"), b"not a record")
        db.set(session_key(checksum, "bad2"), pack(b'{"version": 2, "time": "x"}'))
        for vid in ("bad1", "bad2"):
            out = stream(port, requests(FIXES[:3], vid))
            assert all(not r.HasField("error") for r in out)
        assert srv.checkpoints.counters.bad_records == 2 and srv.checkpoints.counters.restored == 0


def test_a_resent_fix_gets_the_same_answer_and_is_not_applied_twice():
    with running(local_config(), {"city": AMAP.graph}) as (_, port):
        reqs = requests(FIXES[:8], "twice")
        first = stream(port, reqs)
        again = stream(port, [reqs[-1]])  # the answer was lost: the client sends it again
        assert not again[0].HasField("error")
        assert again[0].result == first[-1].result
        moved = pb.FixRequest()
        moved.CopyFrom(reqs[-1])
        moved.fix.lat += 0.0001  # the same time, another position: not a resend
        out = stream(port, [moved, requests(FIXES[8:9], "twice")[0]])
        assert out[0].error.field == "fix.time"
        assert not out[1].HasField("error")


def test_graceful_stop_hands_open_streams_over_without_losing_a_fix(db, redis_port):
    """SIGTERM's path: an open stream's next fix is not answered; its vehicle is written
    first, and the client's resend on a new server resumes exactly where the answers were."""
    half = len(FIXES) // 2
    ref = reference()
    a, pa = start_server(store_config(redis_port, grace=5.0), {"city": AMAP.graph})
    checksum = a.maps.get("city").checksum
    with MapMatchClient(f"127.0.0.1:{pa}") as client:
        bus = client.vehicle("bus", retries=0)
        got = [bus.send(f) for f in FIXES[:half]]
        stopper = threading.Thread(target=a.stop)
        stopper.start()
        wait_until(lambda: a.checkpoints.draining, "draining")
        with pytest.raises(grpc.RpcError) as err:
            bus.send(FIXES[half])
        assert err.value.code() == grpc.StatusCode.UNAVAILABLE
        stopper.join(30)
    assert record_time(db, checksum, "bus") == FIXES[half - 1].time
    with running(store_config(redis_port), {"city": AMAP.graph}) as (b, pb_):
        with MapMatchClient(f"127.0.0.1:{pb_}") as client, client.vehicle("bus") as bus:
            got += [bus.send(f) for f in FIXES[half:]]
        assert b.checkpoints.counters.restored == 1
    assert all(g.error is None for g in got)
    assert [g.result.edge for g in got] == [r.edge for r in ref]
    assert State.INITIALISING not in {g.result.state for g in got[half:]}


def test_the_client_resends_after_a_server_restart_on_the_same_address(db, redis_port):
    """VehicleStream: the stream breaks (server stopped), a new server comes up on the same
    port, the unanswered fix is sent again, and every fix has exactly one answer."""
    port = free_port()
    cfg = store_config(redis_port, address=f"127.0.0.1:{port}", grace=1.0)
    opts = [("grpc.initial_reconnect_backoff_ms", 50), ("grpc.max_reconnect_backoff_ms", 200)]
    ref = reference()
    a = start_server(cfg, {"city": AMAP.graph})[0]
    answers = []
    with (
        MapMatchClient(f"127.0.0.1:{port}", options=opts) as client,
        client.vehicle("taxi", retries=12) as taxi,
    ):
        for i, f in enumerate(FIXES):
            if i == 15:
                a.stop()
                b = start_server(cfg, {"city": AMAP.graph})[0]
            answers.append(taxi.send(f))
        assert taxi.resent >= 1
    b.stop()
    assert len(answers) == len(FIXES) and all(x.error is None for x in answers)
    assert [x.fix.time for x in answers] == [f.time for f in FIXES]
    assert [x.result.edge for x in answers] == [r.edge for r in ref]


# ---------------------------------------------------------------------------------- settings
def test_store_settings_from_flags_environment_and_file(tmp_path: Path):
    import argparse

    from service.config import add_arguments

    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["--session-store", "redis://h:1/2", "--checkpoint-interval", "0.5"])
    cfg = config_from(args, {"MAPMATCH_STORE_TIMEOUT": "0.2"})
    assert (cfg.session_store, cfg.checkpoint_interval, cfg.store_timeout) == ("redis://h:1/2", 0.5, 0.2)
    toml = tmp_path / "serve.toml"
    toml.write_text('session_store = "redis://r:6379/0"\ncheckpoint-interval = 2\n')
    assert read_config_file(toml) == {"session_store": "redis://r:6379/0", "checkpoint_interval": 2.0}
    cfg = config_from(None, {"MAPMATCH_CONFIG": str(toml)})
    assert cfg.session_store == "redis://r:6379/0" and cfg.checkpoint_interval == 2.0
    assert "redis://" not in repr(cfg)  # the URL may hold a password
    from mapmatch.errors import ConfigError

    with pytest.raises(ConfigError, match="session_store must be a Redis URL"):
        ServerConfig(session_store="http://x")
    with pytest.raises(ConfigError, match="checkpoint_interval"):
        ServerConfig(checkpoint_interval=0)


def test_the_session_table_lists_sessions_used_since_a_time_and_drops_only_unused_ones():
    from service.sessions import SessionStore

    now = [0.0]
    table = SessionStore(max_sessions=10, ttl=100.0, clock=lambda: now[0])
    for i, vid in enumerate("abc"):
        now[0] = float(i + 1)
        with table.use("m", vid, dict):
            pass
    assert [s.key[1] for s in table.used_since(1.5)] == ["c", "b"]  # latest first, "a" (1 s) left
    now[0] = 5.0
    with table.use("m", "a", dict):  # used again: to the end of the order
        pass
    assert [s.key[1] for s in table.used_since(4.0)] == ["a"]
    a = table.live(("m", "a"))
    assert a is not None
    assert not table.drop_unused(a, 1.0)  # used after that: kept
    assert table.drop_unused(a, a.last_used) and table.live(("m", "a")) is None


def _table_with_sessions(n: int):  # type: ignore[no-untyped-def]
    """A map registry and a session table with ``n`` sessions, each after a few real fixes."""
    from service.maps import MapRegistry
    from service.sessions import SessionStore

    maps = MapRegistry()
    maps.install(maps.prepare("city", AMAP.graph, source="test"))
    table = SessionStore(max_sessions=10 * n, ttl=600.0)
    m = OnlineMatcher(AMAP.graph)
    for i in range(n):
        st = m.new_session()
        for f in FIXES[: 5 + i % 7]:
            last = m.update(st, f)
        table.put("city", f"v{i}", st, answer=last)
    return maps, table


def test_a_pass_writes_sessions_without_their_locks_and_leaves_one_mid_update_to_the_next(db, redis_port):
    from mapmatch.online.codec import from_bytes, to_bytes
    from service.store import RedisStore
    from service.store_checkpoints import Checkpointer, CheckpointSettings

    maps, table = _table_with_sessions(30)
    checksum = maps.get("city").checksum
    held, busy = table.live(("city", "v0")), table.live(("city", "v1"))
    assert held is not None and busy is not None
    held.lock.acquire()  # a fix holds this one's lock for the whole pass
    busy.version += 1  # an update of this one is under way
    store = RedisStore(f"redis://127.0.0.1:{redis_port}/0", timeout=1.0)
    ck = Checkpointer(store=store, sessions=table, maps=maps, settings=CheckpointSettings(interval=0.05))
    ck.start()
    try:
        wait_until(lambda: ck.healthy, "the store's probe")
        time.sleep(0.05)
        for i in range(30):  # used since the checkpoint thread began
            s = table.live(("city", f"v{i}"))
            assert s is not None
            table.touch(s)
        others = [f"v{i}" for i in range(30) if i != 1]
        wait_until(lambda: all(db.exists(session_key(checksum, v)) for v in others), "the pass")
        assert not db.exists(session_key(checksum, "v1"))  # read mid-update: not written torn
        for vid in ("v0", "v7"):
            s = table.live(("city", vid))
            assert s is not None
            blob = unpack(db.get(session_key(checksum, vid)))[0]
            assert to_bytes(from_bytes(blob)) == blob == to_bytes(s.state)
        held.lock.release()
        busy.version += 1  # the update ends, and counts as use: the next pass writes it
        table.touch(busy)
        wait_until(lambda: db.exists(session_key(checksum, "v1")), "the next pass")
        assert unpack(db.get(session_key(checksum, "v1")))[0] == to_bytes(busy.state)
    finally:
        ck.stop()
    assert ck.counters.written >= 30 and ck.counters.write_failures == 0


def test_a_session_changed_while_it_is_read_is_not_kept(monkeypatch: pytest.MonkeyPatch):
    from service import store_checkpoints
    from service.store_checkpoints import read_session

    _, table = _table_with_sessions(1)
    s = table.live(("city", "v0"))
    assert s is not None
    got = read_session(s)
    assert got is not None and got[0] == s.state.to_bytes() and got[2] == s.last_used

    def racing(state):  # type: ignore[no-untyped-def]
        s.version += 2  # an update began and ended while the encoder read the state
        return b"{}"

    monkeypatch.setattr(store_checkpoints, "to_bytes", racing)
    assert read_session(s) is None
    s.version += 1
    assert read_session(s) is None  # odd: an update under way


def test_a_pass_encodes_at_most_a_slice_of_sessions_between_two_waits(db, redis_port, monkeypatch):
    """The checkpoint thread takes the interpreter from the fixes for one slice at a time: at
    most ``SLICE_MOST`` sessions are encoded between two of its waits (the fixes run in
    those), and every session of the pass is written."""
    from service import store_checkpoints
    from service.store import RedisStore
    from service.store_checkpoints import Checkpointer, CheckpointSettings

    monkeypatch.setattr(store_checkpoints, "SLICE_MOST", 4)  # a slice of 4 sessions, 120 in the pass
    monkeypatch.setattr(store_checkpoints, "SLICE_SECONDS", 10.0)  # bounded by the count alone
    maps, table = _table_with_sessions(120)
    checksum = maps.get("city").checksum
    store = RedisStore(f"redis://127.0.0.1:{redis_port}/0", timeout=1.0)
    ck = Checkpointer(store=store, sessions=table, maps=maps, settings=CheckpointSettings(interval=0.2))
    events: list[str] = []
    encode_one, wait = ck._encode_one, ck._wake.wait

    def counted_encode(*a):  # type: ignore[no-untyped-def]
        events.append("encode")
        return encode_one(*a)

    def counted_wait(timeout=None):  # type: ignore[no-untyped-def]
        events.append("wait")
        return wait(timeout)

    monkeypatch.setattr(ck, "_encode_one", counted_encode)
    monkeypatch.setattr(ck._wake, "wait", counted_wait)
    ck.start()
    try:
        wait_until(lambda: ck.healthy, "the store's probe")
        for i in range(120):  # used since the checkpoint thread began: one pass writes them
            s = table.live(("city", f"v{i}"))
            assert s is not None
            table.touch(s)
        vids = [f"v{i}" for i in range(120)]
        wait_until(lambda: all(db.exists(session_key(checksum, v)) for v in vids), "the pass")
    finally:
        ck.stop()
    runs = [len(run) for run in "".join("e" if e == "encode" else "|" for e in events).split("|") if run]
    assert sum(runs) >= 120 and max(runs) <= 4
    assert len(runs) >= 30  # the pass went in slices, with waits between them
