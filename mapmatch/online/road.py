"""The road model the online filter scores against: one map's geometry, its legal moves and the
scorers (emission, transition, turn) a generic filter step takes from it.

All plain-float code for the per-fix hot path; the arrays come from the prepared map.
"""

from __future__ import annotations

import bisect
import math

import numpy as np
from numba import njit

from mapmatch.config import MatchConfig
from mapmatch.graph.index import project_point_compiled
from mapmatch.graph.road_graph import RoadGraph
from mapmatch.graph.rules import junctions, legal_moves
from mapmatch.model import emission_one, transition_one
from mapmatch.online.state import Hypothesis, Step
from mapmatch.turns import angle_diff

Projection = tuple[float, float, float, float, float]  # offset, dist, px, py, bearing


@njit(cache=True)
def _locate(seg_xy, lo, hi, off, bearing_end):  # type: ignore[no-untyped-def]
    """``(x, y, bearing)`` at ``off`` metres along the polyline ``seg_xy[lo:hi]``."""
    acc = 0.0
    ax, ay = seg_xy[lo, 0], seg_xy[lo, 1]
    for q in range(lo + 1, hi):
        bx, by = seg_xy[q, 0], seg_xy[q, 1]
        dx, dy = bx - ax, by - ay
        seg = math.hypot(dx, dy)
        if acc + seg >= off and seg > 0.0:
            t = (off - acc) / seg
            return ax + t * dx, ay + t * dy, math.degrees(math.atan2(dx, dy)) % 360.0
        acc += seg
        ax, ay = bx, by
    return ax, ay, bearing_end


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
        self.seg = np.ascontiguousarray(graph.seg_xy, dtype=np.float64)
        # every piece of every polyline: length and bearing (the last row of each edge is unused)
        d = np.diff(graph.seg_xy, axis=0) if len(graph.seg_xy) else np.zeros((0, 2))
        self.piece_len = np.hypot(d[:, 0], d[:, 1])
        self.piece_brg = np.degrees(np.arctan2(d[:, 0], d[:, 1])) % 360.0
        # every vertex's distance along its edge
        vcum = np.zeros(len(graph.seg_xy))
        ptr = graph.edge_seg_ptr
        for e in range(graph.n_edges):
            lo, hi = int(ptr[e]), int(ptr[e + 1])
            if hi - lo > 1:
                vcum[lo + 1 : hi] = np.cumsum(self.piece_len[lo : hi - 1])
        self.vcum: list[float] = vcum.tolist()
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

    def project_between(self, e: int, x: float, y: float, lo: float, hi: float) -> Projection | None:
        """The point's nearest point on edge ``e`` between ``lo`` and ``hi`` metres along it, when
        that is a foot of its own inside the stretch (not the stretch's end); else None."""
        lo, hi = max(lo, 0.0), min(hi, self.elen[e])
        if hi <= lo:
            return None
        a, b = self.ptr[e], self.ptr[e + 1]
        q0 = max(bisect.bisect_right(self.vcum, lo, a, b) - 1, a)
        q1 = min(bisect.bisect_left(self.vcum, hi, a, b) + 1, b)
        if q1 - q0 < 2:
            return None
        off, dist, px, py, brg = project_point_compiled(self.seg, q0, q1, x, y, math.inf, self.bstart[e])
        off += self.vcum[q0]
        if not lo < off < hi:
            return None
        return off, dist, px, py, brg

    def locate(self, e: int, off: float) -> tuple[float, float, float]:
        """``(x, y, bearing)`` at ``off`` metres along edge ``e``."""
        return _locate(self.seg, self.ptr[e], self.ptr[e + 1], off, self.bend[e])  # type: ignore[no-any-return]

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
        dx = max(b[0] - x, 0.0, x - b[2])
        dy = max(b[1] - y, 0.0, y - b[3])
        return math.hypot(dx, dy) > cfg.online.far_off

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
        """Log-probability of ``route_dist`` metres along the path for this step's travel (its
        speed judged over at least ``speed_time``, whatever the fix rate)."""
        m = cfg.model
        dt = max(step.dt, cfg.online.speed_time)
        return transition_one(route_dist, step.travelled, dt, m.beta, m.max_speed, m.speed_penalty)

    def turn(self, h: Hypothesis, s_prev: float, turn_obs: float, covered: float, cfg: MatchConfig) -> float:
        """Log-score of the heading change observed over the last ``covered`` metres against the
        bearing change ``h``'s path has there (0 when too little was covered)."""
        if covered >= 0.5 * cfg.online.turn_window and not math.isnan(turn_obs):
            expect = angle_diff(h.bearing, self.bearing_on_path(h, h.s - covered))
            miss = angle_diff(turn_obs, expect) / cfg.online.turn_sigma
            frac = min(1.0, max(h.s - s_prev, 0.0) / cfg.online.turn_window)
            return -(0.5 * miss * miss * frac)
        return 0.0
