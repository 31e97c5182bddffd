"""The position along a path: on a straight road the map cannot show the fix's along-track
error, so the projection is corrected by the learnt fix bias and fused with the turn anchor
carried on by the odometer."""

from __future__ import annotations

import math

from mapmatch.config import MatchConfig
from mapmatch.online.road import RoadModel
from mapmatch.online.state import Hypothesis, PathPos, Step


def along_track(
    road: RoadModel, h: Hypothesis, step: Step, best: PathPos, acc: float, cfg: MatchConfig
) -> tuple[PathPos, float]:
    """Correct the position along ``h``'s path: the fix's projection ``best`` less its learnt
    along-track bias, fused with the turn anchor (on a straight road the map cannot tell the
    fix's along-track error). ``acc`` is the furthest ``s`` allowed. Returns the corrected
    position (``best`` itself when unchanged) and a log-penalty when the path's turn stops the
    position short of the estimate."""
    bx, by, pxx, pxy, pyy = step.bias
    rad = math.radians(best.bearing)
    tx, ty = math.sin(rad), math.cos(rad)
    s_f = s_m = best.s - (bx * tx + by * ty)
    va = 0.0
    white = cfg.online.bias_white_fraction * step.sigma
    vf = tx * tx * pxx + 2.0 * tx * ty * pxy + ty * ty * pyy + white**2
    if not math.isnan(h.anc_sd) and step.odo_known:
        va = h.anc_sd * h.anc_sd
        innov = h.anc + step.odo - s_m
        if innov * innov > cfg.online.anchor_gate**2 * (va + vf):
            h.anc = h.anc_sd = math.nan  # inconsistent: forget it
        else:
            s_f = s_m + innov * vf / (va + vf)
    if abs(s_f - best.s) <= 0.01:
        return best, 0.0
    s_f = min(max(s_f, 0.0), acc)
    want, miss = s_f, 0.0
    j, start, s_f = _stop_at_turns(road, h, best, s_f, cfg)
    if s_f != want:  # the along-track estimate is past a turn this path has not taken yet
        miss = 0.5 * (want - s_f) ** 2 * (1.0 / vf + (1.0 / va if va > 0.0 else 0.0))
    rest = min(max(s_f - start, 0.0), road.elen[h.edges[j]])
    px, py, brg = road.locate(h.edges[j], rest)
    return PathPos(j, rest, s_f, math.hypot(px - step.x, py - step.y), px, py, brg), miss


def _stop_at_turns(
    road: RoadModel, h: Hypothesis, best: PathPos, s_f: float, cfg: MatchConfig
) -> tuple[int, float, float]:
    """Move from ``best`` towards ``s_f`` across nodes only where the path goes straight on (at a
    turn the fix shows it): the edge index reached, its start along the path and the ``s``."""
    j, start = best.j, best.s - best.off
    while s_f > start + road.elen[h.edges[j]] and j < len(h.edges) - 1:
        if not road.straight(h.edges[j], h.edges[j + 1], cfg):
            s_f = start + road.elen[h.edges[j]]
            break
        start += road.elen[h.edges[j]]
        j += 1
    while s_f < start and j > 0:
        if not road.straight(h.edges[j - 1], h.edges[j], cfg):
            s_f = start
            break
        j -= 1
        start -= road.elen[h.edges[j]]
    return j, start, s_f
