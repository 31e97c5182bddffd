"""Map files opened once and children that die with the server, on
real files, real processes and a real server on a loopback port: a map file swapped for a
symlink while LoadMap reads it, a map prepared again over a served file, a batch worker
that cannot load its map, and a server killed or stopped during a build."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import grpc
import psutil
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from service_util import city, local_config, looped_track, running, stub

from graph.artifact import save_map
from service.errors import MapPathError
from service.gen import mapmatch_pb2 as pb
from service.maps import BUILD_PREFIX, LoadLimits, graph_checksum, load_map_file, resolve_map_path

ROOT = Path(__file__).resolve().parents[1]
AMAP = city()
OTHER = city(scale=12.0)
INSIDE = graph_checksum(AMAP.graph)
OUTSIDE = graph_checksum(OTHER.graph)


class _Swapper:
    """Swaps ``name`` between a regular file (the inside map) and a symlink to the outside
    map, as fast as it can, until stopped."""

    def __init__(self, folder: Path, name: str, inside: Path, outside: Path) -> None:
        self.folder, self.name, self.inside, self.outside = folder, name, inside, outside
        self.stop = threading.Event()
        self.swaps = 0
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        tmp_file, tmp_link = self.folder / ".swap-file", self.folder / ".swap-link"
        while not self.stop.is_set():
            for make, tmp in ((lambda t: os.link(self.inside, t), tmp_file),
                              (lambda t: os.symlink(self.outside, t), tmp_link)):  # fmt: skip
                tmp.unlink(missing_ok=True)
                make(tmp)
                os.replace(tmp, self.folder / self.name)
                self.swaps += 1

    def __enter__(self) -> _Swapper:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join()


def _folders(tmp_path: Path) -> tuple[Path, Path, Path]:
    maps = tmp_path / "maps"
    maps.mkdir()
    inside, outside = maps / "inside.map", tmp_path / "outside.map"
    save_map(AMAP.graph, inside)
    save_map(OTHER.graph, outside)
    return maps, inside, outside


def test_a_map_file_swapped_with_a_symlink_is_read_inside_or_refused_never_outside(tmp_path):
    maps, inside, outside = _folders(tmp_path)
    seen = {"inside": 0, "refused": 0}
    # the threads' interleaving is the scheduler's: go on until both sides are met
    deadline = time.monotonic() + 60.0
    with _Swapper(maps, "swap.map", inside, outside) as sw:
        while (
            sw.swaps < 2 or sum(seen.values()) < 400 or not all(seen.values())
        ) and time.monotonic() < deadline:
            try:
                src = resolve_map_path(maps, "swap.map")
            except MapPathError:
                seen["refused"] += 1
                continue
            graph = load_map_file(src, limits=LoadLimits(), name="swap.map")
            assert graph_checksum(graph) == INSIDE  # never the map the symlink points to
            seen["inside"] += 1
    assert seen["inside"] and seen["refused"], seen  # both sides of the race were met


def test_load_map_during_a_symlink_swap_answers_ok_inside_or_permission_denied(tmp_path):
    maps, inside, outside = _folders(tmp_path)
    codes: dict[str, int] = {}
    with running(local_config(map_dir=maps, batch_processes=0), None) as (_, port):
        ch, api = stub(port)
        with _Swapper(maps, "swap.map", inside, outside):
            for _ in range(60):
                try:
                    info = api.LoadMap(pb.LoadMapRequest(map_id="m", path="swap.map"), timeout=60)
                except grpc.RpcError as err:
                    assert err.code() == grpc.StatusCode.PERMISSION_DENIED, err.details()
                    codes["PERMISSION_DENIED"] = codes.get("PERMISSION_DENIED", 0) + 1
                    continue
                assert info.checksum == INSIDE and info.source == "swap.map"
                codes["OK"] = codes.get("OK", 0) + 1
        assert codes.get("OK")  # (never INTERNAL, never the outside map)
        # paths through a symlinked folder or out of the folder are refused too
        os.symlink(tmp_path, maps / "up")
        for p in ("up/outside.map", "../outside.map", "up/maps/inside.map", str(outside)):
            with pytest.raises(grpc.RpcError) as ei:
                api.LoadMap(pb.LoadMapRequest(map_id="x", path=p), timeout=10)
            assert ei.value.code() == grpc.StatusCode.PERMISSION_DENIED
        (maps / "sub").mkdir()
        save_map(AMAP.graph, maps / "sub" / "c.map")
        assert api.LoadMap(pb.LoadMapRequest(map_id="x", path="sub/c.map"), timeout=60).source == "sub/c.map"
        assert api.LoadMap(pb.LoadMapRequest(map_id="y", path=str(inside)), timeout=60).checksum == INSIDE
        ch.close()


def _workers(server, old: int = -1, timeout: float = 120.0) -> int:
    t = time.monotonic()
    while time.monotonic() - t < timeout:
        pids = [p for p in server.batch_workers.pids() if p != old]
        if pids:
            return pids[0]
        time.sleep(0.05)
    raise AssertionError("no batch worker process started")


def _health(port: int, service: str) -> int:
    with grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
        req = health_pb2.HealthCheckRequest(service=service)
        return health_pb2_grpc.HealthStub(ch).Check(req, timeout=10).status


def _until(cond, timeout: float = 60.0) -> bool:
    t = time.monotonic()
    while time.monotonic() - t < timeout:
        if cond():
            return True
        time.sleep(0.05)
    return False


@pytest.mark.slow  # a server process building maps from sources
def test_a_map_prepared_again_over_its_file_still_answers_matchtrack_from_a_restarted_worker(tmp_path):
    path = tmp_path / "city.map"
    save_map(AMAP.graph, path)
    with running(local_config(maps=(("city", path),))) as (server, port):
        ch, api = stub(port)
        first = api.MatchTrack(pb.MatchTrackRequest(track=looped_track(AMAP, 40)), timeout=600)
        worker = _workers(server)
        save_map(OTHER.graph, path)  # what `mapmatch prep -o city.map` does: a new file, renamed over
        os.kill(worker, signal.SIGKILL)
        _workers(server, old=worker)
        again = api.MatchTrack(pb.MatchTrackRequest(track=looped_track(AMAP, 40)), timeout=600)
        assert again == first  # matched on the map loaded, not on the file now on disk
        info = api.GetMapInfo(pb.GetMapInfoRequest(map_id="city"), timeout=10)
        assert info.checksum == INSIDE  # the map served is the one loaded
        assert _health(port, "mapmatch.v1.MapMatch/city") == health_pb2.HealthCheckResponse.SERVING
        ch.close()


def _first_padding(path: Path) -> int:
    """The offset of a padding byte after an array (read by no one but the loader's check)."""
    import json

    raw = path.read_bytes()
    hlen = int.from_bytes(raw[8:16], "little")
    manifest = json.loads(raw[16 : 16 + hlen])
    for t in manifest["arrays"].values():
        if t["nbytes"] % 64:
            return 16 + hlen + t["offset"] + t["nbytes"]
    raise AssertionError("no array with padding")


@pytest.mark.slow  # a server process building maps from sources
def test_a_worker_that_cannot_load_its_map_turns_that_maps_health_not_serving(tmp_path):
    path = tmp_path / "city.map"
    save_map(AMAP.graph, path)
    with running(local_config(maps=(("city", path),))) as (server, port):
        ch, api = stub(port)
        worker = _workers(server)
        assert _until(lambda: not server.batch_workers.failed and worker in server.batch_workers.pids())
        with open(path, "r+b") as f:  # changed in place, in the inode the server holds
            f.seek(_first_padding(path))
            f.write(b"\x01")
        os.kill(worker, signal.SIGKILL)
        _workers(server, old=worker)
        name = "mapmatch.v1.MapMatch/city"
        assert _until(lambda: _health(port, name) == health_pb2.HealthCheckResponse.NOT_SERVING)
        with pytest.raises(grpc.RpcError) as ei:
            api.MatchTrack(pb.MatchTrackRequest(track=looped_track(AMAP, 20)), timeout=120)
        assert (
            ei.value.code() == grpc.StatusCode.FAILED_PRECONDITION and "load it again" in ei.value.details()
        )
        assert "city" in server.batch_workers.failed
        ch.close()


# ---------------------------------------------------------------------------------- children
def _slow_source(folder: Path, nodes: int = 300_000) -> Path:
    """An OSM XML file that takes seconds to build (many nodes, then one way)."""
    path = folder / "slow.osm"
    with open(path, "w") as f:
        f.write('<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6">\n')
        for i in range(1, nodes + 1):
            f.write(f'<node id="{i}" lat="{60 + i * 1e-6:.7f}" lon="{24 + i * 1e-6:.7f}" version="1"/>\n')
        f.write(
            '<way id="1" version="1"><nd ref="1"/><nd ref="2"/><tag k="highway" v="residential"/></way>\n'
        )
        f.write("</osm>\n")
    return path


def _serve(tmp_path: Path, maps: Path, grace: float) -> tuple[subprocess.Popen[str], int]:
    """``mapmatch serve`` with a map and ``--map-dir maps``; its log goes to ``tmp_path/serve.log``."""
    save_map(AMAP.graph, maps / "city.map")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MAPMATCH_GRACE": str(grace)}
    cmd = [sys.executable, "-m", "mapmatch", "serve", "--map", f"city={maps / 'city.map'}",
           "--map-dir", str(maps), "--address", "127.0.0.1:0", "--batch-processes", "1"]  # fmt: skip
    log = open(tmp_path / "serve.log", "w")  # noqa: SIM115 (the server process writes it)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True, env=env, cwd=ROOT)
    log.close()
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if "listening on" not in line:
        proc.kill()
        raise AssertionError(f"server did not start: {line!r}")
    return proc, int(line.split("listening on ")[1].split()[0].rsplit(":", 1)[1])


def _children(pid: int, marker: str) -> list[psutil.Process]:
    try:
        kids = psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []
    out = []
    for k in kids:
        try:
            if marker in " ".join(k.cmdline()):
                out.append(k)
        except psutil.Error:
            pass
    return out


def _alive(procs: list[psutil.Process]) -> list[psutil.Process]:
    out = []
    for p in procs:
        try:
            if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                out.append(p)
        except psutil.NoSuchProcess:
            pass
    return out


def _build_dirs(pid: int) -> list[Path]:
    return list(Path(tempfile.gettempdir()).glob(f"{BUILD_PREFIX}{pid}-*"))


@pytest.mark.slow  # a server process building maps from sources
def test_a_killed_server_takes_its_build_child_and_batch_worker_with_it(tmp_path):
    maps = tmp_path / "maps"
    maps.mkdir()
    _slow_source(maps)
    proc, port = _serve(tmp_path, maps, grace=2.0)
    try:
        assert _until(lambda: _children(proc.pid, "multiprocessing"))  # the batch worker
        kids = _children(proc.pid, "multiprocessing")
        _, api = stub(port)
        fut = api.LoadMap.future(pb.LoadMapRequest(map_id="slow", path="slow.osm"), timeout=300)
        assert _until(lambda: _children(proc.pid, "service.maps"))
        assert _until(lambda: bool(_build_dirs(proc.pid)))
        kids += _children(proc.pid, "service.maps")
        proc.kill()
        proc.wait()
        assert _until(lambda: not _alive(kids), 30)
        assert _until(lambda: not _build_dirs(proc.pid), 30)  # the build child removed its folder
        with pytest.raises(grpc.RpcError):
            fut.result()
    finally:
        if proc.poll() is None:
            proc.kill()


@pytest.mark.slow  # a server process building maps from sources
def test_sigterm_during_a_build_stops_within_the_grace_and_leaves_nothing(tmp_path):
    maps = tmp_path / "maps"
    maps.mkdir()
    _slow_source(maps, nodes=1_500_000)  # a build of a minute or more
    proc, port = _serve(tmp_path, maps, grace=1.0)
    try:
        _, api = stub(port)
        fut = api.LoadMap.future(pb.LoadMapRequest(map_id="slow", path="slow.osm"), timeout=300)
        assert _until(lambda: _children(proc.pid, "service.maps"))
        kids = _children(proc.pid, "service.maps") + _children(proc.pid, "multiprocessing")
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
        print(f"exit {time.monotonic() - t0:.1f} s after SIGTERM (grace 1 s), load {os.getloadavg()[0]:.1f}")
        assert "stopped 1 map build(s) in flight" in (tmp_path / "serve.log").read_text()  # not waited for
        assert _until(lambda: not _alive(kids), 30)
        assert not _build_dirs(proc.pid)
        with pytest.raises(grpc.RpcError):
            fut.result()
    finally:
        if proc.poll() is None:
            proc.kill()


@pytest.mark.slow  # a server process building maps from sources
def test_load_map_builds_osm_and_shapefile_sources_through_their_descriptors(tmp_path):
    import geopandas as gpd

    from graph.build import build_map

    data = ROOT / "tests" / "data"
    (tmp_path / "tiny.osm").write_bytes((data / "prep_tiny.osm").read_bytes())
    roads = gpd.read_file(data / "roads_ft_tf.geojson")
    roads[roads.geometry.geom_type != "Point"].to_crs("EPSG:3035").to_file(tmp_path / "roads.shp")
    want = build_map(tmp_path / "roads.shp").n_edges  # read by name, with its .shx, .dbf and .prj
    with running(local_config(map_dir=tmp_path, batch_processes=0), None) as (_, port):
        ch, api = stub(port)
        info = api.LoadMap(pb.LoadMapRequest(map_id="t", path="tiny.osm"), timeout=150)
        assert info.edge_count > 0 and info.source == "tiny.osm"
        info = api.LoadMap(pb.LoadMapRequest(map_id="s", path="roads.shp"), timeout=150)
        assert info.edge_count == want and info.source == "roads.shp"
        ch.close()
    assert not _build_dirs(os.getpid())
