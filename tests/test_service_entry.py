"""One validation for every entry, limits that agree, streams that go on, readiness that
tells the truth, on a real server on a loopback port."""

from __future__ import annotations

import math
import time

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from online_helpers import DriveSpec, drive
from service_util import city, local_config, looped_track, requests, running, stub

from graph.artifact import save_map
from mapmatch.types import FIELD_RULES
from service.batch_workers import POINT_ANSWER_BYTES
from service.config import ServerConfig
from service.gen import mapmatch_pb2 as pb
from service.server import start_server

AMAP = city()
INVALID = grpc.StatusCode.INVALID_ARGUMENT
# (array, index made bad, value): every value SnapFix refuses for the same field
BAD_POINTS = [
    ("pos_sigma", 1, -1.0),
    ("pos_sigma", 2, math.inf),
    ("speed", 0, math.inf),
    ("heading", 3, 720.0),
    ("distance", 1, -5.0),
    ("lat", 2, 91.0),
    ("time", 1, math.inf),
]


def _field(err: grpc.RpcError) -> str:
    return dict(err.trailing_metadata() or ()).get("mapmatch-field", "")


def _err(fn, *a, **kw) -> grpc.RpcError:
    with pytest.raises(grpc.RpcError) as ei:
        fn(*a, **kw)
    return ei.value


def _track(n: int = 6, **bad: tuple[int, float]) -> pb.Track:
    t = looped_track(AMAP, n)
    for name, (i, v) in bad.items():
        if name not in ("lat", "lon", "time"):
            getattr(t, name).extend([1.0] * n)
        getattr(t, name)[i] = v
    return t


@pytest.fixture(scope="module")
def map_server(tmp_path_factory):
    """A server on a map file: its batch matches run in a batch worker process."""
    path = tmp_path_factory.mktemp("maps") / "city.map"
    save_map(AMAP.graph, path)
    with running(local_config(maps=(("city", path),), batch_processes=1)) as (srv, port):
        yield srv, port


# ---------------------------------------------------------------------------------- entries
@pytest.mark.parametrize(("name", "i", "value"), BAD_POINTS)
def test_match_track_arrays_obey_the_rules_of_a_fix(map_server, name, i, value):
    _, port = map_server
    ch, api = stub(port)
    err = _err(api.MatchTrack, pb.MatchTrackRequest(track=_track(**{name: (i, value)})), timeout=30)
    assert err.code() == INVALID and _field(err) == f"track.{name}[{i}]"
    assert FIELD_RULES[name].text in err.details()
    out = list(
        api.MatchTracks(pb.MatchTracksRequest(tracks=[_track(), _track(**{name: (i, value)})]), timeout=30)
    )
    assert not out[0].HasField("error") and out[0].points
    assert out[1].error.code == INVALID.value[0] and out[1].error.field == f"tracks[1].{name}[{i}]"
    # SnapFix refuses the same value of the same field with the same words
    fix = drive(AMAP, "ab")[1]
    req = requests([fix], "v")[0]
    setattr(req.fix, name, value)
    err = _err(api.SnapFix, req, timeout=10)
    assert err.code() == INVALID and _field(err) == f"fix.{name}"
    assert FIELD_RULES[name].text in err.details()
    ch.close()


def test_sigma_inf_no_longer_gives_nan_confidence(map_server):
    _, port = map_server
    ch, api = stub(port)
    good = api.MatchTrack(pb.MatchTrackRequest(track=_track(12)), timeout=30)
    assert math.isfinite(good.confidence) and good.routes
    err = _err(api.MatchTrack, pb.MatchTrackRequest(track=_track(12, pos_sigma=(0, math.inf))), timeout=30)
    assert err.code() == INVALID and _field(err) == "track.pos_sigma[0]"
    ch.close()


# ---------------------------------------------------------------------------------- limits
def test_default_limits_agree():
    cfg = ServerConfig()
    assert cfg.max_track_points * POINT_ANSWER_BYTES <= cfg.max_answer_bytes


@pytest.mark.parametrize("in_worker", [True, False])
def test_a_track_whose_answer_cannot_fit_is_refused_before_any_work(tmp_path, in_worker):
    maps = None
    if in_worker:
        path = tmp_path / "city.map"
        save_map(AMAP.graph, path)
        cfg = local_config(
            maps=(("city", path),), max_track_points=1000, max_answer_bytes=40 * POINT_ANSWER_BYTES
        )
    else:
        maps = {"city": AMAP.graph}
        cfg = local_config(max_track_points=1000, max_answer_bytes=40 * POINT_ANSWER_BYTES, batch_processes=0)
    with running(cfg, maps) as (_, port):
        ch, api = stub(port)
        err = _err(api.MatchTrack, pb.MatchTrackRequest(track=looped_track(AMAP, 41)), timeout=30)
        assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and _field(err) == "max_answer_bytes"
        assert "send at most 40 points" in err.details()
        out = list(api.MatchTracks(pb.MatchTracksRequest(tracks=[looped_track(AMAP, 41)]), timeout=30))
        assert out[0].error.field == "max_answer_bytes"
        err = _err(api.MatchTrack, pb.MatchTrackRequest(track=looped_track(AMAP, 1001)), timeout=30)
        assert _field(err) == "max_track_points"
        ch.close()


# ---------------------------------------------------------------------------------- streams
def test_an_undecodable_message_is_answered_and_the_stream_goes_on(map_server):
    _, port = map_server
    ch = grpc.insecure_channel(f"127.0.0.1:{port}")
    garbage = b"\xff\xff\xff\xff\x0f"
    fixes = drive(AMAP, "abc", DriveSpec(speed=10.0, dt=1.0))[:4]
    reqs = [r.SerializeToString() for r in requests(fixes, "v9")]
    call = ch.stream_stream(
        "/mapmatch.v1.MapMatch/StreamFixes", response_deserializer=pb.SnapResponse.FromString
    )
    out = list(call(iter([reqs[0], garbage, *reqs[1:]]), timeout=30))
    assert len(out) == len(reqs) + 1
    assert out[1].error.code == INVALID.value[0] and out[1].error.field == "request"
    assert all(not r.HasField("error") for i, r in enumerate(out) if i != 1)
    assert [r.seq for r in out if not r.HasField("error")] == list(range(len(reqs)))
    batch = pb.FixBatch(fixes=requests(fixes, "v9b")).SerializeToString()
    call = ch.stream_stream(
        "/mapmatch.v1.MapMatch/StreamFixBatches", response_deserializer=pb.SnapBatch.FromString
    )
    got = list(call(iter([garbage, batch]), timeout=30))
    assert got[0].error.code == INVALID.value[0] and got[0].error.field == "request" and not got[0].responses
    assert len(got[1].responses) == len(fixes) and not got[1].HasField("error")
    ch.close()


# ---------------------------------------------------------------------------------- readiness
def test_serving_means_match_track_is_answered_at_once(tmp_path):
    """Batch readiness has its own health name: once it is SERVING a batch worker is warm and
    a MatchTrack is answered at once (with the kernels cached, the server's own SERVING waits
    for that too; on a machine's first run it does not wait for the compile)."""
    from mapmatch.kernels import is_cached
    from service.server import BATCH_HEALTH

    path = tmp_path / "city.map"
    save_map(AMAP.graph, path)
    cfg = local_config(maps=(("city", path),), batch_processes=1)
    cached = is_cached("batch")
    srv, port = start_server(cfg, wait_ready=False)
    try:
        ch = grpc.insecure_channel(f"127.0.0.1:{port}")
        health = health_pb2_grpc.HealthStub(ch)
        api = stub(port)[1]
        serving = health_pb2.HealthCheckResponse.SERVING

        def status(name: str) -> int:
            return health.Check(health_pb2.HealthCheckRequest(service=name), timeout=5).status

        for _ in range(6000):
            if status("") == serving:
                break
            time.sleep(0.05)
        else:
            raise AssertionError("never SERVING")
        if cached:
            assert status(BATCH_HEALTH) == serving
        for _ in range(12000):  # a first run: the worker compiles the batch kernels (minutes, loaded)
            if status(BATCH_HEALTH) == serving:
                break
            time.sleep(0.05)
        else:
            raise AssertionError(f"{BATCH_HEALTH} never SERVING")
        assert srv.batch_workers is not None and srv.batch_workers.wait_warm(0)
        res = api.MatchTrack(pb.MatchTrackRequest(track=looped_track(AMAP, 20)), timeout=10)
        assert len(res.points) == 20
        ch.close()
    finally:
        srv.stop(0)


def test_a_call_waiting_for_a_preparing_worker_is_answered_unavailable_before_its_deadline():
    """A batch worker still preparing its maps (on a first run, compiling) says nothing; a call
    waiting for it gets UNAVAILABLE at its deadline's margin, not a silent expiry, and the
    worker is left to finish."""
    import asyncio
    import multiprocessing

    from service.batch_workers import PREPARING, BatchWorkers, StatusError, TrackLimits, _Job, _Slot

    workers = BatchWorkers(processes=1, limits=TrackLimits(1000, 1 << 20))
    parent, child = multiprocessing.Pipe()

    class Alive:
        pid = 1

        def is_alive(self) -> bool:
            return True

    slot = _Slot(0)
    slot.conn, slot.proc, slot.loading = parent, Alive(), 1
    loop = asyncio.new_event_loop()
    try:
        job = _Job(loop, loop.create_future(), ("match", "track", None, "track"), b"", time.monotonic() + 0.3)
        got = workers._call(slot, job)
    finally:
        loop.close()
        parent.close()
        child.close()
    assert isinstance(got, StatusError) and got.code is grpc.StatusCode.UNAVAILABLE
    assert PREPARING in str(got)
    assert slot.loading == 1 and slot.conn is parent  # the worker was not stopped
