"""The benches' lighter load generator (``bench/h2_load.py``: gRPC over HTTP/2 framed by the
``h2`` library) against a real server on a loopback port: every fix sent gets its answer,
the server's answers are those of grpcio's client, and a stream's bad fix is counted."""

from __future__ import annotations

import asyncio
import contextlib
import threading

import pytest
from bench_modules import bench_module
from online_helpers import DriveSpec, drive
from service_util import city, local_config, requests, running, stub

pytest.importorskip("h2", reason="needs h2 (the dev extra)")

AMAP = city()
FIXES = drive(AMAP, "abcfedghd", DriveSpec(speed=10.0, dt=1.0, sigma=3.0))[:12]


def run(port: int, streams: list[tuple[str, list[bytes]]], *, rate: float | None) -> dict:  # type: ignore[type-arg]
    h2_load = bench_module("h2_load")
    ready, start = threading.Semaphore(0), threading.Event()
    start.set()
    stats = asyncio.run(
        h2_load.run_clients_h2(port, streams, rate=rate, window=3, seconds=60.0, barrier=(ready, start))
    )
    assert ready.acquire(blocking=False)  # the streams were open before the start
    return stats


def test_every_fix_of_every_stream_is_answered_as_grpcio_answers_it() -> None:
    with running(local_config(), {"city": AMAP.graph}) as (_, port):
        ch, api = stub(port)
        with contextlib.closing(ch):
            expected = [r.result for r in api.StreamFixes(iter(requests(FIXES, "ref", "city")), timeout=30)]
        vids = [f"v{i}" for i in range(3)]
        streams = [(v, [r.SerializeToString() for r in requests(FIXES, v, "city")]) for v in vids]
        stats = run(port, streams, rate=None)
        assert stats["n"] == 3 * len(FIXES) and stats["errors"] == 0
        assert len(stats["lat"]) == 3 * len(FIXES) and min(stats["lat"]) > 0.0
        for v in vids:  # each vehicle's session holds the drive: its last answer is the reference's
            ch, api = stub(port)
            with contextlib.closing(ch):
                last = api.SnapFix(requests(FIXES[-1:], v, "city")[0], timeout=10)
            assert last.result == expected[-1]


def test_a_bad_fix_is_an_error_answer_and_paced_streams_go_on() -> None:
    with running(local_config(), {"city": AMAP.graph}) as (_, port):
        good = [r.SerializeToString() for r in requests(FIXES[:4], "a", "city")]
        bad = requests(FIXES[:4], "b", "city")
        bad[2].fix.lat = 91.0  # out of range: an error answer naming the field
        stats = run(port, [("a", good), ("b", [r.SerializeToString() for r in bad])], rate=50.0)
        assert stats["n"] == 8 and stats["errors"] == 1
