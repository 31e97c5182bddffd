"""Compare the two PBF readers for map preparation: pyosmium (what graph.osm uses) and pyrosm.

For each map and reader, a fresh subprocess reads the drivable ways with node coordinates and
prints wall time, peak RSS (``ru_maxrss``) and how much the read added to the RSS after imports.

    python bench/bench_osm_readers.py [FILE.osm.pbf ...]
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CHILD = r"""
import json, resource, sys, time
from pathlib import Path
reader, path = sys.argv[1], Path(sys.argv[2])
if reader == "osmium":
    import osmium
    from graph.osm import network_filter, scan_osm
    keep = network_filter("drive")  # imports osmnx: outside the timing
else:
    import pyrosm
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t = time.perf_counter()
if reader == "osmium":
    ways_, rels = scan_osm(path, keep, {})
    ways, nodes = len(ways_), len({r[0] for w in ways_ for r in w[2]})
else:
    osm = pyrosm.OSM(str(path))
    n, e = osm.get_network(network_type="driving", nodes=True)
    ways, nodes = len(e), len(n)
dt = time.perf_counter() - t
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"s": dt, "rss_mb": rss / 1024, "rss_import_mb": rss0 / 1024, "ways": ways, "nodes": nodes}))
"""


def measure(reader: str, path: Path) -> dict[str, float]:
    out = subprocess.run(
        [sys.executable, "-c", CHILD, reader, str(path)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        check=False,
    )
    if out.returncode != 0:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr.strip() else "failed"}  # type: ignore[dict-item]
    return json.loads(out.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def main() -> None:
    from tests.conftest import OSM_DIR, helsinki_pbf

    files = [Path(a) for a in sys.argv[1:]] or [
        helsinki_pbf(),
        OSM_DIR / "monaco.osm.pbf",
        OSM_DIR / "andorra.osm.pbf",
    ]
    print(f"{'map':<20} {'reader':<8} {'time s':>7} {'peak MB':>8} {'+read MB':>9} {'ways':>7} {'nodes':>7}")
    for f in files:
        if not f.exists():
            print(f"{f.name:<20} missing")
            continue
        for reader in ("osmium", "pyrosm"):
            r = measure(reader, f)
            if "error" in r:
                print(f"{f.name:<20} {reader:<8} error: {r['error']}")
                continue
            added = r["rss_mb"] - r["rss_import_mb"]
            print(
                f"{f.name:<20} {reader:<8} {r['s']:7.2f} {r['rss_mb']:8.0f} {added:9.0f} "
                f"{r['ways']:7d} {r['nodes']:7d}"
            )
    print(
        "osmium: graph.osm.scan_osm: drivable ways (osmnx filter) with node locations, restriction relations"
    )
    print("pyrosm: get_network('driving', nodes=True) -> nodes and edges GeoDataFrames")


if __name__ == "__main__":
    main()
