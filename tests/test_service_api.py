"""The gRPC API over a real channel on loopback: streams, unary calls, tracks, maps, sessions."""

from __future__ import annotations

import itertools
import math
import threading
import time

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc
from online_helpers import DriveSpec, drive
from service_util import city, local_config, requests, running, stub

from graph.artifact import save_map
from mapmatch.types import Candidate, Correction, Fix, SnapResult, State, Turn
from service import convert
from service.gen import mapmatch_pb2 as pb

AMAP = city()


@pytest.fixture(scope="module")
def server():
    with running(local_config(session_ttl=60.0), {"city": AMAP.graph}) as (srv, port):
        yield srv, port


@pytest.fixture
def api(server):
    ch, st = stub(server[1])
    yield st
    ch.close()


def _field(err: grpc.RpcError) -> str:
    return dict(err.trailing_metadata() or ()).get("mapmatch-field", "")


# ---------------------------------------------------------------------------------- online
def test_stream_one_result_per_fix_in_order_on_the_driven_roads(api):
    fixes_1 = drive(AMAP, "abc", DriveSpec(speed=10.0, dt=1.0, sigma=3.0))
    fixes_2 = drive(AMAP, "adg", DriveSpec(speed=10.0, dt=1.0, sigma=3.0))
    reqs = []  # two vehicles interleaved on one stream
    for pair in itertools.zip_longest(requests(fixes_1, "v1"), requests(fixes_2, "v2", seq0=1000)):
        reqs += [r for r in pair if r is not None]
    out = list(api.StreamFixes(iter(reqs), timeout=30))
    assert [(r.vehicle_id, r.seq) for r in out] == [(r.vehicle_id, r.seq) for r in reqs]
    assert all(not r.HasField("error") for r in out)
    assert all(r.map_id == "city" for r in out)
    ab, bc = AMAP.edge("a", "b"), AMAP.edge("b", "c")
    ad, dg = AMAP.edge("a", "d"), AMAP.edge("d", "g")
    e1 = [r.result.edge for r in out if r.vehicle_id == "v1"]
    e2 = [r.result.edge for r in out if r.vehicle_id == "v2"]
    # after the start, every fix is on a driven road, and both vehicles reach their last road
    assert set(e1[2:]) <= {ab, bc} and e1[-1] == bc
    assert set(e2[2:]) <= {ad, dg} and e2[-1] == dg
    last = [r for r in out if r.vehicle_id == "v1"][-1]
    assert last.result.state in (pb.STATE_ON_ROAD, pb.STATE_AMBIGUOUS)
    assert last.result.u == AMAP.graph.node_id[AMAP.nodes["b"]]
    assert last.result.way_id == AMAP.graph.edge_way_id[bc]
    assert 0.0 <= last.result.offset <= AMAP.graph.edge_len[bc]
    assert abs(last.result.bearing - 90.0) < 1.0
    # wherever the matcher weighs several roads, they come with probabilities
    for r in out:
        if r.result.candidates:
            assert sum(c.probability for c in r.result.candidates) == pytest.approx(1.0)
    lon, lat = AMAP.lonlat(*AMAP.xy("c"))
    assert abs(last.result.lat - lat) < 1e-3 and abs(last.result.lon - lon) < 1e-3


def test_stream_bad_fix_gets_an_error_result_and_the_stream_goes_on(api):
    fixes = drive(AMAP, "abc", DriveSpec(speed=10.0, dt=1.0))
    reqs = requests(fixes, "bad-stream")
    reqs[3].fix.lat = 123.0  # out of range
    reqs[5].vehicle_id = ""  # missing vehicle
    reqs[7].map_id = "atlantis"  # unknown map
    reqs[9].fix.heading = -5.0
    out = list(api.StreamFixes(iter(reqs), timeout=30))
    assert len(out) == len(reqs)
    errs = {i: (r.error.code, r.error.field) for i, r in enumerate(out) if r.HasField("error")}
    assert errs == {
        3: (grpc.StatusCode.INVALID_ARGUMENT.value[0], "fix.lat"),
        5: (grpc.StatusCode.INVALID_ARGUMENT.value[0], "vehicle_id"),
        7: (grpc.StatusCode.NOT_FOUND.value[0], "map_id"),
        9: (grpc.StatusCode.INVALID_ARGUMENT.value[0], "fix.heading"),
    }
    assert out[-1].result.edge == AMAP.edge("b", "c")


def test_stream_time_going_backwards_is_a_field_error(api):
    fixes = drive(AMAP, "ab", DriveSpec(speed=10.0, dt=1.0))
    reqs = requests(fixes[:4], "backwards")
    reqs[2].fix.time = reqs[1].fix.time - 5.0
    out = list(api.StreamFixes(iter(reqs), timeout=30))
    assert out[2].HasField("error") and out[2].error.field == "fix.time"
    assert not out[3].HasField("error")


def test_unary_fix_is_stateful_by_vehicle(api):
    fixes = drive(AMAP, "abe", DriveSpec(speed=10.0, dt=1.0, sigma=3.0))
    out = [api.SnapFix(r, timeout=10) for r in requests(fixes, "unary-1")]
    # the last fix lies on node e itself, where b-e ends: the one before is well inside b-e
    assert out[-2].result.edge == AMAP.edge("b", "e")
    assert out[-1].result.time == fixes[-1].time
    # the session remembers: the server holds one, and its export is non-empty
    blob = api.ExportSession(pb.ExportSessionRequest(vehicle_id="unary-1"), timeout=10)
    assert blob.map_id == "city" and blob.state


def test_unary_errors_name_the_field(api):
    ok = requests(drive(AMAP, "ab")[:1], "unary-err")[0]
    cases = [
        (pb.FixRequest(vehicle_id="x"), grpc.StatusCode.INVALID_ARGUMENT, "fix"),
        (pb.FixRequest(fix=ok.fix), grpc.StatusCode.INVALID_ARGUMENT, "vehicle_id"),
        (pb.FixRequest(vehicle_id="x", fix=pb.Fix(time=math.nan, lat=60.0, lon=25.0)), None, "fix.time"),
        (pb.FixRequest(vehicle_id="x", fix=pb.Fix(time=1, lat=60.0, lon=25.0, speed=-1)), None, "fix.speed"),
        (pb.FixRequest(map_id="nowhere", vehicle_id="x", fix=ok.fix), grpc.StatusCode.NOT_FOUND, "map_id"),
    ]
    for req, code, fld in cases:
        with pytest.raises(grpc.RpcError) as ei:
            api.SnapFix(req, timeout=10)
        assert ei.value.code() == (code or grpc.StatusCode.INVALID_ARGUMENT)
        assert _field(ei.value) == fld
        assert fld in ei.value.details()


# ---------------------------------------------------------------------------------- batch
def _track(route: str, tid: str) -> pb.Track:
    fixes = drive(AMAP, route, DriveSpec(speed=10.0, dt=2.0, noise=2.0, seed=3))
    return pb.Track(
        track_id=tid,
        time=[f.time for f in fixes],
        lat=[f.lat for f in fixes],
        lon=[f.lon for f in fixes],
    )


def test_match_track_follows_the_driven_route(api):
    res = api.MatchTrack(pb.MatchTrackRequest(track=_track("abed", "t1")), timeout=60)
    assert res.track_id == "t1"
    want = [AMAP.edge(*p) for p in ("ab", "be", "ed")]
    assert len(res.routes) == 1
    edges = list(res.routes[0].edges)
    assert edges[:3] == want  # (a last noisy point at d may reach just past it)
    assert list(res.routes[0].way_ids) == [int(AMAP.graph.edge_way_id[e]) for e in edges]
    assert len(res.points) == len(res.routes[0].lat) or len(res.points) > 0
    assert all(p.status == pb.POINT_STATUS_MATCHED for p in res.points)
    assert res.length_m > 0


def test_match_tracks_streams_one_result_per_track_in_order(api):
    bad = pb.Track(track_id="bad", lat=[60.0, 60.1], lon=[25.0])
    tracks = [_track("abc", "t1"), bad, _track("adg", "t2")]
    out = list(api.MatchTracks(pb.MatchTracksRequest(map_id="city", tracks=tracks), timeout=60))
    assert [r.track_id for r in out] == ["t1", "bad", "t2"]
    assert (
        out[1].error.field == "tracks[1].lon"
        and out[1].error.code == grpc.StatusCode.INVALID_ARGUMENT.value[0]
    )
    assert set(out[2].routes[0].edges) == {AMAP.edge("a", "d"), AMAP.edge("d", "g")}


def test_match_track_errors(api):
    with pytest.raises(grpc.RpcError) as ei:
        api.MatchTrack(pb.MatchTrackRequest(), timeout=10)
    assert ei.value.code() == grpc.StatusCode.INVALID_ARGUMENT and _field(ei.value) == "track"
    with pytest.raises(grpc.RpcError) as ei:
        api.MatchTrack(
            pb.MatchTrackRequest(track=pb.Track(lat=[60.0], lon=[25.0], heading=[1, 2])), timeout=10
        )
    assert _field(ei.value) == "track.heading"
    with pytest.raises(grpc.RpcError) as ei:
        api.MatchTracks(pb.MatchTracksRequest(map_id="x", tracks=[_track("ab", "t")]), timeout=10).next()
    assert ei.value.code() == grpc.StatusCode.NOT_FOUND


def test_message_size_limit_is_resource_exhausted():
    with running(local_config(max_message_bytes=64 * 1024), {"city": AMAP.graph}) as (_, port):
        ch, api = stub(port)
        n = 20_000  # 3 x 20k doubles > 64 KiB
        big = pb.Track(track_id="big", time=list(range(n)), lat=[60.0] * n, lon=[25.0] * n)
        with pytest.raises(grpc.RpcError) as ei:
            api.MatchTrack(pb.MatchTrackRequest(track=big), timeout=10)
        assert ei.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert api.ListMaps(pb.ListMapsRequest(), timeout=5).maps  # server fine
        ch.close()


def test_deadline_is_honoured_and_the_server_goes_on(api):
    tracks = [_track("abcfed", f"t{i}") for i in range(200)]
    with pytest.raises(grpc.RpcError) as ei:
        list(api.MatchTracks(pb.MatchTracksRequest(tracks=tracks), timeout=0.05))
    assert ei.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
    assert api.ListMaps(pb.ListMapsRequest(), timeout=5).maps


def test_cancelled_stream_does_not_disturb_other_streams(api):
    gate = threading.Event()

    def slow_requests():
        yield from requests(drive(AMAP, "ab")[:2], "cancel-me")
        gate.wait(10)

    call = api.StreamFixes(slow_requests(), timeout=30)
    next(call)
    call.cancel()
    gate.set()
    out = list(api.StreamFixes(iter(requests(drive(AMAP, "ab"), "after-cancel")), timeout=10))
    assert out and not any(r.HasField("error") for r in out)


# ---------------------------------------------------------------------------------- maps
def test_list_and_info(api, server):
    resp = api.ListMaps(pb.ListMapsRequest(), timeout=5)
    assert resp.default_map_id == "city" and resp.server_id
    info = resp.maps[0]
    g = AMAP.graph
    assert (info.map_id, info.node_count, info.edge_count) == ("city", g.n_nodes, g.n_edges)
    assert (info.min_lon, info.min_lat, info.max_lon, info.max_lat) == pytest.approx(g.bbox)
    assert info.checksum == server[0].maps.get("city").checksum and info.crs == g.crs
    assert api.GetMapInfo(pb.GetMapInfoRequest(map_id="city"), timeout=5).checksum == info.checksum
    with pytest.raises(grpc.RpcError) as ei:
        api.GetMapInfo(pb.GetMapInfoRequest(map_id="nowhere"), timeout=5)
    assert ei.value.code() == grpc.StatusCode.NOT_FOUND


def test_load_and_unload_maps_at_run_time(tmp_path):
    other = city(scale=12.0)
    path = tmp_path / "other.map"
    save_map(other.graph, path)
    with running(local_config(map_dir=tmp_path), {"city": AMAP.graph}) as (_, port):
        ch, api = stub(port)
        info = api.LoadMap(pb.LoadMapRequest(map_id="other", path="other.map"), timeout=60)
        assert info.edge_count == other.graph.n_edges and info.version and info.source == "other.map"
        listed = api.ListMaps(pb.ListMapsRequest(), timeout=5)
        assert sorted(m.map_id for m in listed.maps) == ["city", "other"] and listed.default_map_id == ""
        # with two maps a request must name one
        req = requests(drive(other, "ab")[:1], "v")[0]
        with pytest.raises(grpc.RpcError) as ei:
            api.SnapFix(req, timeout=5)
        assert ei.value.code() == grpc.StatusCode.INVALID_ARGUMENT and _field(ei.value) == "map_id"
        req.map_id = "other"
        assert api.SnapFix(req, timeout=5).map_id == "other"
        assert api.UnloadMap(pb.UnloadMapRequest(map_id="other"), timeout=5).sessions_dropped == 1
        assert api.ListMaps(pb.ListMapsRequest(), timeout=5).default_map_id == "city"
        for bad, code, fld in [
            (pb.LoadMapRequest(map_id="x", path="missing.map"), grpc.StatusCode.PERMISSION_DENIED, "path"),
            (pb.LoadMapRequest(map_id="", path=str(path)), grpc.StatusCode.INVALID_ARGUMENT, "map_id"),
        ]:
            with pytest.raises(grpc.RpcError) as ei:
                api.LoadMap(bad, timeout=30)
            assert _field(ei.value) == fld and (code is None or ei.value.code() == code)
        (tmp_path / "junk.map").write_bytes(b"RGMAP\x00\x00\x01garbage")
        with pytest.raises(grpc.RpcError) as ei:
            api.LoadMap(pb.LoadMapRequest(map_id="junk", path="junk.map"), timeout=30)
        assert ei.value.code() == grpc.StatusCode.INVALID_ARGUMENT and _field(ei.value) == "path"
        with pytest.raises(grpc.RpcError) as ei:
            api.UnloadMap(pb.UnloadMapRequest(map_id="other"), timeout=5)
        assert ei.value.code() == grpc.StatusCode.NOT_FOUND
        ch.close()


# ---------------------------------------------------------------------------------- standard services
def test_health_not_serving_until_a_map_is_loaded_and_warmed(tmp_path):
    path = tmp_path / "city.map"
    save_map(AMAP.graph, path)
    with running(local_config(map_dir=tmp_path), None) as (_, port):
        ch = grpc.insecure_channel(f"127.0.0.1:{port}")
        health = health_pb2_grpc.HealthStub(ch)
        for svc in ("", "mapmatch.v1.MapMatch"):
            st = health.Check(health_pb2.HealthCheckRequest(service=svc), timeout=5).status
            assert st == health_pb2.HealthCheckResponse.NOT_SERVING
        from service.gen import mapmatch_pb2_grpc as pb_grpc

        pb_grpc.MapMatchStub(ch).LoadMap(pb.LoadMapRequest(map_id="city", path="city.map"), timeout=60)
        st = health.Check(health_pb2.HealthCheckRequest(service="mapmatch.v1.MapMatch"), timeout=5).status
        assert st == health_pb2.HealthCheckResponse.SERVING
        pb_grpc.MapMatchStub(ch).UnloadMap(pb.UnloadMapRequest(map_id="city"), timeout=60)
        st = health.Check(health_pb2.HealthCheckRequest(service=""), timeout=5).status
        assert st == health_pb2.HealthCheckResponse.NOT_SERVING
        ch.close()


def test_reflection_lists_the_services(server):
    ch = grpc.insecure_channel(f"127.0.0.1:{server[1]}")
    refl = reflection_pb2_grpc.ServerReflectionStub(ch)
    resp = next(refl.ServerReflectionInfo(iter([reflection_pb2.ServerReflectionRequest(list_services="")])))
    names = {s.name for s in resp.list_services_response.service}
    assert {"mapmatch.v1.MapMatch", "grpc.health.v1.Health"} <= names
    req = reflection_pb2.ServerReflectionRequest(file_containing_symbol="mapmatch.v1.MapMatch")
    resp = next(refl.ServerReflectionInfo(iter([req])))
    assert resp.file_descriptor_response.file_descriptor_proto
    ch.close()


# ---------------------------------------------------------------------------------- sessions
def test_session_limit_is_resource_exhausted():
    with running(local_config(max_sessions=2), {"city": AMAP.graph}) as (_, port):
        ch, api = stub(port)
        req = requests(drive(AMAP, "ab")[:1], "v")[0]
        for vid in ("v1", "v2"):
            req.vehicle_id = vid
            api.SnapFix(req, timeout=5)
        req.vehicle_id = "v3"
        with pytest.raises(grpc.RpcError) as ei:
            api.SnapFix(req, timeout=5)
        assert ei.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        out = list(api.StreamFixes(iter([req]), timeout=5))
        assert out[0].error.code == grpc.StatusCode.RESOURCE_EXHAUSTED.value[0]
        # ending a session frees a place
        assert api.EndSession(pb.EndSessionRequest(vehicle_id="v1"), timeout=5).existed
        assert api.SnapFix(req, timeout=5).result.time == req.fix.time
        ch.close()


@pytest.mark.slow  # waits out a session TTL
def test_sessions_expire_after_the_ttl():
    # a TTL long enough that a loaded machine cannot let "old" expire between two calls
    with running(local_config(session_ttl=1.0, max_sessions=1), {"city": AMAP.graph}) as (srv, port):
        ch, api = stub(port)
        req = requests(drive(AMAP, "ab")[:1], "old")[0]
        api.SnapFix(req, timeout=5)
        assert srv.sessions.count() == 1
        req.vehicle_id = "new"
        with pytest.raises(grpc.RpcError):
            api.SnapFix(req, timeout=5)  # full while "old" is alive
        time.sleep(1.3)
        assert api.SnapFix(req, timeout=5).result.time == req.fix.time  # "old" expired
        with pytest.raises(grpc.RpcError) as ei:
            api.ExportSession(pb.ExportSessionRequest(vehicle_id="old"), timeout=5)
        assert ei.value.code() == grpc.StatusCode.NOT_FOUND and _field(ei.value) == "vehicle_id"
        assert srv.sessions.expired_total >= 1
        time.sleep(2.0)  # the server's sweeper (every TTL / 2) drops idle sessions without any request
        assert srv.sessions.expired_total >= 2 and len(srv.sessions._sessions) == 0
        ch.close()


def test_session_moves_between_two_servers_and_continues_identically():
    fixes = drive(AMAP, "abefc", DriveSpec(speed=10.0, dt=1.0, noise=1.5, seed=7, sigma=3.0))
    reqs = requests(fixes, "mover")
    half = len(reqs) // 2
    with (
        running(local_config(), {"city": AMAP.graph}) as (_, p1),
        running(local_config(), {"city": AMAP.graph}) as (_, p2),
        running(local_config(), {"city": AMAP.graph}) as (_, p3),
    ):
        (c1, a1), (c2, a2), (c3, a3) = stub(p1), stub(p2), stub(p3)
        # reference: the whole drive on one server
        ref = list(a3.StreamFixes(iter(reqs), timeout=30))
        first = list(a1.StreamFixes(iter(reqs[:half]), timeout=30))
        blob = a1.ExportSession(pb.ExportSessionRequest(vehicle_id="mover", remove=True), timeout=5)
        with pytest.raises(grpc.RpcError):  # moved away: gone from server 1
            a1.ExportSession(pb.ExportSessionRequest(vehicle_id="mover"), timeout=5)
        a2.ImportSession(pb.ImportSessionRequest(session=blob), timeout=5)
        with pytest.raises(grpc.RpcError) as ei:
            a2.ImportSession(pb.ImportSessionRequest(session=blob), timeout=5)
        assert ei.value.code() == grpc.StatusCode.ALREADY_EXISTS
        second = list(a2.StreamFixes(iter(reqs[half:]), timeout=30))
        moved = [r.result for r in first + second]
        assert [r.SerializeToString(deterministic=True) for r in moved] == [
            r.result.SerializeToString(deterministic=True) for r in ref
        ]
        # a session from another map version, or garbage, is refused
        bad = pb.SessionBlob(map_id="city", vehicle_id="x", map_checksum="0" * 32, state=blob.state)
        with pytest.raises(grpc.RpcError) as ei:
            a2.ImportSession(pb.ImportSessionRequest(session=bad), timeout=5)
        assert _field(ei.value) == "session.map_checksum"
        bad = pb.SessionBlob(
            map_id="city", vehicle_id="x", map_checksum=blob.map_checksum, state=b"not a state"
        )
        with pytest.raises(grpc.RpcError) as ei:
            a2.ImportSession(pb.ImportSessionRequest(session=bad), timeout=5)
        assert ei.value.code() == grpc.StatusCode.INVALID_ARGUMENT and _field(ei.value) == "session.state"
        for c in (c1, c2, c3):
            c.close()


def test_many_vehicles_in_parallel_streams_keep_their_own_order(server):
    port = server[1]
    errors: list[str] = []

    def run(k: int) -> None:
        ch, api = stub(port)
        route = ["abc", "adg", "abe", "def"][k % 4]
        reqs = requests(drive(AMAP, route, DriveSpec(dt=0.5)), f"par-{k}", seq0=k * 1000)
        out = list(api.StreamFixes(iter(reqs), timeout=60))
        if [r.seq for r in out] != [r.seq for r in reqs] or any(r.HasField("error") for r in out):
            errors.append(f"vehicle {k}")
        ch.close()

    threads = [threading.Thread(target=run, args=(k,)) for k in range(16)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []


def test_reuseport_lets_two_servers_share_a_port():
    method = "/mapmatch.v1.MapMatch/ListMaps"
    with running(local_config(reuse_port=True), {"city": AMAP.graph}) as (s1, port):
        second = local_config(reuse_port=True, address=f"127.0.0.1:{port}")
        with running(second, {"city": AMAP.graph}) as (s2, port2):
            assert port2 == port
            for _ in range(60):  # each new connection goes to one of the two, chosen by the kernel
                ch, api = stub(port, options=[("grpc.use_local_subchannel_pool", 1)])
                api.ListMaps(pb.ListMapsRequest(), timeout=5)
                ch.close()
                if s1.metrics.calls[method] and s2.metrics.calls[method]:
                    break
            assert s1.metrics.calls[method] > 0 and s2.metrics.calls[method] > 0


def test_convert_round_trips_fixes_and_results():
    f = drive(AMAP, "ab", DriveSpec(sigma=3.0, heading_noise=1.0))[1]
    assert convert.fix_from_proto(convert.fix_to_proto(f)) == f or math.isnan(f.heading_sigma)
    bare = Fix(time=1.0, lat=60.0, lon=25.0, gps_valid=False, pos_cov=(4.0, 1.0, 9.0))
    back = convert.fix_from_proto(convert.fix_to_proto(bare))
    assert back.gps_valid is False and back.pos_cov == (4.0, 1.0, 9.0) and math.isnan(back.heading)
    r = SnapResult(
        time=5.0,
        state=State.AMBIGUOUS,
        edge=3,
        u=11,
        v=12,
        way_id=99,
        offset=4.5,
        lat=60.1,
        lon=24.9,
        bearing=270.0,
        dist=1.5,
        turn=Turn.LEFT,
        candidates=(
            Candidate(edge=3, u=11, v=12, way_id=99, probability=0.7, offset=4.5, dist=1.5),
            Candidate(edge=5, u=11, v=13, way_id=98, probability=0.3, offset=4.0, dist=2.0),
        ),
        correction=Correction(
            time_from=1.0, time_to=4.0, edges=(1, 3), replaced_edges=(1, 5), edge_times=(1.0, 3.0)
        ),
        raw_lat=60.10001,
        raw_lon=24.90001,
    )
    assert convert.snap_result_from_proto(convert.snap_result_to_proto(r)) == r


def test_batched_stream_answers_like_single_streams(api):
    a = requests(drive(AMAP, "abc", DriveSpec(sigma=3.0)), "batch-a")
    b = requests(drive(AMAP, "gda", DriveSpec(sigma=3.0)), "batch-b")
    n = min(len(a), len(b))
    batches = [pb.FixBatch(fixes=[a[k], b[k]]) for k in range(n)]
    batches[4].fixes[1].fix.lon = 500.0
    out = list(api.StreamFixBatches(iter(batches), timeout=30))
    assert [len(x.responses) for x in out] == [2] * n
    assert out[4].responses[1].error.field == "fix.lon"
    ref = list(
        api.StreamFixes(iter(requests(drive(AMAP, "abc", DriveSpec(sigma=3.0)), "single-a")[:n]), timeout=30)
    )
    got = [x.responses[0].result for x in out]
    assert [g.SerializeToString(deterministic=True) for g in got] == [
        r.result.SerializeToString(deterministic=True) for r in ref
    ]


def test_access_log_is_structured_with_counts_and_latency(api, caplog):
    import json
    import logging

    caplog.set_level(logging.INFO, logger="mapmatch.access")
    api.ListMaps(pb.ListMapsRequest(), timeout=5)
    list(api.StreamFixes(iter(requests(drive(AMAP, "ab"), "logged")), timeout=10))
    with pytest.raises(grpc.RpcError):
        api.GetMapInfo(pb.GetMapInfoRequest(map_id="nowhere"), timeout=5)
    deadline = time.time() + 5
    recs: list[dict] = []
    while time.time() < deadline and len(recs) < 3:
        recs = [json.loads(r.getMessage()) for r in caplog.records if r.name == "mapmatch.access"]
        time.sleep(0.05)
    by = {r["method"].rsplit("/", 1)[1]: r for r in recs}
    assert by["ListMaps"]["code"] == "OK" and by["ListMaps"]["calls"] >= 1 and by["ListMaps"]["ms"] >= 0
    s = by["StreamFixes"]
    assert s["in"] == s["out"] == len(drive(AMAP, "ab")) and s["msg_p50_ms"] <= s["msg_max_ms"]
    assert by["GetMapInfo"]["code"] == "NOT_FOUND"
    assert all("peer" in r for r in recs)


def test_a_matcher_failure_is_internal_for_that_fix_only():
    with running(local_config(), {"city": AMAP.graph}) as (srv, port):
        entry = srv.maps.get("city")
        real = entry.online.update

        def flaky(state, fix, **kw):
            if fix.time == 3.0 and fix.heading == 90.0:  # only vehicle "a" drives east at t=3
                raise RuntimeError("boom")
            return real(state, fix, **kw)

        entry.online.update = flaky
        ch, api = stub(port)
        a = requests(drive(AMAP, "abc"), "a")
        b = requests(drive(AMAP, "adg"), "b")
        reqs = [r for pair in zip(a, b, strict=False) for r in pair]
        out = list(api.StreamFixes(iter(reqs), timeout=30))
        errs = [(r.vehicle_id, r.seq, r.error.code) for r in out if r.HasField("error")]
        assert errs == [("a", 3, grpc.StatusCode.INTERNAL.value[0])]
        assert "boom" not in out[6].error.message  # internals stay in the server log
        assert out[-1].result.edge == AMAP.edge("d", "g") and out[-2].result.edge >= 0
        ch.close()


def test_fixes_on_the_loop_and_on_the_online_thread_get_the_same_answers():
    fixes = drive(AMAP, "abcf", DriveSpec(speed=10.0, dt=1.0, sigma=3.0))
    bad = Fix(time=1e9, lat=95.0, lon=0.0)  # rejected: answered with an error naming the field
    answers = []
    for inline in (True, False):
        with running(local_config(inline_fixes=inline), {"city": AMAP.graph}) as (_, port):
            ch, api = stub(port)
            got = list(api.StreamFixes(iter(requests([*fixes, bad], "same")), timeout=30))
            snap = api.SnapFix(requests(fixes[:1], "single")[0], timeout=10)
            ch.close()
        assert len(got) == len(fixes) + 1 and got[-1].error.field == "fix.lat"
        answers.append(([g.SerializeToString(deterministic=True) for g in got], snap.result.edge))
    assert answers[0] == answers[1]
