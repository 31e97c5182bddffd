"""Corrections: the fixed-lag smoother over the ambiguous region's fixes, compared with what was
reported live, and the corrections' timelines (runs, merges)."""

from __future__ import annotations

import math

from mapmatch.config import MatchConfig
from mapmatch.online.road import RoadModel
from mapmatch.online.state import Hypothesis, LiveFix, RegionState, Step
from mapmatch.types import Correction


def remember_live(rg: RegionState, edge: int, step: Step, cfg: MatchConfig) -> None:
    """Keep this fix of the ambiguous region (what a correction may revise): the first
    ``max_live`` fixes of the region."""
    if not rg.live or len(rg.live) < cfg.online.corrections.max_live:
        rg.live.append(
            LiveFix(step.time, edge, step.x, step.y, step.heading, step.sigma, step.kappa, step.gps)
        )


def correction(road: RoadModel, rg: RegionState, best: Hypothesis, cfg: MatchConfig) -> Correction | None:
    """Compare what was reported live with the committed path's timeline (the live fixes
    revised to it)."""
    # fixes from before the committed path began cannot be judged by it: they stay as reported
    rg.live = [x for x in rg.live if x.time >= best.enter[0]]
    if not rg.live:
        return None
    mism: list[tuple[float, int, int]] = []
    assigned, cost = smooth(road, rg.live, best)
    path = best.edges[: best.k + 1]
    for entry, j, row in zip(rg.live, assigned, cost, strict=True):
        t, rep = entry.time, entry.edge
        now = best.edges[j]
        if now != rep and rep in path and (not entry.gps or row[path.index(rep)] < row[j]):
            # dead reckoning, or likelier where it was reported on the committed path: keep it
            continue
        if now != rep:
            mism.append((t, now, rep))
            entry.edge = now
    if not mism:
        return None
    edges, times = runs([(m[0], m[1]) for m in mism])
    return Correction(
        time_from=mism[0][0],
        time_to=mism[-1][0],
        edges=edges,
        replaced_edges=dedup([m[2] for m in mism]),
        edge_times=times,
    )


def smooth(road: RoadModel, live: list[LiveFix], best: Hypothesis) -> tuple[list[int], list[list[float]]]:
    """Fixed-lag smoothing: the most likely monotone assignment of the region's fixes to
    the committed path's edges ``edges[0..k]`` (a small Viterbi). Returns it and the costs."""
    n_j = best.k + 1
    cost: list[list[float]] = []
    for f in live:
        row = []
        for j in range(n_j):
            _, dist, _, _, brg = road.project(best.edges[j], f.x, f.y)
            row.append(-road.emission(dist, f.sigma, f.heading, brg, f.kappa))
        cost.append(row)
    acc = cost[0][:]
    back: list[list[int]] = []
    for i in range(1, len(cost)):
        run_min, run_arg = math.inf, 0
        new, arg = [], []
        for j in range(n_j):
            if acc[j] < run_min:
                run_min, run_arg = acc[j], j
            new.append(cost[i][j] + run_min)
            arg.append(run_arg)
        acc = new
        back.append(arg)
    j = min(range(n_j), key=lambda q: acc[q])
    out = [j]
    for arg in reversed(back):
        j = arg[j]
        out.append(j)
    return out[::-1], cost


def dedup(seq: list[int]) -> tuple[int, ...]:
    """``seq`` without repeats in a row."""
    out: list[int] = []
    for e in seq:
        if not out or out[-1] != e:
            out.append(e)
    return tuple(out)


def runs(timeline: list[tuple[float, int]]) -> tuple[tuple[int, ...], tuple[float, ...]]:
    """``(time, edge)`` pairs in time order as runs: each edge once per run, with its start."""
    edges: list[int] = []
    times: list[float] = []
    for t, e in timeline:
        if not edges or edges[-1] != e:
            edges.append(e)
            times.append(t)
    return tuple(edges), tuple(times)


def merge(a: Correction, b: Correction | None) -> Correction:
    """One correction for both. The merged timeline is exact only when the two spans touch:
    across a gap it would revise fixes neither one revised, so then it carries no times."""
    if b is None:
        return a
    timed = len(a.edge_times) == len(a.edges) and len(b.edge_times) == len(b.edges)
    if timed and a.time_from <= b.time_to and b.time_from <= a.time_to:
        edges, times = runs(
            sorted([*zip(a.edge_times, a.edges, strict=True), *zip(b.edge_times, b.edges, strict=True)])
        )
    else:
        first, second = (a, b) if a.time_from <= b.time_from else (b, a)
        edges, times = dedup([*first.edges, *second.edges]), ()
    return Correction(
        time_from=min(a.time_from, b.time_from),
        time_to=max(a.time_to, b.time_to),
        edges=edges,
        replaced_edges=dedup([*a.replaced_edges, *b.replaced_edges]),
        edge_times=times,
    )
