"""Tiny road maps drawn as ASCII art, for tests and examples (in the manner of Valhalla's tests).

Letters and digits are intersections; roads are drawn with ``-`` and ``|`` (two-way), ``/``
and ``\\`` (diagonal, two-way), and ``>``, ``<``, ``v``, ``^`` for one-way pieces in the arrow's
direction. One character is ``scale`` metres across and ``2 * scale`` metres down, so drawings
look proportional in a monospace font::

    a---b---c
        |
        d

The map is placed in UTM zone 35N near Helsinki, at ``origin`` (metres), north up.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graph.errors import InputError
from graph.projection import to_lonlat
from graph.road_graph import RESTRICTION_NO, RESTRICTION_ONLY, Edges, Nodes, RoadGraph

ASCII_CRS = "EPSG:32635"
ASCII_ORIGIN = (385_000.0, 6_672_000.0)

_STEPS = {  # direction (drow, dcol) -> (road chars, chars one-way along it, chars one-way against it)
    (0, 1): ("-><", ">", "<"),
    (0, -1): ("-><", "<", ">"),
    (1, 0): ("|v^", "v", "^"),
    (-1, 0): ("|v^", "^", "v"),
    (1, 1): ("\\", "", ""),
    (-1, -1): ("\\", "", ""),
    (1, -1): ("/", "", ""),
    (-1, 1): ("/", "", ""),
}


@dataclass(frozen=True)
class AsciiMap:
    """A graph drawn as ASCII art, with lookups by the letters used in the drawing."""

    graph: RoadGraph
    nodes: dict[str, int]
    scale: float

    def edge(self, a: str, b: str) -> int:
        """The directed edge from intersection ``a`` to ``b``."""
        u, v = self.nodes[a], self.nodes[b]
        for e in self.graph.out_of(u):
            if self.graph.edge_v[e] == v:
                return int(e)
        raise KeyError(f"no edge {a}->{b}")

    def xy(self, name: str) -> NDArray[np.float64]:
        """Position in metres of intersection ``name``."""
        return np.asarray(self.graph.node_xy[self.nodes[name]], dtype=np.float64)

    def lonlat(self, x: float, y: float) -> tuple[float, float]:
        """WGS84 ``(lon, lat)`` of a point in metres."""
        ll = to_lonlat(self.graph.crs, [x], [y])[0]
        return float(ll[0]), float(ll[1])


def parse_ascii_map(
    drawing: str,
    *,
    scale: float = 10.0,
    origin: tuple[float, float] = ASCII_ORIGIN,
    restrictions: Iterable[tuple[str, str, str, str]] = (),
) -> AsciiMap:
    """Parse an ASCII drawing into a :class:`RoadGraph`.

    Parameters
    ----------
    drawing
        The map. Leading and trailing blank lines and common indentation are ignored.
    scale
        Metres per character across (``2 * scale`` per line down).
    origin
        Position in metres of the top-left character.
    restrictions
        Turn restrictions as ``(from_node, via_node, to_node, kind)`` with kind ``"no"`` or
        ``"only"``, e.g. ``("a", "b", "c", "no")`` forbids a->b->c.
    """
    grid = _grid(drawing)
    nodes: dict[str, int] = {}
    pos: list[tuple[float, float]] = []
    cells: dict[tuple[int, int], str] = {}
    for r, row in enumerate(grid):
        for c, ch in enumerate(row):
            if ch.isalnum() and ch not in "v":
                if ch in nodes:
                    raise InputError(f"intersection {ch!r} drawn twice")
                nodes[ch] = len(pos)
                pos.append((origin[0] + c * scale, origin[1] - r * 2 * scale))
                cells[(r, c)] = ch
    us, vs = _roads(grid, cells, nodes)
    xy = np.array(pos, dtype=np.float64).reshape(-1, 2)
    ll = to_lonlat(ASCII_CRS, xy[:, 0], xy[:, 1]) if len(xy) else np.empty((0, 2))
    ids = np.array([ord(n) for n in nodes], dtype=np.int64)
    nodes_in = Nodes(xy, ll, ids)
    edges_in = Edges(us, vs, way_id=np.arange(1, len(us) + 1, dtype=np.int64))
    amap = AsciiMap(graph=RoadGraph.from_edges(ASCII_CRS, nodes_in, edges_in), nodes=nodes, scale=scale)
    rows = []
    for src, via, dst, kind in restrictions:
        k = {"no": RESTRICTION_NO, "only": RESTRICTION_ONLY}[kind]
        rows.append((amap.edge(src, via), nodes[via], amap.edge(via, dst), k))
    if rows:
        g = RoadGraph.from_edges(ASCII_CRS, nodes_in, edges_in, restrictions=rows)
        amap = AsciiMap(graph=g, nodes=nodes, scale=scale)
    return amap


def _grid(drawing: str) -> list[str]:
    """The drawing's lines without leading and trailing blank lines and common indentation."""
    lines = [ln.rstrip() for ln in drawing.splitlines()]
    while lines and not lines[0].strip():
        lines.pop(0)
    while lines and not lines[-1].strip():
        lines.pop()
    indent = min((len(ln) - len(ln.lstrip()) for ln in lines if ln.strip()), default=0)
    return [ln[indent:] for ln in lines]


def _roads(
    grid: list[str], cells: dict[tuple[int, int], str], nodes: dict[str, int]
) -> tuple[list[int], list[int]]:
    """The directed edges drawn between the intersections (``cells``: their places in ``grid``)."""

    def at(r: int, c: int) -> str:
        if 0 <= r < len(grid) and 0 <= c < len(grid[r]):
            return grid[r][c]
        return " "

    us: list[int] = []
    vs: list[int] = []
    seen: set[tuple[int, int, int, int]] = set()
    for (r, c), name in cells.items():
        for (dr, dc), (road, fwd, bwd) in _STEPS.items():
            rr, cc = r + dr, c + dc
            if at(rr, cc) not in road:
                continue
            forward_ok, backward_ok = True, True
            while at(rr, cc) in road:
                ch = at(rr, cc)
                if ch in bwd:
                    forward_ok = False
                if ch in fwd:
                    backward_ok = False
                rr, cc = rr + dr, cc + dc
            other = cells.get((rr, cc))
            if other is None:
                raise InputError(f"road leaving {name!r} ends nowhere at line {rr + 1}, column {cc + 1}")
            key = (min(r, rr), min(c, cc), max(r, rr), max(c, cc))
            if key in seen:
                continue
            seen.add(key)
            a, b = nodes[name], nodes[other]
            if forward_ok:
                us.append(a)
                vs.append(b)
            if backward_ok:
                us.append(b)
                vs.append(a)
    return us, vs
