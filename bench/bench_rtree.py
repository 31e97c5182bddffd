"""Candidate search: a bulk-loaded rtree (libspatialindex) against shapely's STRtree
(:class:`graph.index.EdgeIndex`) and the compiled grid (:class:`mapmatch.gridindex.GridIndex`).

On the largest shared map (Kubicka 00000028 unless ``--map`` names a prepared map or a source),
it times building each index (the start-up search structure) and the candidate query of a real
track's points at the batch matcher's radius, and checks that the three find the same
(point, road) pairs. Prints a Markdown table with the machine's load average.

    python bench/bench_rtree.py [--map PATH] [--radius 50] [--repeat 20]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from shared_data import KUBICKA  # noqa: E402


def _best(fn: Callable[[], Any], repeat: int) -> tuple[float, Any]:
    """The least wall time of ``repeat`` runs, and the last answer."""
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def _rtree_build(index: Any) -> Any:
    """A bulk-loaded (STR packed) rtree over the segments' boxes."""
    from rtree import index as rindex

    a, b = index.seg_a, index.seg_b
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    props = rindex.Property(interleaved=True)
    return rindex.Index(
        ((i, (lo[i, 0], lo[i, 1], hi[i, 0], hi[i, 1]), None) for i in range(len(a))), properties=props
    )


def _rtree_pairs(tree: Any, index: Any, xy: NDArray[np.float64], radius: float) -> set[tuple[int, int]]:
    """(point, undirected road) pairs within ``radius``: the boxes from rtree's vectorised query,
    then the exact segment distance (the same test as the STRtree's ``dwithin``)."""
    ids, counts = tree.intersection_v(xy - radius, xy + radius)
    ids, counts = ids.astype(np.int64), counts.astype(np.int64)
    pi = np.repeat(np.arange(len(xy)), counts)
    a = index.seg_a[ids]
    ab = index.seg_b[ids] - a
    L2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12)
    t = np.clip(np.einsum("ij,ij->i", xy[pi] - a, ab) / L2, 0.0, 1.0)
    d = np.hypot(*(xy[pi] - (a + ab * t[:, None])).T)
    ok = d <= radius
    return set(zip(pi[ok].tolist(), index.seg_edge[ids[ok]].tolist(), strict=True))


def _undirected(c: Any, graph: Any) -> set[tuple[int, int]]:
    rev = graph.edge_reverse[c.edge]
    e = np.where((rev >= 0) & (rev < c.edge), rev, c.edge)
    return set(zip(c.point.tolist(), e.tolist(), strict=True))


def _load(path: Path) -> Any:
    from graph.artifact import MAGIC, load_map
    from graph.build import build_map

    with open(path, "rb") as fh:
        prepared = fh.read(len(MAGIC)) == MAGIC
    return load_map(path) if prepared else build_map(path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", type=Path, default=KUBICKA / "00000028" / "roads.geojson")
    ap.add_argument("--track", type=Path, default=KUBICKA / "00000028" / "track.csv")
    ap.add_argument("--radius", type=float, default=50.0)
    ap.add_argument("--repeat", type=int, default=20)
    args = ap.parse_args(argv)
    try:
        import rtree  # noqa: F401  (not a dependency of the package: `pip install rtree`)
    except ImportError:
        print("error: this comparison needs rtree: pip install rtree", file=sys.stderr)
        return 2
    if not args.map.is_file():
        print(f"error: no map at {args.map} (set MAPMATCH_SHARED or give --map)", file=sys.stderr)
        return 2
    from graph.index import EdgeIndex
    from graph.projection import to_xy
    from mapmatch.gridindex import GridIndex
    from mapmatch.io import read_tracks

    graph = _load(args.map)
    track = read_tracks(args.track)[0]
    xy = np.ascontiguousarray(to_xy(graph.crs, track.lon, track.lat))
    t_str, index = _best(lambda: EdgeIndex(graph), 3)
    t_grid, grid = _best(lambda: GridIndex(index), 3)
    t_rt, tree = _best(lambda: _rtree_build(index), 3)
    grid.query(xy[:10], args.radius)  # compiled (or loaded from the cache) before timing
    q_str, c_str = _best(lambda: index.query(xy, args.radius), args.repeat)
    q_grid, c_grid = _best(lambda: grid.query(xy, args.radius), args.repeat)
    q_rt, c_rt = _best(lambda: _rtree_pairs(tree, index, xy, args.radius), args.repeat)
    same = _undirected(c_str, graph) == _undirected(c_grid, graph) == c_rt
    n, m = len(xy), len(index.seg_a)
    print(f"# candidate search: {graph.n_edges:,} edges, {m:,} segments, {n:,} points, radius "
          f"{args.radius:g} m; same pairs: {same}; load average {os.getloadavg()[0]:.1f}")  # fmt: skip
    print("| index | build (s) | query of the track (ms) | per point (µs) |")
    print("|---|---|---|---|")
    for name, tb, tq in (
        ("compiled grid (`GridIndex`)", t_grid, q_grid),
        ("STRtree (`EdgeIndex`)", t_str, q_str),
        ("rtree, bulk-loaded", t_rt, q_rt),
    ):
        print(f"| {name} | {tb:.2f} | {tq * 1e3:.1f} | {tq / n * 1e6:.1f} |")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
