"""A digest of the batch matcher's answers on the shared Kubicka tracks (REAL GPS), to show that a
speed change leaves every answer identical.

Each track's map is loaded as the bench loads it (``bench/peers_adapter.py``: ``build_map`` and
the route table), the track is sub-sampled as the peers' harness does (every S-th fix and the
last) and matched with ``lonlat=True``; every field of the answer (per point: status, edge,
offset, lon/lat, distance; routes, splits, length, confidence, route geometry in lon/lat and in
the map's CRS) goes into a SHA-256, floats by their exact bits. Prints one digest per track and
S and one over all of them. With ``--choices``, only the choices go in (per point: status and
edge; routes and splits): the digest a change that moves distances by rounding alone keeps.

    python bench/hash_batch.py                 # all 15 tracks, S = 1, 10, 30
    python bench/hash_batch.py --choices       # the matched edges, routes and splits only
    python bench/hash_batch.py --ids 0,14 --S 30
    python bench/hash_batch.py --set batch.split.off_map_cut=300      # which answers a setting changes
"""

from __future__ import annotations

import argparse
import hashlib
import struct
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT))

from bench_batch import _tracks  # noqa: E402

from mapmatch.types import Track, TrackMatch  # noqa: E402


def subsample(n: int, s: int) -> list[int]:
    """The peers' harness's sub-sampling (``engines_kubicka.subsample``)."""
    idx = list(range(0, n, s))
    if idx[-1] != n - 1:
        idx.append(n - 1)
    return idx


def digest(res: TrackMatch, *, choices: bool = False) -> str:
    """SHA-256 of every field of a filled answer (floats by their bits); with ``choices``, of the
    statuses, edges, routes and splits only."""
    h = hashlib.sha256()

    def floats(xs: object) -> None:
        a = np.ascontiguousarray(np.asarray(xs, dtype=np.float64))
        h.update(struct.pack("<q", a.size))
        h.update(a.tobytes())

    def ints(xs: object) -> None:
        a = np.ascontiguousarray(np.asarray(xs, dtype=np.int64))
        h.update(struct.pack("<q", a.size))
        h.update(a.tobytes())

    pts = res.points
    ints([p.index for p in pts])
    h.update("".join(str(p.status) for p in pts).encode())
    ints([p.edge for p in pts])
    if not choices:
        floats([[p.offset, p.lat, p.lon, p.dist] for p in pts])
    ints([len(r) for r in res.routes])
    for r in res.routes:
        ints(r)
    ints(res.splits)
    if choices:
        return h.hexdigest()
    floats([res.length_m, res.confidence])
    ints([len(r) for r in res.route_lonlat])
    for piece in res.route_lonlat:
        floats(piece)
    for xy in res.route_xy:
        floats(xy)
    return h.hexdigest()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ids", default="all", help="all, or comma-separated track numbers")
    ap.add_argument("--S", default="1,10,30")
    ap.add_argument("--choices", action="store_true", help="hash the choices only, not the floats")
    ap.add_argument("--set", action="append", default=[], dest="settings", metavar="SECTION.FIELD=VALUE")
    a = ap.parse_args()
    from mapmatch.batch import BATCH_CONFIG

    config = BATCH_CONFIG.with_settings(a.settings)
    peers_adapter, data, names = _tracks(a.ids)
    total = hashlib.sha256()
    for name in names:
        matcher = peers_adapter.load(data / name)
        header = (data / name / "track.csv").read_text().splitlines()[0].split(",")
        cols = {c: i for i, c in enumerate(header)}
        raw = np.loadtxt(data / name / "track.csv", delimiter=",", skiprows=1, ndmin=2)
        t, lat, lon = raw[:, cols["t"]], raw[:, cols["lat"]], raw[:, cols["lon"]]
        for s in (int(x) for x in a.S.split(",")):
            idx = np.asarray(subsample(len(t), s))
            res = matcher.match(Track(name, t[idx], lat[idx], lon[idx]), config)
            d = digest(res, choices=a.choices)
            total.update(f"{name}/{s}/{d}".encode())
            print(f"{name} S={s:2d} points={len(idx):5d} {d[:16]}", flush=True)
    print(f"all {total.hexdigest()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
