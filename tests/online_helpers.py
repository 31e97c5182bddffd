"""Fix generators for online-matcher tests: drive along a path of ASCII-map nodes."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from graph.ascii import AsciiMap
from graph.projection import to_lonlat
from mapmatch.types import Fix


@dataclass(frozen=True)
class DriveSpec:
    """How :func:`drive` moves and samples along its route.

    Attributes
    ----------
    speed : float
        Metres per second, constant; also each fix's reported speed.
    dt : float
        Seconds between fixes.
    noise : float
        Standard deviation (m) of the Gaussian position noise on each axis.
    seed : int
        Seed of the noise generator.
    t0 : float
        Time of the first fix.
    sigma : float
        Reported position sigma of each fix (NaN: none).
    odometer : bool
        Whether fixes after the first carry the distance driven since the previous one.
    heading_noise : float
        Standard deviation (degrees) of the Gaussian heading noise.
    start_offset : float
        Metres along the route of the first fix.
    """

    speed: float = 10.0
    dt: float = 1.0
    noise: float = 0.0
    seed: int = 0
    t0: float = 0.0
    sigma: float = math.nan
    odometer: bool = True
    heading_noise: float = 0.0
    start_offset: float = 0.0


def drive(
    amap: AsciiMap,
    route: str | list[str],
    spec: DriveSpec | None = None,
    *,
    points: list[tuple[float, float]] | None = None,
) -> list[Fix]:
    """Fixes every ``spec.dt`` s at ``spec.speed`` m/s along the polyline through the named nodes.

    ``spec`` defaults to ``DriveSpec()``. ``points`` replaces the node route with explicit
    (x, y) positions in metres.
    """
    sp = spec if spec is not None else DriveSpec()
    pts = np.array(points if points is not None else [amap.xy(n) for n in route], dtype=float)
    seg = np.diff(pts, axis=0)
    lens = np.hypot(seg[:, 0], seg[:, 1])
    cum = np.concatenate([[0.0], np.cumsum(lens)])
    rng = np.random.default_rng(sp.seed)
    step = sp.speed * sp.dt
    n = int((cum[-1] - sp.start_offset) // step) + 1
    out = []
    for i in range(n):
        s = sp.start_offset + i * step
        j = min(int(np.searchsorted(cum, s, side="right")) - 1, len(lens) - 1)
        t = (s - cum[j]) / lens[j]
        x, y = pts[j] + t * seg[j]
        hd = math.degrees(math.atan2(seg[j, 0], seg[j, 1])) % 360.0
        if sp.noise:
            x += rng.normal(0, sp.noise)
            y += rng.normal(0, sp.noise)
        if sp.heading_noise:
            hd = (hd + rng.normal(0, sp.heading_noise)) % 360.0
        lon, lat = to_lonlat(amap.graph.crs, [x], [y])[0]
        out.append(
            Fix(
                time=sp.t0 + i * sp.dt,
                lat=float(lat),
                lon=float(lon),
                heading=hd,
                pos_sigma=sp.sigma,
                speed=sp.speed,
                distance=step if (sp.odometer and i) else math.nan,
                gps_valid=True,
            )
        )
    return out
