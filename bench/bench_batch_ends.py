"""Batch matching where the map ends before the track does (issue #14's class 1: a car park, a
driveway, an unmapped lane at a track's start or end), or misses a road mid-drive: ours, and the
peers with ``--engines``.

Each shared Kubicka track (REAL GPS) is matched on its own map with every road within
``--buffer`` metres of the true route's first and last ``--cut`` metres removed (SIMULATED
missing roads), sub-sampled as the peers' harness does (every S-th fix from fix 0, plus the
last). The figure that matters is d+, the road routed that the true route does not have: the
fixes by the missing roads should be left unmatched, not routed round to far roads. d− counts
the missing roads' own length too (no engine can match a road the map lacks). Scored by the
peers' ``score.py`` against the true route with the run's first and last fix. With ``--at
middle`` the roads go about the true route's midpoint instead (``--cut`` metres of it): a road
the map lacks mid-drive, whose fixes should be left unmatched and the route cut there.

    python bench/bench_batch_ends.py                      # cut 300 m, buffer 25 m, S = 1, 10, 30
    python bench/bench_batch_ends.py --cut 500 --buffer 3 --set batch.outliers.off_map_sigmas=4
    python bench/bench_batch_ends.py --at middle          # a road missing mid-route instead
    python bench/bench_batch_ends.py --engines custom,valhalla,osrm,fastmm   # the peers too

With peers, each track's cut map is also written as the peers read it (``roads.geojson`` and
``map.osm.pbf`` less the same roads) to ``~/.cache/mapmatch-peers/<ends|middle>_cut<C>_buf<B>/data``, and
``run_peers.py`` prepares and matches it there (the first run prepares every peer's map: a few
minutes); ours runs in process as without peers, scored the same way.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT))

from bench_batch import CACHE, PEERS, PEERS_PY, _tracks  # noqa: E402
from hash_batch import subsample  # noqa: E402


def without_ends(
    roads: dict[str, Any], truth: dict[str, Any], cut: float, buffer: float, *, at: str = "ends"
) -> dict[str, Any]:
    """``roads`` (GeoJSON) less every feature within ``buffer`` m of the true route's first and
    last ``cut`` m (``at="ends"``), or of its ``cut`` m about its midpoint (``at="middle"``);
    distances in the truth's UTM zone."""
    import shapely
    import shapely.ops
    from pyproj import Transformer

    fw = Transformer.from_crs("EPSG:4326", f"EPSG:{truth['properties']['utm_epsg']}", always_xy=True)
    parts = [np.column_stack(fw.transform(*np.asarray(p)[:, :2].T)) for p in truth["geometry"]["coordinates"]]
    line = shapely.LineString(np.vstack(parts))
    end = line.length
    if at == "middle":
        ends = [shapely.ops.substring(line, (end - cut) / 2, (end + cut) / 2)]
    else:
        ends = [shapely.ops.substring(line, 0.0, cut), shapely.ops.substring(line, end - cut, end)]
    zone = shapely.union_all([e.buffer(buffer) for e in ends])
    keep = []
    for f in roads["features"]:
        c = np.asarray(f["geometry"]["coordinates"], dtype=np.float64)
        if not zone.intersects(shapely.LineString(np.column_stack(fw.transform(c[:, 0], c[:, 1])))):
            keep.append(f)
    return {**roads, "features": keep}


def write_peer_track(src: Path, dst: Path, kept: dict[str, Any]) -> None:
    """``src``'s track folder with only ``kept``'s roads, for the peers: ``roads.geojson`` and
    ``map.osm.pbf`` (whose way ``i + 1`` is road feature ``i``), the rest copied."""
    import shutil

    import osmium

    dst.mkdir(parents=True, exist_ok=True)
    for f in ("track.csv", "truth.geojson", "meta.json"):
        shutil.copy2(src / f, dst / f)
    (dst / "roads.geojson").write_text(json.dumps(kept))
    ways = {int(f["properties"]["id"]) + 1 for f in kept["features"]}
    pbf = dst / "map.osm.pbf"
    part = dst / "map.osm.pbf.part"
    part.unlink(missing_ok=True)
    with osmium.SimpleWriter(osmium.io.File(str(part), "pbf")) as w:
        for o in osmium.FileProcessor(str(src / "map.osm.pbf")):
            if isinstance(o, osmium.osm.Node) or (isinstance(o, osmium.osm.Way) and o.id in ways):
                w.add(o)
    part.replace(pbf)


def run_peers(data: Path, engines: list[str], steps: list[int], ids: str) -> list[dict[str, Any]]:
    """The peers' rows (one per track, engine and S) from ``run_peers.py`` on ``data``'s tracks."""
    import os
    import subprocess

    cache = data.parent
    env = dict(os.environ, PEERS_DIR=str(CACHE / "venvs"))
    cmd = [str(PEERS_PY), str(PEERS / "run_peers.py"), "--data", str(data), "--cache", str(cache)]
    cmd += ["--engines", ",".join(engines), "--S", ",".join(map(str, steps)), "--tag", "ends"]
    if ids != "all":
        cmd += ["--ids", ids]
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL)
    out = cache / "results" / "ends.jsonl"
    return [json.loads(x) for x in out.read_text().splitlines() if x.strip()]


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--ids", default="all", help="all, or comma-separated track numbers")
    ap.add_argument("--S", default="1,10,30")
    ap.add_argument("--cut", type=float, default=300.0, help="metres of true route at each end")
    ap.add_argument("--buffer", type=float, default=25.0, help="roads within this many metres go")
    ap.add_argument(
        "--at", choices=("ends", "middle"), default="ends",
        help="cut the true route's ends, or the --cut metres about its midpoint (a road the map lacks)",
    )  # fmt: skip
    ap.add_argument("--set", action="append", default=[], dest="settings", metavar="SECTION.FIELD=VALUE")
    ap.add_argument("--engines", default="custom", help="custom (ours), and any of the peers' engines")
    a = ap.parse_args()
    peers = [e for e in a.engines.split(",") if e and e != "custom"]
    peer_data = CACHE / f"{a.at}_cut{a.cut:g}_buf{a.buffer:g}" / "data"
    sys.path.insert(0, str(PEERS))
    import score  # type: ignore[import-not-found]

    from mapmatch.batch import BATCH_CONFIG, BatchMatcher
    from mapmatch.io import Columns, read_tracks

    config = BATCH_CONFIG.with_settings(a.settings)
    adapter, data, names = _tracks(a.ids)
    steps = [int(s) for s in a.S.split(",")]
    rows: list[tuple[str, int, int, float, float, float, int]] = []
    print(f"{'track':9} {'S':>3} {'roads cut':>9} {'d+ m':>7} {'d- m':>7} {'RMF':>7} pieces")
    for name in names:
        src = data / name
        doc = json.loads((src / "truth.geojson").read_text())
        truth = doc if doc.get("type") == "Feature" else doc["features"][0]
        roads = json.loads((src / "roads.geojson").read_text())
        kept = without_ends(roads, truth, a.cut, a.buffer, at=a.at)
        if peers:
            write_peer_track(src, peer_data / name, kept)
        with tempfile.TemporaryDirectory() as tmp:
            (Path(tmp) / "roads.geojson").write_text(json.dumps(kept))
            matcher = BatchMatcher(adapter.load_graph(Path(tmp)), config=config)
        (track,) = read_tracks(src / "track.csv", columns=Columns(time="t"))
        cut_n = len(roads["features"]) - len(kept["features"])
        for s in steps:
            idx = subsample(len(track), s)
            sub = type(track)(track.track_id, track.time[idx], track.lat[idx], track.lon[idx])
            lines, info = adapter.convert(matcher, matcher.match(sub, lonlat=False))
            res = score.score(truth, lines, ((sub.lon[0], sub.lat[0]), (sub.lon[-1], sub.lat[-1])))
            rows.append((name, s, cut_n, res["d_plus_m"], res["d_minus_m"], res["rmf"], info["pieces"]))
            r = rows[-1]
            line = f"{r[0]:9} {r[1]:>3} {r[2]:>9} {r[3]:>7.0f} {r[4]:>7.0f} {r[5]:>7.4f} {r[6]:>6}"
            print(line, flush=True)
    by_engine: dict[str, list[tuple[int, float, float]]] = {"custom": [(r[1], r[3], r[5]) for r in rows]}
    if peers:
        for rec in run_peers(peer_data, peers, steps, a.ids):
            failed = rec.get("rmf") is None  # no route: scores 1, adds no road
            d_plus, rmf = (0.0, 1.0) if failed else (float(rec["d_plus_m"]), float(rec["rmf"]))
            run = (int(rec["S"]), d_plus, rmf)
            by_engine.setdefault(str(rec["engine"]), []).append(run)
    print(f"\n{a.at}, cut {a.cut:g} m, buffer {a.buffer:g} m: REAL GPS on maps with SIMULATED missing roads")
    for eng, runs in by_engine.items():
        for s in steps:
            d = [x[1] for x in runs if x[0] == s]
            rmfs = [x[2] for x in runs if x[0] == s]
            if d:
                print(
                    f"{eng:9} S={s:>2}: d+ mean {np.mean(d):.0f} m, max {max(d):.0f} m, over 300 m on "
                    f"{sum(x > 300 for x in d)} of {len(d)} tracks; mean RMF {np.mean(rmfs):.4f}"
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
