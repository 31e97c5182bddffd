"""Fix generators for online-matcher tests: drive along a path of ASCII-map nodes."""

from __future__ import annotations

import math

import numpy as np

from graph.ascii import AsciiMap
from graph.projection import to_lonlat
from mapmatch.types import Fix


def drive(
    amap: AsciiMap,
    route: str | list[str],
    *,
    speed: float = 10.0,
    dt: float = 1.0,
    noise: float = 0.0,
    seed: int = 0,
    t0: float = 0.0,
    sigma: float = math.nan,
    odometer: bool = True,
    heading_noise: float = 0.0,
    start_offset: float = 0.0,
    points: list[tuple[float, float]] | None = None,
) -> list[Fix]:
    """Fixes every ``dt`` s at ``speed`` m/s along the polyline through the named nodes.

    ``points`` replaces the node route with explicit (x, y) positions in metres.
    """
    pts = np.array(points if points is not None else [amap.xy(n) for n in route], dtype=float)
    seg = np.diff(pts, axis=0)
    lens = np.hypot(seg[:, 0], seg[:, 1])
    cum = np.concatenate([[0.0], np.cumsum(lens)])
    rng = np.random.default_rng(seed)
    step = speed * dt
    n = int((cum[-1] - start_offset) // step) + 1
    out = []
    for i in range(n):
        s = start_offset + i * step
        j = min(int(np.searchsorted(cum, s, side="right")) - 1, len(lens) - 1)
        t = (s - cum[j]) / lens[j]
        x, y = pts[j] + t * seg[j]
        hd = math.degrees(math.atan2(seg[j, 0], seg[j, 1])) % 360.0
        if noise:
            x += rng.normal(0, noise)
            y += rng.normal(0, noise)
        if heading_noise:
            hd = (hd + rng.normal(0, heading_noise)) % 360.0
        lon, lat = to_lonlat(amap.graph.crs, [x], [y])[0]
        out.append(
            Fix(
                time=t0 + i * dt,
                lat=float(lat),
                lon=float(lon),
                heading=hd,
                pos_sigma=sigma,
                speed=speed,
                distance=step if (odometer and i) else math.nan,
                gps_valid=True,
            )
        )
    return out
