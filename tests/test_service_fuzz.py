"""Fuzzing the server (hypothesis) over fixes, batches, session blobs and raw bytes: every
answer is OK or one of the documented statuses, never INTERNAL or UNKNOWN."""

from __future__ import annotations

import json

import grpc
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from online_helpers import DriveSpec, drive
from service_util import city, local_config, requests, running, stub

from service.gen import mapmatch_pb2 as pb

AMAP = city()
# the statuses README documents for the MapMatch methods
DOCUMENTED = {
    grpc.StatusCode.OK,
    grpc.StatusCode.INVALID_ARGUMENT,
    grpc.StatusCode.NOT_FOUND,
    grpc.StatusCode.RESOURCE_EXHAUSTED,
    grpc.StatusCode.ALREADY_EXISTS,
    grpc.StatusCode.PERMISSION_DENIED,
}
FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))

floats = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(min_value=-200, max_value=200),
    st.sampled_from([0.0, -0.0, 1e308, -1e308, 5e-324, 360.0, 90.0, -90.0, 180.0]),
)


@pytest.fixture(scope="module")
def port():
    cfg = local_config(max_batch_fixes=50, max_track_points=200, max_vehicle_id=64, max_sessions=500)
    with running(cfg, {"city": AMAP.graph}) as (_, p):
        yield p


@pytest.fixture(scope="module")
def api(port):
    ch, s = stub(port)
    yield s
    ch.close()


@pytest.fixture(scope="module")
def blob(api):
    for r in requests(drive(AMAP, "abcfe"), "blob-src"):
        api.SnapFix(r, timeout=10)
    return api.ExportSession(pb.ExportSessionRequest(vehicle_id="blob-src"), timeout=10)


@st.composite
def fixes(draw) -> pb.Fix:
    f = pb.Fix(time=draw(floats), lat=draw(floats), lon=draw(floats))
    for name in ("heading", "pos_sigma", "heading_sigma", "speed", "distance"):
        if draw(st.booleans()):
            setattr(f, name, draw(floats))
    if draw(st.booleans()):
        f.gps_valid = draw(st.booleans())
    return f


@st.composite
def fix_requests(draw) -> pb.FixRequest:
    return pb.FixRequest(
        map_id=draw(st.sampled_from(["", "city", "atlantis"])),
        vehicle_id=draw(st.one_of(st.sampled_from(["v1", "v2", ""]), st.text(max_size=80))),
        seq=draw(st.integers(min_value=0, max_value=2**63 - 1)),
        fix=draw(fixes()),
    )


def _code(fn) -> grpc.StatusCode:
    try:
        fn()
    except grpc.RpcError as exc:
        assert exc.code() in DOCUMENTED, (exc.code(), exc.details())
        return exc.code()
    return grpc.StatusCode.OK


@FUZZ
@given(reqs=st.lists(fix_requests(), min_size=1, max_size=8))
def test_fuzzed_fixes(api, reqs):
    for r in reqs:
        _code(lambda r=r: api.SnapFix(r, timeout=10))
    for resp in api.StreamFixes(iter(reqs), timeout=30):
        if resp.HasField("error"):
            assert grpc.StatusCode.INTERNAL.value[0] != resp.error.code
            assert resp.error.code in {c.value[0] for c in DOCUMENTED}


@FUZZ
@given(batches=st.lists(st.lists(fix_requests(), max_size=60), min_size=1, max_size=3))
def test_fuzzed_batches(api, batches):
    msgs = [pb.FixBatch(fixes=b) for b in batches]

    def run():
        for out in api.StreamFixBatches(iter(msgs), timeout=30):
            for resp in out.responses:
                if resp.HasField("error"):
                    assert resp.error.code in {c.value[0] for c in DOCUMENTED}

    _code(run)


@FUZZ
@given(n=st.integers(min_value=0, max_value=250), data=st.data())
def test_fuzzed_tracks(api, n, data):
    base = drive(AMAP, "abcfed")
    k = len(base)
    lat = [base[i % k].lat if data.draw(st.booleans()) else data.draw(floats) for i in range(n)]
    lon = [base[i % k].lon for i in range(data.draw(st.sampled_from([n, max(n - 1, 0)])))]
    track = pb.Track(track_id="f", lat=lat, lon=lon, time=[float(i) for i in range(n)] if n % 2 else [])
    _code(lambda: api.MatchTrack(pb.MatchTrackRequest(track=track), timeout=60))


def _mutate(value, draw):
    """A value of the decoded state changed a little, or replaced by junk."""
    if isinstance(value, list) and value and draw(st.booleans()):
        i = draw(st.integers(0, len(value) - 1))
        value = list(value)
        value[i] = _mutate(value[i], draw)
        return value
    return draw(
        st.one_of(
            floats,
            st.integers(min_value=-(2**70), max_value=2**70),
            st.none(),
            st.text(max_size=5),
            st.lists(floats, max_size=4),
            st.booleans(),
        )
    )


@FUZZ
@given(data=st.data())
def test_fuzzed_session_blobs(api, blob, data):
    d = json.loads(blob.state)
    for _ in range(data.draw(st.integers(1, 3))):
        key = data.draw(st.sampled_from(sorted(d)))
        d[key] = _mutate(d[key], data.draw)
    state = json.dumps(d).encode()
    vid = data.draw(st.sampled_from(["fz1", "fz2"]))
    session = pb.SessionBlob(map_id="city", vehicle_id=vid, map_checksum=blob.map_checksum, state=state)
    code = _code(
        lambda: api.ImportSession(pb.ImportSessionRequest(session=session, replace=True), timeout=10)
    )
    if code is grpc.StatusCode.OK:  # an accepted state must serve the next fixes
        for r in requests(drive(AMAP, "abc", DriveSpec(t0=1000.0))[:3], vid):
            _code(lambda r=r: api.SnapFix(r, timeout=10))
        api.EndSession(pb.EndSessionRequest(vehicle_id=vid), timeout=10)


METHODS = ["SnapFix", "MatchTrack", "ListMaps", "GetMapInfo", "LoadMap", "UnloadMap", "ExportSession",
           "ImportSession", "EndSession", "ListSessions"]  # fmt: skip


@FUZZ
@given(method=st.sampled_from(METHODS), raw=st.binary(max_size=200))
def test_fuzzed_raw_bytes(port, method, raw):
    with grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
        call = ch.unary_unary(f"/mapmatch.v1.MapMatch/{method}")
        _code(lambda: call(raw, timeout=10))
        for name in ("StreamFixes", "StreamFixBatches"):
            s = ch.stream_stream(f"/mapmatch.v1.MapMatch/{name}")
            _code(lambda s=s: list(s(iter([raw, raw]), timeout=10)))
