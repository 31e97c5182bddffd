"""The road model the online filter scores against: one map's geometry, its legal moves and the
scorers (emission, transition, turn) a generic filter step takes from it.

All plain-float code for the per-fix hot path; the arrays come from the prepared map.
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right

import numpy as np
from numpy.typing import NDArray

from graph.angles import angle_diff, bearing, bearings
from graph.index import project_point_compiled
from graph.jit import read_only
from graph.road_graph import RoadGraph
from graph.rules import junctions, legal_moves
from mapmatch.config import MatchConfig
from mapmatch.model import emission_one, transition_one
from mapmatch.online.geometry import RoadArrays, locate_on
from mapmatch.online.state import Hypothesis, Step

Projection = tuple[float, float, float, float, float]  # offset, dist, px, py, bearing


def _piece_table(seg_xy: NDArray[np.float64], ptr: list[int]) -> tuple[list[float], list[float], list[float]]:
    """Per polyline vertex row ``q`` (the piece from ``q - 1`` to ``q`` of its edge): the
    distance from the edge's start to its end, its length and its bearing, each computed as
    the compiled :func:`~mapmatch.online.geometry.locate_on` computes them (the C library's
    ``hypot``, as numpy's; sums in order), so that a look-up in the table gives its answers."""
    d = np.diff(seg_xy, axis=0, prepend=seg_xy[:1]) if len(seg_xy) else np.zeros((0, 2))
    seg_len: list[float] = np.hypot(d[:, 0], d[:, 1]).tolist()
    dx, dy = d[:, 0].tolist(), d[:, 1].tolist()
    cum = [0.0] * len(seg_len)
    brg = [0.0] * len(seg_len)
    for e in range(len(ptr) - 1):
        acc = 0.0
        for q in range(ptr[e] + 1, ptr[e + 1]):
            cum[q] = acc + seg_len[q]
            brg[q] = bearing(dx[q], dy[q])
            acc += seg_len[q]
    return cum, seg_len, brg


class RoadModel:
    """Per-map arrays as Python lists, and the geometry and scores built on them."""

    def __init__(self, graph: RoadGraph) -> None:
        self.graph = graph
        self.elen: list[float] = graph.edge_len.tolist()
        self.ev: list[int] = graph.edge_v.tolist()
        self.eu: list[int] = graph.edge_u.tolist()
        self.rev: list[int] = graph.edge_reverse.tolist()
        self.bstart: list[float] = graph.edge_bearing_start.tolist()
        self.bend: list[float] = graph.edge_bearing_end.tolist()
        self.ptr: list[int] = graph.edge_seg_ptr.tolist()
        self.seg = read_only(graph.seg_xy, np.float64)
        # the same, as arrays for the compiled kernels
        # every vertex's distance along its edge
        piece = np.hypot(*np.diff(graph.seg_xy, axis=0).T) if len(graph.seg_xy) else np.zeros(0)
        vcum = np.zeros(len(graph.seg_xy))
        for e in range(graph.n_edges):
            lo, hi = int(graph.edge_seg_ptr[e]), int(graph.edge_seg_ptr[e + 1])
            if hi - lo > 1:
                vcum[lo + 1 : hi] = np.cumsum(piece[lo : hi - 1])
        self.arrays = RoadArrays(  # read-only whatever the map's source: one compile (``read_only``)
            seg=self.seg,
            ptr=read_only(graph.edge_seg_ptr, np.int64),
            elen=read_only(graph.edge_len, np.float64),
            bstart=read_only(graph.edge_bearing_start, np.float64),
            bend=read_only(graph.edge_bearing_end, np.float64),
            vcum=read_only(vcum, np.float64),
        )
        self.arrays_tuple = tuple(self.arrays)  # as a plain tuple: how the kernels take it
        self._cum, self._seg_len, self._brg = _piece_table(self.seg, self.ptr)
        # every piece of every polyline: length and bearing (the last row of each edge is unused)
        d = np.diff(graph.seg_xy, axis=0) if len(graph.seg_xy) else np.zeros((0, 2))
        self.piece_len = np.hypot(d[:, 0], d[:, 1])
        self.piece_brg = bearings(d[:, 0], d[:, 1])
        # what the report reads per fix, as Python values: node ids and the way pieces
        ids = graph.node_id
        self.u_id: list[int] = ids[graph.edge_u].tolist()
        self.v_id: list[int] = ids[graph.edge_v].tolist()
        self._pptr: list[int] = graph.piece_ptr.tolist()
        self._pstart: list[float] = graph.piece_start.tolist()
        names, classes = graph.names, graph.highways
        self._pfields: list[tuple[int, str, str, float]] = [  # as RoadGraph.piece_fields
            (w, names[n] if n >= 0 else "", classes[c] if c >= 0 else "", v if v == v else 0.0)
            for w, n, c, v in zip(
                graph.piece_way_id.tolist(),
                graph.piece_name_idx.tolist(),
                graph.piece_highway_idx.tolist(),
                graph.piece_speed_kph.astype(np.float64).tolist(),
                strict=True,
            )
        ]
        self.branching: list[bool] = junctions(graph).tolist()
        moves = legal_moves(graph, uturns="junction")
        self._mptr: list[int] = moves.ptr.tolist()
        self._mto: list[int] = moves.to.tolist()
        self._muturn: list[bool] = moves.uturn.tolist()
        # a robust "longest distance between adjacent nodes" for the region radius
        self.edge_len_ref = float(np.percentile(graph.edge_len, 95)) if graph.n_edges else 0.0
        self.bounds = (
            (
                float(graph.seg_xy[:, 0].min()),
                float(graph.seg_xy[:, 1].min()),
                float(graph.seg_xy[:, 0].max()),
                float(graph.seg_xy[:, 1].max()),
            )
            if len(graph.seg_xy)
            else None
        )

    # ------------------------------------------------------------------ geometry
    def project(self, e: int, x: float, y: float) -> Projection:
        """``(offset, dist, px, py, bearing)`` of the point's projection onto edge ``e``."""
        return project_point_compiled(  # type: ignore[no-any-return]
            self.seg, self.ptr[e], self.ptr[e + 1], x, y, self.elen[e], self.bstart[e]
        )

    def locate(self, e: int, off: float) -> tuple[float, float, float]:
        """``(x, y, bearing)`` at ``off`` metres along edge ``e``."""
        return locate_on(self.seg, self.ptr[e], self.ptr[e + 1], off, self.bend[e])  # type: ignore[no-any-return]

    def piece(self, e: int, off: float) -> tuple[int, str, str, float]:
        """Way id, name, road class and speed of the way piece under ``(e, off)`` (as
        :meth:`RoadGraph.piece_fields` of :meth:`RoadGraph.piece_index`)."""
        lo, hi = self._pptr[e], self._pptr[e + 1]
        i = lo if hi - lo <= 1 else bisect_right(self._pstart, off, lo + 1, hi) - 1
        return self._pfields[i]

    def bearing_at(self, e: int, off: float) -> float:
        """The bearing at ``off`` metres along edge ``e`` (``locate(e, off)[2]``, looked up)."""
        lo, hi = self.ptr[e] + 1, self.ptr[e + 1]
        if off != off:
            return self.bend[e]
        q = bisect_left(self._cum, off, lo, hi)  # the first piece ending at or past ``off`` ...
        seg = self._seg_len
        while q < hi and seg[q] <= 0.0:  # ... of some length
            q += 1
        return self._brg[q] if q < hi else self.bend[e]

    def straight(self, e: int, e2: int, cfg: MatchConfig) -> bool:
        """Whether ``e2`` continues ``e`` straight on at their shared node."""
        return abs(angle_diff(self.bstart[e2], self.bend[e])) <= cfg.model.straight_max_deg

    def bearing_on_path(self, h: Hypothesis, s: float) -> float:
        """The road's bearing ``s`` metres along ``h``'s path."""
        if s <= 0.0:
            return self.bstart[h.edges[0]]
        acc = 0.0
        for e in h.edges:
            if s <= acc + self.elen[e]:
                return self.locate(e, s - acc)[2]
            acc += self.elen[e]
        return self.bend[h.edges[-1]]

    def far_off(self, x: float, y: float, cfg: MatchConfig) -> bool:
        """Whether the point is further than ``far_off`` from the map's bounds."""
        b = self.bounds
        if b is None:
            return True
        if b[0] <= x <= b[2] and b[1] <= y <= b[3]:
            return False  # inside (the common case): distance 0, never over far_off (≥ 0)
        dx = max(b[0] - x, 0.0, x - b[2])
        dy = max(b[1] - y, 0.0, y - b[3])
        return math.hypot(dx, dy) > cfg.online.reinit.far_off

    # ------------------------------------------------------------------ road rules
    def children(self, e: int, cfg: MatchConfig) -> list[tuple[int, float]]:
        """Legal continuations of edge ``e`` at its end node, with log-penalties."""
        lo, hi = self._mptr[e], self._mptr[e + 1]
        pen = -cfg.model.uturn_penalty
        return [(self._mto[i], pen if self._muturn[i] else 0.0) for i in range(lo, hi)]

    # ------------------------------------------------------------------ scorers
    # log-likelihood of a fix ``dist`` from the road, heading against its bearing
    emission = staticmethod(emission_one)

    @staticmethod
    def transition(route_dist: float, step: Step, cfg: MatchConfig) -> float:
        """Log-probability of ``route_dist`` metres along the path for this step's travel (no
        speed term: the odometer gives the travel)."""
        m = cfg.model
        return transition_one(route_dist, step.travelled, 0.0, m.beta, m.beta_per_m, 0.0, 0.0)
