"""A MatchTrack's hand-off to a batch worker (issue 17): the server reads a request's map id,
track and point count from the wire format without parsing the track (checked against the
protobuf parser, also on merged and damaged bytes), answers the same statuses on a real
server on port 0 as before, and the workers run in the CPU class ``batch_sched`` names."""

from __future__ import annotations

import os
import time
from pathlib import Path

import grpc
import psutil
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from service_util import city, local_config, looped_track, running, stub

from graph.artifact import save_map
from mapmatch.errors import ConfigError
from service.batch_workers import PEEK_FIELDS, peek_track_request
from service.config import add_arguments, config_from
from service.gen import mapmatch_pb2 as pb

AMAP = city()

doubles = st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=40)
tracks = st.builds(
    pb.Track,
    track_id=st.text(max_size=8),
    time=doubles,
    lat=doubles,
    lon=doubles,
    heading=doubles,
    speed=st.lists(st.floats(allow_nan=False), max_size=3),
)
requests = st.builds(pb.MatchTrackRequest, map_id=st.text(max_size=12), track=st.none() | tracks)


def _parsed(data: bytes) -> tuple[str, bool, int] | None:
    try:
        msg = pb.MatchTrackRequest.FromString(data)
    except Exception:
        return None
    t = msg.track
    return msg.map_id, msg.HasField("track"), max(len(t.lat), len(t.lon), len(t.time))


@settings(max_examples=300, deadline=None)
@given(requests, st.one_of(st.none(), requests))
def test_the_peek_reads_what_the_parser_reads(req, other):
    """Plain requests, and two requests concatenated (the parser merges them: the last map id,
    the track's arrays appended)."""
    data = req.SerializeToString() + (other.SerializeToString() if other is not None else b"")
    peek = peek_track_request(data)
    assert peek is not None
    assert (peek.map_id, peek.has_track, peek.points) == _parsed(data)


@settings(max_examples=300, deadline=None)
@given(requests, st.data())
def test_a_damaged_request_is_left_to_the_parser_or_read_alike(req, data):
    raw = bytearray(req.SerializeToString())
    if not raw:
        raw = bytearray(b"\x0a")
    for _ in range(data.draw(st.integers(1, 3))):
        i = data.draw(st.integers(0, len(raw) - 1))
        raw[i] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(raw)))
    damaged = bytes(raw[:cut])
    peek = peek_track_request(damaged)
    parsed = _parsed(damaged)
    if peek is not None and parsed is not None:  # (bytes the parser refuses, a worker refuses)
        assert (peek.map_id, peek.has_track) == parsed[:2]
        assert peek.points in (parsed[2], None)  # None: not counted (too many fields)


def test_the_peek_gives_up_on_unpacked_or_too_many_fields():
    unpacked = b"".join(b"\x19" + bytes(8) for _ in range(3))  # field 3 (lat) as 3 single doubles
    track = b"\x12" + bytes([len(unpacked)]) + unpacked
    peek = peek_track_request(track)
    assert peek is not None and peek.has_track and peek.points == 3
    many = b"".join(b"\x19" + bytes(8) for _ in range(PEEK_FIELDS + 1))
    peek = peek_track_request(b"\x12" + _varint(len(many)) + many)
    assert peek is not None and peek.has_track and peek.points is None
    assert _parsed(b"\x12" + _varint(len(many)) + many) == ("", True, PEEK_FIELDS + 1)
    top = b"".join(b"\x0a\x01x" for _ in range(PEEK_FIELDS + 1))
    assert peek_track_request(top) is None
    assert peek_track_request(b"\x0a\x02\xff\xfe") is None  # a map id that is not UTF-8
    assert _parsed(b"\x0a\x02\xff\xfe") is None


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _map_file(tmp_path: Path) -> Path:
    path = tmp_path / "city.map"
    save_map(AMAP.graph, path)
    return path


def _err(fn, *a, **kw) -> grpc.RpcError:
    with pytest.raises(grpc.RpcError) as ei:
        fn(*a, **kw)
    return ei.value


def _worker(server, timeout: float = 60.0) -> psutil.Process:
    t = time.monotonic()
    while time.monotonic() - t < timeout:
        pids = server.batch_workers.pids()
        if pids:
            return psutil.Process(pids[0])
        time.sleep(0.05)
    raise AssertionError("no batch worker process started")


def _idle_class(pid: int) -> bool:
    return os.sched_getscheduler(pid) == os.SCHED_IDLE


@pytest.mark.slow  # a server with batch worker processes and many calls
def test_statuses_of_requests_handed_to_a_worker(tmp_path):
    cfg = local_config(maps=(("city", _map_file(tmp_path)),), max_track_points=50)
    with running(cfg) as (server, port):
        worker = _worker(server)
        ch, api = stub(port)
        small = pb.MatchTrackRequest(map_id="city", track=looped_track(AMAP, 20))
        res = api.MatchTrack(small, timeout=60)
        assert len(res.points) == 20 and res.points[0].status == pb.POINT_STATUS_MATCHED
        err = _err(api.MatchTrack, pb.MatchTrackRequest(map_id="nowhere", track=small.track), timeout=30)
        assert err.code() == grpc.StatusCode.NOT_FOUND
        err = _err(api.MatchTrack, pb.MatchTrackRequest(map_id="city"), timeout=30)
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT and "track" in err.details()
        c0 = sum(worker.cpu_times()[:2])
        err = _err(api.MatchTrack, pb.MatchTrackRequest(track=looped_track(AMAP, 51)), timeout=30)
        assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "max_track_points" in err.details()
        assert "51 points" in err.details()
        # the same limit on a track of more single doubles than a peek reads: the worker finds it
        unpacked = b"".join(b"\x19" + bytes(8) for _ in range(PEEK_FIELDS + 6))
        raw = b"\x12" + _varint(len(unpacked)) + unpacked
        call = ch.unary_unary("/mapmatch.v1.MapMatch/MatchTrack")
        err = _err(call, raw, timeout=30)
        assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "max_track_points" in err.details()
        err = _err(call, b"\x12\x05\x1a\x03abc", timeout=30)  # a track whose lat array is cut short
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT and "does not decode" in err.details()
        assert sum(worker.cpu_times()[:2]) - c0 < 5.0
        ch.close()


def _settled(worker: psutil.Process, check, timeout: float = 60.0) -> bool:
    t = time.monotonic()
    while not check(worker) and time.monotonic() - t < timeout:  # set as the child starts
        time.sleep(0.05)
    return bool(check(worker))


def _autogroup(pid: int | str) -> list[str]:
    """``/proc/PID/autogroup`` as words ("/autogroup-279", "nice", "0"); empty where not shown.

    Some containers have the file but give it no text, or refuse to read it.
    """
    try:
        words = Path(f"/proc/{pid}/autogroup").read_text().split()
    except OSError:
        return []
    return words if len(words) == 3 and words[1] == "nice" else []


@pytest.mark.slow  # a server and its batch worker processes
def test_batch_workers_run_in_an_idle_cpu_class(tmp_path):
    path = _map_file(tmp_path)
    with running(local_config(maps=(("city", path),))) as (server, _port):  # "idle", the default
        worker = _worker(server)
        assert _settled(worker, lambda w: _idle_class(w.pid))
        assert os.getsid(worker.pid) == os.getsid(os.getpid())
    with running(local_config(maps=(("city", path),), batch_sched="idle-session")) as (server, _port):
        worker = _worker(server)
        assert _settled(worker, lambda w: _idle_class(w.pid))
        assert os.getsid(worker.pid) == worker.pid != os.getsid(os.getpid())  # a session of its own
        theirs, ours = _autogroup(worker.pid), _autogroup("self")
        if theirs and ours:  # Linux autogroup scheduling, where the kernel shows it: own group, at batch_nice
            assert theirs[-1] == "10"
            assert theirs[0] != ours[0]
    with running(local_config(maps=(("city", path),), batch_sched="normal")) as (server, _port):
        worker = _worker(server)
        assert _settled(worker, lambda w: w.nice() != psutil.Process().nice())
        assert os.sched_getscheduler(worker.pid) == os.SCHED_OTHER


def test_batch_sched_is_configured_by_flag_environment_and_checked():
    import argparse

    ap = argparse.ArgumentParser()
    add_arguments(ap)
    assert config_from(ap.parse_args([]), {}).batch_sched == "idle"
    assert config_from(ap.parse_args(["--batch-sched", "normal"]), {}).batch_sched == "normal"
    assert config_from(ap.parse_args(["--batch-sched", "idle-session"]), {}).batch_sched == "idle-session"
    assert config_from(ap.parse_args([]), {"MAPMATCH_BATCH_SCHED": "normal"}).batch_sched == "normal"
    with pytest.raises(ConfigError, match="batch_sched"):
        config_from(ap.parse_args([]), {"MAPMATCH_BATCH_SCHED": "fifo"})
