"""Failover: 3 server processes behind nginx and Redis, 50 vehicles on real GPS, one SIGKILL.

Debian's ``nginx`` (the template in ``deploy/nginx``, ``hash $http_x_vehicle_id consistent``)
and ``redis-server`` run on loopback ports, each with its configuration in a temporary folder;
three ``mapmatch serve`` processes hold the session store. 50 vehicles stream real-GPS fused
drives (the Kubicka tracks through :func:`mapmatch.sim.realgps.real_drive`, 1 Hz fixes sent
at ``RATE`` per second, each vehicle on a :class:`~service.client.VehicleStream` of its own).
Mid-drive the server holding the most vehicles is killed with SIGKILL; later the busier of the
two left is stopped with SIGTERM, as a rolling restart stops it. Then:

* every fix has exactly one answer, in order, and none is an error;
* the vehicles of the killed and of the stopped server were all found in the store by the
  next server (no vehicle started afresh); each killed one lost at most the checkpoint
  interval's worth of fixes (its record, read just before the kill, lags its last answer by
  at most ``interval * RATE + 2`` fixes), which its client replays; the stopped server wrote
  its vehicles before it ended;
* the affected drives' correct-road rate is within 0.2 points of one uninterrupted session
  per vehicle in one process, and the other vehicles' answers are that run's, fix for fix.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
from failover_util import nginx, redis_server
from shared_data import KUBICKA, reason

from graph.artifact import save_map
from graph.build import build_map
from mapmatch.online import OnlineMatcher
from mapmatch.sim.realgps import real_drive
from mapmatch.types import Fix
from service import convert
from service.client import Answer, MapMatchClient
from service.gen import mapmatch_pb2 as pb
from service.gen import mapmatch_pb2_grpc as pb_grpc
from service.store import session_key, unpack

redis = pytest.importorskip("redis", reason="needs the redis client: pip install 'mapmatch[redis]'")

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
TRACKS = ("00000003", "00000007", "00000045", "00000070", "00000091")  # small maps, real drives
SEEDS = (1, 2)  # two fused drives of each track (dead-reckoning errors and outages differ)
WINDOWS = 5  # vehicles per drive: windows starting at spread places along it
FIXES = 150  # fixes per vehicle
RATE = 4.0  # fixes sent per second per vehicle (1 Hz drive time, 4x faster than real time)
KILL_AT = 0.35  # share of the run after which a server is killed (SIGKILL)
STOP_AT = 0.65  # ... and another one is stopped (SIGTERM)
INTERVAL = 1.0  # --checkpoint-interval
# --store-timeout: a look-up on a loaded 2-core machine can take longer than the default's
# 0.1 s; past it a vehicle starts afresh (counted), which this test must not see
STORE_TIMEOUT = 2.0


@dataclass
class Vehicle:
    vid: str
    map_id: str
    fixes: list[Fix]
    truth_edge: np.ndarray
    known: np.ndarray
    answers: list[Answer] = field(default_factory=list)
    answered_at: list[float] = field(default_factory=list)
    resent: int = 0
    error: str = ""


def _fleet(folder: Path) -> tuple[dict[str, Path], list[Vehicle], dict[str, list[int]]]:
    """Maps saved as files, the 50 vehicles, and each vehicle's answers in one process."""
    maps: dict[str, Path] = {}
    vehicles: list[Vehicle] = []
    reference: dict[str, list[int]] = {}
    for name in TRACKS:
        graph = build_map(KUBICKA / name / "roads.geojson")
        maps[name] = folder / f"{name}.map"
        save_map(graph, maps[name])
        matcher = OnlineMatcher(graph)
        for seed in SEEDS:
            d = real_drive(graph, KUBICKA / name, rate_hz=1.0, outages=True, seed=seed)
            fixes = [convert.fix_from_proto(convert.fix_to_proto(f)) for f in d.fix_objects()]
            edges = d.truth["edge"].to_numpy()
            known = d.truth["truth_known"].to_numpy(dtype=bool)
            span = max(0, len(fixes) - FIXES)
            for w in range(WINDOWS):
                a = span * w // (WINDOWS - 1)
                v = Vehicle(
                    f"{name}-{seed}-{w}",
                    name,
                    fixes[a : a + FIXES],
                    edges[a : a + FIXES],
                    known[a : a + FIXES],
                )
                st = matcher.new_session()
                reference[v.vid] = [matcher.update(st, f).edge for f in v.fixes]
                vehicles.append(v)
    return maps, vehicles, reference


def _start_servers(
    maps: dict[str, Path], store: str, folder: Path, n: int
) -> list[tuple[subprocess.Popen[str], int, Path]]:
    cmd = [sys.executable, "-m", "mapmatch", "serve", "--address", "127.0.0.1:0", "--session-store", store,
           "--checkpoint-interval", str(INTERVAL), "--store-timeout", str(STORE_TIMEOUT),
           "--batch-processes", "0", "--log-format", "json", "--grace", "2",
           *(a for m, p in maps.items() for a in ("--map", f"{m}={p}"))]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = []
    for i in range(n):
        log = folder / f"server-{i}.log"
        proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=log.open("w"), text=True, env=env, cwd=ROOT
        )
        out.append((proc, 0, log))
    started = []
    for proc, _, log in out:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        if "listening on" not in line:
            raise RuntimeError(f"server failed to start: {line!r}\n{log.read_text()[-2000:]}")
        port = int(line.split("listening on ")[1].split()[0].rsplit(":", 1)[1])
        started.append((proc, port, log))
    return started


def _drive(client: MapMatchClient, v: Vehicle, t0: float) -> None:
    try:
        with client.vehicle(v.vid, map_id=v.map_id, retries=10) as s:
            for i, f in enumerate(v.fixes):
                delay = t0 + i / RATE - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                v.answers.append(s.send(f))
                v.answered_at.append(time.monotonic())
            v.resent = s.resent
    except Exception as exc:  # reported by the test
        v.error = f"{type(exc).__name__}: {exc}"


def _holders(ports: list[int], vehicles: list[Vehicle]) -> dict[int, list[Vehicle]]:
    """Which server holds each vehicle's session (asked of each server directly)."""
    import grpc

    out: dict[int, list[Vehicle]] = {p: [] for p in ports}
    for port in ports:
        with grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
            api = pb_grpc.MapMatchStub(ch)
            for v in vehicles:
                with contextlib.suppress(grpc.RpcError):  # NOT_FOUND: not this server's
                    api.ExportSession(pb.ExportSessionRequest(map_id=v.map_id, vehicle_id=v.vid), timeout=5)
                    out[port].append(v)
    return out


def _store_counts(log: Path) -> dict[str, float]:
    """The counters a server logs when it stops (``session store: passes 3, ...``)."""
    for line in reversed(log.read_text().splitlines()):
        with contextlib.suppress(ValueError):
            msg = json.loads(line).get("message", "")
            if msg.startswith("session store: passes"):
                return {k: float(v) for k, v in (kv.split(" ") for kv in msg.split(": ", 1)[1].split(", "))}
    raise AssertionError(f"no counters in {log}:\n{log.read_text()[-2000:]}")


def _rate(v: Vehicle, edges: list[int]) -> tuple[int, int]:
    ok = (np.asarray(edges) == v.truth_edge) & v.known
    return int(ok.sum()), int(v.known.sum())


def _wait_at(t: float) -> None:
    time.sleep(max(0.0, t - time.monotonic()))


class Failover(NamedTuple):
    """What the failover run did and saw."""

    servers: list[tuple[subprocess.Popen[str], int, Path]]
    killed: int  # port of the server killed with SIGKILL
    held: dict[int, list[Vehicle]]  # vehicles per server just before the kill
    records: list[bytes | None]  # the killed server's vehicles' store records just before the kill
    kill_at: float
    stopped: int  # port of the server stopped with SIGTERM
    held2: dict[int, list[Vehicle]]  # vehicles per server left just before the stop


def _run_failover(folder: Path, maps: dict[str, Path], vehicles: list[Vehicle]) -> Failover:
    """Stream every vehicle through nginx to 3 servers; SIGKILL one, later SIGTERM another."""
    with redis_server(folder / "redis") as rport:
        db = redis.Redis(port=rport)
        servers = _start_servers(maps, f"redis://127.0.0.1:{rport}/0", folder, 3)
        procs = {p: s for s, p, _ in servers}
        try:
            ports = [p for _, p, _ in servers]
            checksums = {m: _checksum(ports[0], m) for m in maps}
            with nginx(folder / "nginx", [f"127.0.0.1:{p}" for p in ports]) as lb:
                client = MapMatchClient(f"127.0.0.1:{lb}")
                t0 = time.monotonic() + 1.0
                threads = [threading.Thread(target=_drive, args=(client, v, t0)) for v in vehicles]
                for t in threads:
                    t.start()
                # SIGKILL the server holding the most vehicles
                _wait_at(t0 + KILL_AT * FIXES / RATE - 1.0)
                held = _holders(ports, vehicles)
                killed = max(ports, key=lambda p: len(held[p]))
                affected = held[killed]
                keys = [session_key(checksums[v.map_id], v.vid) for v in affected]
                records = db.mget(keys)  # just before the kill: what the others will find (or older)
                kill_at = time.monotonic()
                procs[killed].send_signal(signal.SIGKILL)
                # later, SIGTERM the busier of the two left (a rolling restart's step)
                _wait_at(t0 + STOP_AT * FIXES / RATE - 1.0)
                left = [p for p in ports if p != killed]
                held2 = _holders(left, vehicles)
                stopped = max(left, key=lambda p: len(held2[p]))
                procs[stopped].send_signal(signal.SIGTERM)
                procs[stopped].wait(30)
                for t in threads:
                    t.join(FIXES / RATE + 120)
                client.close()
        finally:
            for proc in procs.values():
                if proc.poll() is None:
                    proc.send_signal(signal.SIGTERM)
            for proc in procs.values():
                proc.wait(30)
        db.close()

    return Failover(servers, killed, held, records, kill_at, stopped, held2)


def _kill_lags(run: Failover) -> list[int]:
    """Per vehicle of the killed server: answered fixes newer than its record, before the kill."""
    lags = []
    for v, rec in zip(run.held[run.killed], run.records, strict=True):
        assert rec is not None, v.vid
        t_rec = float(json.loads(unpack(rec)[0])["time"])
        answered = zip(v.answers, v.answered_at, strict=True)
        lags.append(sum(1 for a, at in answered if at < run.kill_at and a.fix.time > t_rec))
    return lags


def _assert_as_in_one_process(
    vehicles: list[Vehicle],
    left: tuple[list[Vehicle], list[Vehicle]],
    reference: dict[str, list[int]],
    lags: list[int],
) -> None:
    """The vehicles no server left (``left``: the killed server's, the stopped one's) are one
    process's, fix for fix; the affected drives' correct-road rate stays within 0.2 points of
    one process's."""
    affected, moved = left
    for v in vehicles:
        if v not in affected and v not in moved:
            assert [a.result.edge for a in v.answers] == reference[v.vid], v.vid
    touched = [v for v in vehicles if v in affected or v in moved]
    got = np.sum([_rate(v, [a.result.edge for a in v.answers]) for v in touched], axis=0)
    ref = np.sum([_rate(v, reference[v.vid]) for v in touched], axis=0)
    same = sum(
        1 for v in touched for a, r in zip(v.answers, reference[v.vid], strict=True) if a.result.edge == r
    )
    print(
        f"\nfailover: {len(affected)} of {len(vehicles)} vehicles on the killed server, {len(moved)} on the "
        f"stopped one; {sum(v.resent for v in touched)} fixes resent; records at most {max(lags)} fixes "
        f"behind at the kill; correct road {100.0 * got[0] / got[1]:.2f} % against "
        f"{100.0 * ref[0] / ref[1]:.2f} % in one process; {same} of {FIXES * len(touched)} answers "
        "as in one process"
    )
    assert abs(100.0 * got[0] / got[1] - 100.0 * ref[0] / ref[1]) <= 0.2, (got, ref)


def test_a_killed_server_and_a_stopped_one_lose_no_vehicle(tmp_path: Path) -> None:
    if not KUBICKA.is_dir():
        pytest.skip(reason(KUBICKA))
    maps, vehicles, reference = _fleet(tmp_path)
    run = _run_failover(tmp_path, maps, vehicles)
    servers, killed, held, held2, stopped = run.servers, run.killed, run.held, run.held2, run.stopped
    affected = held[killed]
    moved = held2[stopped]
    assert affected and moved and len({v.vid for ps in held.values() for v in ps}) == len(vehicles)
    assert len({v.vid for ps in held2.values() for v in ps}) == len(vehicles)
    assert {v.vid for v in affected} <= {v.vid for ps in held2.values() for v in ps}
    # every fix answered exactly once, in order, none rejected
    for v in vehicles:
        assert not v.error, (v.vid, v.error)
        assert [a.fix.time for a in v.answers] == [f.time for f in v.fixes], v.vid
        assert all(a.error is None for a in v.answers), (v.vid, [a.error for a in v.answers if a.error])
    assert all(v.resent for v in affected)  # the killed server's streams broke and were resent
    # nobody started afresh: each time the next server found the vehicle in the store
    counts = {p: _store_counts(log) for _, p, log in servers if p != killed}
    assert sum(c["restored"] for c in counts.values()) == len(affected) + len(moved), counts
    assert sum(c["timeouts"] + c["lookup_failures"] + c["bad_records"] for c in counts.values()) == 0
    assert counts[stopped]["handed_over"] >= len(moved)  # the stop wrote its vehicles before it ended
    # the SIGKILL lost at most the checkpoint interval's worth of fixes (replayed by the clients)
    allowed = math.ceil(INTERVAL * RATE) + 2
    lags = _kill_lags(run)
    assert max(lags) <= allowed, lags
    _assert_as_in_one_process(vehicles, (affected, moved), reference, lags)


def _checksum(port: int, map_id: str) -> str:
    import grpc

    with grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
        info = pb_grpc.MapMatchStub(ch).GetMapInfo(pb.GetMapInfoRequest(map_id=map_id), timeout=5)
        return str(info.checksum)
