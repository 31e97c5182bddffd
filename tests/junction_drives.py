"""Drives past three-way junctions drawn as ASCII art with their branches bent to true angles,
for ``test_junction_classes``: GPS noise (white or correlated), a constant bias, dead-reckoned
stretches, and the per-fix truth (distance along the route) to score the answers against."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graph.ascii import AsciiMap
from graph.projection import to_lonlat
from graph.road_graph import Edges, Nodes, RoadGraph
from mapmatch.types import Fix


def bent(amap: AsciiMap, places: dict[str, tuple[str, float, float]]) -> AsciiMap:
    """The map with some intersections moved: ``name -> (from_node, length_m, bearing_deg)``
    puts ``name`` that far from ``from_node`` (already placed) on that bearing (clockwise from
    north). The drawing gives the roads; this gives the angles a drawing cannot."""
    g = amap.graph
    xy = np.array(g.node_xy, dtype=np.float64)
    for name, (src, length, bearing) in places.items():
        b = math.radians(bearing)
        xy[amap.nodes[name]] = xy[amap.nodes[src]] + length * np.array([math.sin(b), math.cos(b)])
    graph = RoadGraph.from_edges(
        g.crs, Nodes(xy, None, g.node_id), Edges(g.edge_u, g.edge_v, way_id=g.edge_way_id)
    )
    return AsciiMap(graph=graph, nodes=amap.nodes, scale=amap.scale)


@dataclass(frozen=True)
class Gps:
    """How the fixes err. ``noise``: σ per axis (m) of a Gauss-Markov error with correlation
    time ``tau`` (s; 0: independent per fix); ``bias``: a constant (east, north) offset (m);
    ``heading_noise``: σ of the reported heading (degrees)."""

    noise: float = 0.0
    tau: float = 0.0
    bias: tuple[float, float] = (0.0, 0.0)
    heading_noise: float = 0.0


@dataclass(frozen=True)
class Outage:
    """GPS lost from ``start`` to ``end`` metres along the route: the fixes are dead reckoned
    from the last GPS fix with the odometer reading ``odo_scale`` times the truth and the
    heading off by ``heading_bias`` degrees."""

    start: float
    end: float
    odo_scale: float = 1.03
    heading_bias: float = 1.0


@dataclass(frozen=True)
class Drive:
    """The fixes and, per fix, the true distance along the route (m)."""

    fixes: list[Fix]
    s: NDArray[np.float64]


def route_xy(amap: AsciiMap, route: str) -> NDArray[np.float64]:
    """The polyline through the named intersections."""
    return np.array([amap.xy(n) for n in route], dtype=np.float64)


def _along(pts: NDArray[np.float64], s: float) -> tuple[NDArray[np.float64], float]:
    """Position and heading (degrees) ``s`` metres along the polyline."""
    seg = np.diff(pts, axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
    j = min(int(np.searchsorted(cum, s, side="right")) - 1, len(seg) - 1)
    t = (s - cum[j]) / (cum[j + 1] - cum[j])
    return pts[j] + t * seg[j], math.degrees(math.atan2(seg[j, 0], seg[j, 1])) % 360.0


def _errors(gps: Gps, n: int, dt: float, rng: np.random.Generator) -> NDArray[np.float64]:
    """(n, 2) position errors: the bias plus a Gauss-Markov process of σ ``gps.noise``."""
    a = math.exp(-dt / gps.tau) if gps.tau > 0 else 0.0
    white = rng.normal(0.0, gps.noise, (n, 2))
    out = np.empty((n, 2))
    out[0] = white[0]
    for i in range(1, n):
        out[i] = a * out[i - 1] + math.sqrt(1.0 - a * a) * white[i]
    return out + np.asarray(gps.bias)


def simulate(
    amap: AsciiMap,
    route: str,
    *,
    gps: Gps,
    seed: int,
    speed: float = 12.0,
    dt: float = 1.0,
    outage: Outage | None = None,
) -> Drive:
    """Fixes every ``dt`` s at ``speed`` m/s along ``route`` (intersection letters)."""
    pts = route_xy(amap, route)
    total = float(np.sum(np.hypot(*np.diff(pts, axis=0).T)))
    rng = np.random.default_rng(seed)
    n = int(total // (speed * dt)) + 1
    s = np.arange(n) * speed * dt
    err = _errors(gps, n, dt, rng)
    hd_err = rng.normal(0.0, gps.heading_noise, n) if gps.heading_noise else np.zeros(n)
    fixes: list[Fix] = []
    dr: NDArray[np.float64] | None = None
    sigma = math.hypot(gps.noise, math.hypot(*gps.bias)) or 1.0
    for i in range(n):
        p, hd = _along(pts, float(s[i]))
        lost = outage is not None and outage.start <= s[i] < outage.end
        step = speed * dt if i else math.nan
        if lost and outage is not None:
            if dr is None:
                dr = np.array(_xy(amap, fixes[-1]))
            h = math.radians(hd + outage.heading_bias)
            dr = dr + outage.odo_scale * step * np.array([math.sin(h), math.cos(h)])
            x, y = dr
            step *= outage.odo_scale
        else:
            dr = None
            x, y = p + err[i]
        lon, lat = to_lonlat(amap.graph.crs, [x], [y])[0]
        fixes.append(
            Fix(
                time=i * dt,
                lat=float(lat),
                lon=float(lon),
                heading=(hd + hd_err[i]) % 360.0,
                pos_sigma=math.nan if lost else sigma,
                speed=speed,
                distance=step,
                gps_valid=not lost,
            )
        )
    return Drive(fixes, s)


def _xy(amap: AsciiMap, f: Fix) -> tuple[float, float]:
    from graph.projection import point_to_xy

    return point_to_xy(amap.graph.crs, f.lon, f.lat)


def runs(edges: list[int]) -> list[int]:
    """The edges in order, repeats and -1 (no road) dropped."""
    out: list[int] = []
    for e in edges:
        if e >= 0 and (not out or out[-1] != e):
            out.append(e)
    return out


def settled_after(edges: list[int], s: NDArray[np.float64], want: int, *, since: float) -> float:
    """How far past ``since`` (m along the route) the answers stay on ``want`` to the end:
    the distance of the first fix of the final run of ``want`` (inf when the last answer is
    another edge)."""
    if not edges or edges[-1] != want:
        return math.inf
    k = len(edges)
    while k > 0 and edges[k - 1] == want:
        k -= 1
    return max(float(s[k]) - since, 0.0)
