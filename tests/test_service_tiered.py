"""A cold `mapmatch serve` answers at once with its online kernels interpreted, compiles them in
a child process, then switches to them without a restart: a real drive streamed through it
(half before the switch, half after, on one session) gets every answer a compiled server gives."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import time
from pathlib import Path

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from service_util import requests, stub
from shared_data import KUBICKA, ROOT, reason

from graph.artifact import save_map
from graph.build import build_map
from mapmatch.types import Fix
from service.gen import mapmatch_pb2 as pb
from service.server import KERNELS_HEALTH, NOT_SERVING, SERVING

TRACK = KUBICKA / "00000003"
"""A real drive (821 GPS points at 1 Hz) and its roads."""
SWITCH_TIMEOUT = 900.0
"""Seconds the switch may take: the child compiles the online kernels (about 10 s of CPU,
several times that in wall time on a busy machine)."""

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(SWITCH_TIMEOUT + 300),
    pytest.mark.skipif(not TRACK.is_dir(), reason=reason(TRACK)),
]


def _fixes(path: Path) -> list[Fix]:
    with path.open() as f:
        return [Fix(time=float(r["t"]), lat=float(r["lat"]), lon=float(r["lon"])) for r in csv.DictReader(f)]


def _health(port: int, service: str) -> int:
    with grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
        req = health_pb2.HealthCheckRequest(service=service)
        return int(health_pb2_grpc.HealthStub(ch).Check(req, timeout=10).status)


def _stream(port: int, reqs: list[pb.FixRequest]) -> list[pb.SnapResponse]:
    ch, api = stub(port)
    with ch:
        got = list(api.StreamFixes(iter(reqs), timeout=300))
    assert len(got) == len(reqs)
    for g in got:
        g.vehicle_id = ""  # echoed: the only field the two vehicles differ in
    return got


def test_a_cold_server_answers_interpreted_then_switches_to_compiled_with_the_same_answers(
    tmp_path: Path,
) -> None:
    map_path = tmp_path / "k.map"
    save_map(build_map(TRACK / "roads.geojson"), map_path)
    fixes = _fixes(TRACK / "track.csv")
    cache = tmp_path / "numba-cache"
    cache.mkdir()  # empty: nothing compiled
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_CACHE_DIR": str(cache), "MAPMATCH_GRACE": "5"}
    for name in ("MAPMATCH_KERNELS", "NUMBA_DISABLE_JIT"):
        env.pop(name, None)
    log = tmp_path / "serve.log"
    with log.open("w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "mapmatch", "serve", "--map", f"k={map_path}", "--address", "127.0.0.1:0",
             "--batch-processes", "0", "--log-format", "text"],
            stdout=subprocess.PIPE, stderr=err, text=True, env=env, cwd=ROOT,
        )  # fmt: skip
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "listening on" in line, log.read_text()
        port = int(line.split("listening on ")[1].split()[0].rsplit(":", 1)[1])
        assert _health(port, "") == SERVING
        assert _health(port, KERNELS_HEALTH) == NOT_SERVING
        half = len(fixes) // 2
        first = _stream(port, requests(fixes[:half], "a"))
        assert _health(port, KERNELS_HEALTH) == NOT_SERVING  # that half ran interpreted
        t0 = time.monotonic()
        while _health(port, KERNELS_HEALTH) != SERVING:
            assert proc.poll() is None, log.read_text()
            assert time.monotonic() - t0 < SWITCH_TIMEOUT, log.read_text()
            time.sleep(0.5)
        # the same session goes on compiled; a second vehicle runs the whole drive compiled
        second = _stream(port, requests(fixes[half:], "a", seq0=half))
        compiled = _stream(port, requests(fixes, "b"))
        text = log.read_text()
        assert "fixes are answered interpreted" in text
        assert "online kernels compiled by the child process" in text
        assert sum(r.HasField("result") for r in compiled) > 0.9 * len(fixes)
        assert first + second == compiled
        assert list(cache.rglob("*.nbi"))  # the child wrote numba's cache
    finally:
        proc.terminate()
        proc.wait(30)
