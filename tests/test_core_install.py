"""The core install (``pip install mapmatch``, no extras), in processes where an import hook
refuses every optional library (pandas, pyarrow, rapidfuzz, the ``prep`` and ``plots``
libraries) as if it were not installed: ``mapmatch match`` and ``replay`` on CSV and GPX, and
the gRPC server on a prepared map (a StreamFixes stream and a MatchTrack answered by a batch
worker process). A command that needs a missing extra exits 2 with the message naming it."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from graph.artifact import save_map
from mapmatch.io import write_tracks
from tests.online_helpers import DriveSpec, drive
from tests.service_util import city
from tests.test_match_cli import make_tracks
from tests.test_replay import fix_rows, write_fixes

ROOT = Path(__file__).resolve().parents[1]
BLOCKED = ("pandas", "pyarrow", "rapidfuzz", "osmnx", "geopandas", "pyogrio", "networkx", "matplotlib")

SITE = textwrap.dedent(
    """
    import sys

    BLOCKED = frozenset({blocked!r})


    class NotInstalled:
        '''Refuses the blocked modules as an install without them would.'''

        def find_spec(self, name, path=None, target=None):
            if name.partition(".")[0] in BLOCKED:
                raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
            return None


    sys.meta_path.insert(0, NotInstalled())
    """
)

SERVE = textwrap.dedent(
    """
    import json
    import sys
    from pathlib import Path

    import grpc

    from mapmatch.fixes import read_fixes_csv
    from service import convert
    from service.config import ServerConfig
    from service.gen import mapmatch_pb2 as pb
    from service.gen import mapmatch_pb2_grpc as pb_grpc
    from service.server import start_server

    d = Path(sys.argv[1])
    fixes = read_fixes_csv(d / "fixes.csv")["car-1"]
    track = json.loads((d / "track.json").read_text())
    config = ServerConfig(address="127.0.0.1:0", grace=1.0, reuse_port=False,
                          maps=(("city", d / "city.map"),), batch_processes=1)
    server, port = start_server(config)
    try:
        with grpc.insecure_channel(f"127.0.0.1:{{port}}") as ch:
            api = pb_grpc.MapMatchStub(ch)
            reqs = [pb.FixRequest(map_id="city", vehicle_id="car-1", seq=i, fix=convert.fix_to_proto(f))
                    for i, f in enumerate(fixes)]
            snaps = list(api.StreamFixes(iter(reqs), timeout=300))
            print("streamed:", len(snaps), sum(s.result.edge >= 0 for s in snaps))
            res = api.MatchTrack(pb.MatchTrackRequest(map_id="city", track=pb.Track(**track)), timeout=300)
            print("batch edges:", [e for r in res.routes for e in r.edges])
    finally:
        server.stop(0)
    print("loaded:", sorted(m for m in sys.modules if m.partition(".")[0] in {blocked!r}))
    """
)


@pytest.fixture(scope="module")
def core(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, str]]:
    """A folder with a prepared map, tracks (CSV, GPX), fixes, and the environment of a
    process in which the optional libraries cannot be imported."""
    d = tmp_path_factory.mktemp("core")
    m = city()
    save_map(m.graph, d / "city.map")
    tracks = make_tracks(m, 3)
    write_tracks(d / "fleet.csv", tracks)
    write_tracks(d / "fleet.gpx", tracks)
    t = tracks[0]
    (d / "track.json").write_text(
        json.dumps({"track_id": "t", "time": t.time.tolist(), "lat": t.lat.tolist(), "lon": t.lon.tolist()})
    )
    write_fixes(d / "fixes.csv", fix_rows("car-1", drive(m, "abc", DriveSpec(speed=8, noise=1.0, seed=1))))
    (d / "roads.geojson").write_text(
        json.dumps({"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {},
                    "geometry": {"type": "LineString", "coordinates": [[24.9, 60.1], [24.91, 60.1]]}}]})
    )  # fmt: skip
    site = d / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(SITE.format(blocked=BLOCKED))
    path = os.pathsep.join([str(site), str(ROOT), os.environ.get("PYTHONPATH", "")])
    return d, {**os.environ, "PYTHONPATH": path}


def _mapmatch(env: dict[str, str], *argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "mapmatch", "-q", *argv], capture_output=True, text=True, env=env, timeout=900
    )


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_the_hook_refuses_the_optional_libraries(core: tuple[Path, dict[str, str]]) -> None:
    _, env = core
    code = "import importlib.util, pandas"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode != 0 and "No module named 'pandas'" in proc.stderr


@pytest.mark.slow  # six CLI processes under the core-install import hook
def test_match_and_replay_on_csv_and_gpx(core: tuple[Path, dict[str, str]]) -> None:
    d, env = core
    m = str(d / "city.map")
    for src in ("fleet.csv", "fleet.gpx"):
        out = d / f"points-{src}.csv"
        proc = _mapmatch(env, "match", "--map", m, str(d / src), "-o", str(out), "--workers", "1")
        assert proc.returncode == 0, proc.stderr[-3000:]
        rows = _rows(out)
        assert len(rows) == 3 * 12 and {r["status"] for r in rows} == {"matched"}
    gj = d / "routes.geojson"
    proc = _mapmatch(env, "match", "--map", m, str(d / "fleet.csv"), "-o", str(gj), "--workers", "1")
    assert proc.returncode == 0, proc.stderr[-3000:]
    features = json.loads(gj.read_text())["features"]
    assert [f["properties"]["track_id"] for f in features] == ["v00", "v01", "v02"]
    for src in ("fixes.csv", "fleet.gpx"):
        out = d / f"online-{src}.csv"
        proc = _mapmatch(env, "replay", "--map", m, str(d / src), "-o", str(out))
        assert proc.returncode == 0, proc.stderr[-3000:]
        rows = _rows(out)
        assert len(rows) > 5 and sum(r["edge"] not in ("", "-1") for r in rows) > len(rows) // 2


@pytest.mark.slow  # a server and its batch worker under the import hook
def test_serve_streams_and_batch_worker_without_extras(core: tuple[Path, dict[str, str]]) -> None:
    d, env = core
    code = SERVE.format(blocked=BLOCKED)
    proc = subprocess.run(
        [sys.executable, "-c", code, str(d)], capture_output=True, text=True, env=env, timeout=900
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = dict(line.split(": ", 1) for line in proc.stdout.splitlines() if ": " in line)
    n, placed = map(int, lines["streamed"].split())
    assert n > 5 and placed > n // 2
    assert lines["batch edges"] not in ("[]", "")
    assert lines["loaded"] == "[]"


@pytest.mark.parametrize(
    ("argv", "extra"),
    [
        (["match", "--map", "{d}/city.map", "{d}/fleet.csv", "-o", "{d}/out.parquet"], "tables"),
        (["match", "--map", "{d}/city.map", "{d}/fleet.csv", "-o", "{d}/out-folder"], "tables"),
        (["simulate", "--map", "{d}/city.map", "--random-route", "-o", "{d}/s.csv"], "tables"),
        (["eval", "--route", "{d}/routes.geojson", "--matched", "{d}/fixes.csv"], "eval"),
        (["prep", "{d}/roads.geojson", "-o", "{d}/roads.map"], "prep"),
    ],
)  # fmt: skip
def test_a_missing_extra_is_named(core: tuple[Path, dict[str, str]], argv: list[str], extra: str) -> None:
    d, env = core
    proc = _mapmatch(env, *[a.format(d=d) for a in argv])
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert f"pip install 'mapmatch[{extra}]'" in proc.stderr and "Traceback" not in proc.stderr
