"""Online matcher at a standstill: a vehicle standing between two roads.

A standing vehicle's fixes are not independent: their error is the receiver's, minutes long,
so they must not count once per fix; but neither are they worthless, or the first fix alone
(which may lie nearer the other road) decides the road for the whole stop.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from graph.ascii import AsciiMap, parse_ascii_map
from graph.projection import to_lonlat
from mapmatch.config import DEFAULT_CONFIG
from mapmatch.online import OnlineMatcher
from mapmatch.types import Fix

# two roads 16 m apart (scale 4: lines 8 m apart), joined at both ends
TWO_ROADS = """
a--------------------------------------b
 \\                                    /
  c----------------------------------d
"""


def _fix(amap: AsciiMap, t: float, x: float, y: float, moved: float) -> Fix:
    lon, lat = to_lonlat(amap.graph.crs, [x], [y])[0]
    return Fix(
        time=t,
        lat=float(lat),
        lon=float(lon),
        heading=90.0,
        heading_sigma=2.0,
        pos_sigma=4.0,
        speed=moved,
        distance=moved if t > 0.0 else math.nan,
        gps_valid=True,
    )


def parked_start(amap: AsciiMap, *, stand: int, seed: int) -> list[Fix]:
    """A vehicle parked on c-d for ``stand`` seconds at 1 Hz, then driving east at 5 m/s: its
    first fix lies 11 m towards a-b (5 m from it), the others around the truth (σ 2 m)."""
    c, d = amap.xy("c"), amap.xy("d")
    x0, y0 = float(c[0] + 0.4 * (d[0] - c[0])), float(c[1])
    rng = np.random.default_rng(seed)
    fixes = [_fix(amap, 0.0, x0, y0 + 11.0, 0.0)]
    for i in range(1, stand):
        dx, dy = rng.normal(0.0, 2.0, 2)
        fixes.append(_fix(amap, float(i), x0 + dx, y0 + dy, 0.0))
    for i in range(stand, stand + 8):
        x0 += 5.0
        dx, dy = rng.normal(0.0, 2.0, 2)
        fixes.append(_fix(amap, float(i), x0 + dx, y0 + dy, 5.0))
    return fixes


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_start_up_standing_between_two_roads_takes_the_road_its_fixes_show(seed: int) -> None:
    """The stand's fixes, weighed by the time they span over the error's correlation time
    (``bias.bias_time``), outweigh its first fix within half a minute, and the road they show
    is kept once the vehicle moves; counted as no evidence (the distance share alone, as with
    no correlation time), the first fix decides the whole stand."""
    amap = parse_ascii_map(TWO_ROADS, scale=4.0)
    cd, ab = amap.edge("c", "d"), amap.edge("a", "b")
    fixes = parked_start(amap, stand=90, seed=seed)
    no_time = DEFAULT_CONFIG.with_settings(["online.bias.bias_time=0"])
    for cfg, road, span in ((DEFAULT_CONFIG, cd, slice(30, None)), (no_time, ab, slice(0, 90))):
        m = OnlineMatcher(amap.graph, config=cfg)
        st = m.new_session()
        got = [m.update(st, f).edge for f in fixes]
        assert got[0] == ab  # the first fix lies nearer a-b
        assert set(got[span]) == {road}
