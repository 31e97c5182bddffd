"""A real Kubicka et al. (2015) track, matched end to end and scored against its true route."""

from __future__ import annotations

import itertools
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from mapmatch.batch import BatchMatcher
from mapmatch.io import Columns, read_tracks

pytestmark = pytest.mark.slow


def _score_module(shared: Path):  # the peers' scorer, used in place (never copied)
    peers = shared / "peers"
    if not (peers / "score.py").exists():
        pytest.skip(f"needs {peers / 'score.py'}")
    sys.path.insert(0, str(peers))
    import score  # type: ignore[import-not-found]

    return score


@pytest.mark.parametrize(("track", "S"), [("00000021", 1), ("00000021", 10), ("00000007", 30)])
def test_kubicka_track_matches_its_true_route(
    kubicka_dir: Path, shared_dir: Path, track: str, S: int
) -> None:
    from graph.build import build_map

    score = _score_module(shared_dir)
    d = kubicka_dir / track
    graph = build_map(d / "roads.geojson")
    (t,) = read_tracks(d / "track.csv", columns=Columns(time="t"))
    idx = np.r_[np.arange(0, len(t), S), len(t) - 1] if (len(t) - 1) % S else np.arange(0, len(t), S)
    t.time, t.lat, t.lon = t.time[idx], t.lat[idx], t.lon[idx]
    r = BatchMatcher(graph).match(t)
    assert len(r.routes) == 1 and r.splits == []
    truth = json.loads((d / "truth.geojson").read_text())
    first_last = ((t.lon[0], t.lat[0]), (t.lon[-1], t.lat[-1]))
    sc = score.score(truth, [[list(p) for p in piece] for piece in r.route_lonlat], first_last)
    assert sc["rmf"] < 0.01, sc
    assert sum(p.status != "unmatched" for p in r.points) >= 0.95 * len(idx)


def test_every_piece_of_a_route_torn_by_multipath_is_connected(kubicka_dir: Path) -> None:
    """A REAL track with SIMULATED multipath bursts (a third of the 1 Hz fixes start one) splits
    into several pieces. Each piece is a connected run of edges: a piece trimmed to nothing
    (its route only touches a node) stays empty and does not merge its neighbours into one."""
    import random

    from graph.build import build_map
    from graph.projection import to_lonlat, to_xy

    d = kubicka_dir / "00000035"
    graph = build_map(d / "roads.geojson")
    (t,) = read_tracks(d / "track.csv", columns=Columns(time="t"))
    x, y = to_xy(graph.crs, t.lon, t.lat).T
    rng = random.Random(23)
    ex, ey = np.zeros(len(t)), np.zeros(len(t))
    i = 0
    while i < len(t):  # bursts of 1-5 fixes, each displaced by one offset
        if rng.random() < 0.3:
            r, a = rng.uniform(50.0, 200.0), rng.uniform(0.0, 2.0 * np.pi)
            for k in range(i, min(len(t), i + rng.randint(1, 5))):
                ex[k], ey[k] = 0.5 * r * np.cos(a), r * np.sin(a)
                i = k
        i += 1
    t.lon, t.lat = to_lonlat(graph.crs, x + ex, y + ey).T
    r = BatchMatcher(graph).match(t)
    assert len(r.routes) == len(r.splits) + 1 > 5
    assert any(not piece for piece in r.routes)  # the case this test is for
    for piece in r.routes:
        for a, b in itertools.pairwise(piece):
            assert graph.edge_v[a] == graph.edge_u[b] or graph.edge_reverse[a] == b, (a, b)
