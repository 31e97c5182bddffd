"""The core install (``pip install mapmatch``, no extras): a process in which the map-preparation
libraries cannot be imported loads a prepared map, matches a track in batch and fixes online
(``mapmatch match``, ``mapmatch replay``) and serves both over gRPC; map preparation there
fails with the message that names the ``prep`` extra."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pandas as pd

from graph.artifact import save_map
from graph.extras import PREP_MODULES
from mapmatch.io import write_tracks
from tests.online_helpers import DriveSpec, drive
from tests.service_util import city
from tests.test_match_cli import make_tracks
from tests.test_replay import fix_rows, write_fixes

ROOT = Path(__file__).resolve().parents[1]
# the other extras are not needed either: plots, demo, dask, redis (pyarrow is core: batch parts)
BLOCKED = (*PREP_MODULES, "matplotlib", "folium", "pyrosm", "dask", "distributed", "redis")

CHILD = textwrap.dedent(
    """
    import sys
    for name in {blocked!r}:
        sys.modules[name] = None  # `import name` raises ImportError in this process

    from pathlib import Path

    import grpc

    from graph.errors import MissingExtraError
    from mapmatch.cli import main
    from service.config import ServerConfig
    from service.gen import mapmatch_pb2 as pb
    from service.gen import mapmatch_pb2_grpc as pb_grpc
    from service.server import start_server

    d = Path(sys.argv[1])
    flags = ["--no-progress"]
    assert main(["match", "--map", str(d / "city.map"), str(d / "fleet.csv"), "-o",
                 str(d / "points.csv"), "--workers", "1", *flags]) == 0
    assert main(["replay", "--map", str(d / "city.map"), str(d / "fixes.csv"), "-o",
                 str(d / "online.csv")]) == 0
    try:
        from graph.build import build_map
        build_map(d / "roads.geojson")
    except MissingExtraError as exc:
        print("prep:", exc)
    config = ServerConfig(address="127.0.0.1:0", grace=1.0, reuse_port=False,
                          maps=(("city", d / "city.map"),), batch_processes=0)
    server, port = start_server(config)
    try:
        with grpc.insecure_channel(f"127.0.0.1:{{port}}") as ch:
            api = pb_grpc.MapMatchStub(ch)
            track = pb.Track(track_id="t", time=[0.0, 3.0, 6.0, 9.0],
                             lat={lat!r}, lon={lon!r})
            res = api.MatchTrack(pb.MatchTrackRequest(map_id="city", track=track), timeout=120)
            print("served edges:", [e for r in res.routes for e in r.edges])
    finally:
        server.stop(0)
    leaked = [m for m in {blocked!r} if sys.modules.get(m) is not None]
    print("leaked:", leaked)
    """
)


def test_core_path_imports_no_extra(tmp_path: Path) -> None:
    m = city()
    save_map(m.graph, tmp_path / "city.map")
    tracks = make_tracks(m, 3)
    write_tracks(tmp_path / "fleet.csv", tracks)
    write_fixes(
        tmp_path / "fixes.csv", fix_rows("car-1", drive(m, "abc", DriveSpec(speed=8, noise=1.0, seed=1)))
    )
    t = tracks[0]
    code = CHILD.format(blocked=BLOCKED, lat=[float(x) for x in t.lat[:4]], lon=[float(x) for x in t.lon[:4]])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, env=env, timeout=900
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout
    assert "prep: map preparation needs osmnx, which is not installed: pip install 'mapmatch[prep]'" in out
    assert "leaked: []" in out
    assert "served edges: [" in out and "served edges: []" not in out
    points = pd.read_csv(tmp_path / "points.csv")
    assert len(points) == sum(len(t) for t in tracks) and set(points["status"]) == {"matched"}
    online = pd.read_csv(tmp_path / "online.csv")
    assert len(online) > 5 and online["edge"].notna().all()
