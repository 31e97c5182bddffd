"""Exact Viterbi over the lattice, routing each step as it goes (compiled).

Each step is :mod:`mapmatch.batch.step`'s; which fixes to leave out is
:mod:`mapmatch.batch.leave_out`'s. A point no candidate of the previous point can reach is left
out; a run of them splits the match.
"""

from __future__ import annotations

import math

import numpy as np

from graph.jit import njit
from mapmatch.arena import UNCOUNTED, full_b1, full_f8, full_i8, int64, take_b1, take_f8, take_i8
from mapmatch.batch.arrays import KernelParams, Lattice
from mapmatch.batch.leave_out import (
    Detour,
    Saved,
    _best,
    _drop_one,
    _leave_out_prev,
    _leave_out_visited,
    _track_end,
    _track_start,
)
from mapmatch.batch.step import Trellis, _far_gap, _left_the_route, _try_step, step_inputs


@njit(cache=True, nogil=True)
def _piece_end(a, b, tr, lat, g):  # type: ignore[no-untyped-def]
    """The candidate a piece ends on, of its last point's ``a:b``: the best, unless it was reached
    by driving on to its place and turning round there, and the candidate at that place facing
    the way driven explains the fix as well (no heading says the vehicle turned): then that
    one. A turn of no length at a piece's end tells nothing; it can only tie with driving on,
    where the U-turn costs nothing (``uturn_penalty`` 0), else the best is driving on already."""
    score = tr.score
    j = a + np.argmax(score[a:b])
    i = tr.bp[j]
    if not tr.bpu[j] or i < 0:
        return j
    e = lat.edge[i]
    if g.edge_len[e] - lat.offset[j] < lat.offset[i]:
        return j  # turned round at the previous fix's place and drove back: a U-turn of length
    for k in range(a, b):
        if lat.edge[k] == e and score[k] > -np.inf and lat.emis[k] >= lat.emis[j]:
            return k
    return j


@njit(cache=True, nogil=True)
def solve(lat: Lattice, p: KernelParams, router, ar, sig):  # type: ignore[no-untyped-def]
    """Exact Viterbi over the lattice, routing each step as it goes.

    A point no candidate of the previous accepted point can reach is left out (an outlier);
    after ``max_skip`` such points in a row, or across a jump (:func:`_far_gap`), a new piece starts at
    the first of them. The track's first and last points are left out where visiting them costs
    more than leaving them out (:func:`_emission_cost` plus :func:`_detour_cost`; ``sig``: each
    lattice point's σ). Returns
    per lattice point the chosen candidate (-1 = left out), whether a piece starts there,
    whether the step into it is an along-road U-turn, and its route bound.
    """
    cand_ptr = lat.ptr
    max_skip = p.max_skip
    m = len(cand_ptr) - 1
    nc = len(lat.emis)
    prev_pt = full_i8(ar, m, -1)
    accepted = full_b1(ar, m, False)
    seg_start = full_b1(ar, m, False)
    used_bound = full_f8(ar, m, 0.0)
    choice = full_i8(ar, m, -1)
    via_u = full_b1(ar, m, False)
    if m == 0:
        return choice, seg_start, via_u, used_bound
    kmax = 1
    for t in range(m):
        kmax = max(kmax, cand_ptr[t + 1] - cand_ptr[t])
    tr = Trellis(
        full_f8(ar, nc, -np.inf),
        full_i8(ar, nc, -1),
        full_b1(ar, nc, False),
        take_i8(ar, kmax),
        take_f8(ar, kmax),
    )
    bp = tr.bp
    bpu = tr.bpu
    saved = Saved(take_f8(ar, kmax), take_i8(ar, kmax), take_b1(ar, kmax), take_f8(ar, 2))
    detour = Detour(
        take_i8(ar, max_skip + 1),
        take_i8(ar, max_skip + 1),
        take_f8(ar, max_skip + 1),
        take_f8(ar, max_skip + 1),
    )
    _forward(lat, p, router, tr, saved, detour, prev_pt, accepted, seg_start, used_bound)
    # backtrack, each piece from its last point; the track's own ends may be left out (a
    # split's, beside a jump or a gap, are not: there the fixes are already in doubt)
    t = m - 1
    while not accepted[t]:
        t -= 1
    if p.outlier_lookahead:
        t = _track_end(t, tr, lat, p, router, sig, prev_pt, seg_start, used_bound)
    last = t
    j = _piece_end(cand_ptr[t], cand_ptr[t + 1], tr, lat, router.g)
    later = -1  # the point after ``t`` in its piece
    while True:
        choice[t] = j
        if seg_start[t]:
            q = t - 1
            while q >= 0 and not accepted[q]:
                q -= 1
            # a piece of one point at the track's start or end, beside another piece: one
            # fix makes no route (a fix near some road before or after a run off the route)
            if p.outlier_lookahead and later < 0 and (q < 0) != (t == last):
                choice[t] = -1
                seg_start[t] = False
            if q < 0:
                break
            t = q
            j = _piece_end(cand_ptr[t], cand_ptr[t + 1], tr, lat, router.g)
            later = -1
        else:
            via_u[t] = bpu[j]
            later = t
            j = bp[j]
            t = prev_pt[t]
    if p.outlier_lookahead:
        _track_start(choice, seg_start, via_u, used_bound, tr, lat, p, router, sig)
    return choice, seg_start, via_u, used_bound


@njit(**UNCOUNTED)
def _forward(lat, p, router, tr, saved, detour, prev_pt, accepted, seg_start, used_bound):  # type: ignore[no-untyped-def]
    """:func:`solve`'s forward pass: every step scored, its points accepted or left out, and the
    pieces started, into ``prev_pt``, ``accepted``, ``seg_start`` and ``used_bound``.

    Compiled without reference counting (:data:`~mapmatch.arena.UNCOUNTED`), apart from
    :func:`solve`, which allocates: the inlined :func:`~mapmatch.batch.step._try_step` copies
    every tuple it is handed, and with reference counting each copy would cost a call per
    array, over a hundred a step."""
    inputs = step_inputs(lat, tr, p, router)
    cand_ptr = lat.ptr
    emis = lat.emis
    pxy = lat.pxy
    gap_time = p.gap_time if p.gap_time > 0 else np.inf
    ptime = lat.ptime
    max_skip = p.max_skip
    m = len(cand_ptr) - 1
    score = tr.score
    prev = int64(0)  # not 0: one compile of each kernel it is handed to (``mapmatch.arena.int64``)
    accepted[0] = True
    seg_start[0] = True
    for j in range(cand_ptr[0], cand_ptr[1]):
        score[j] = emis[j]
    nskip = 0
    s0 = int64(-1)
    t = int64(1)
    d = 0.0
    while t < m or nskip > 1:
        restart = -1
        if t >= m:
            restart = s0  # several trailing points unreachable: they form their own piece
        else:
            d = math.hypot(pxy[t, 0] - pxy[prev, 0], pxy[t, 1] - pxy[prev, 1])
            dt = ptime[t] - ptime[prev]
            if _far_gap(d, dt, p, 1) or _left_the_route(prev, t, lat, p) or dt > gap_time:
                restart = s0 if nskip > 0 else t
        if restart < 0:
            reached, bound = _try_step(prev, t, d, lat, p, inputs)
            if reached:
                accepted[t] = True
                prev_pt[t] = prev
                used_bound[t] = bound
                # maybe ``prev`` was the outlier, not the points after it
                if (
                    nskip > 1
                    and p.outlier_lookahead
                    and not seg_start[prev]
                    and _leave_out_prev(prev_pt[prev], s0, t, lat, tr, p, router, saved, detour)
                ):
                    accepted[prev] = False
                    r = t
                    while r >= s0:
                        accepted[r] = True
                        prev_pt[r] = detour.pred[r - s0]
                        used_bound[r] = detour.bound[r - s0]
                        r = prev_pt[r]
                elif (
                    nskip == 0
                    and p.outlier_lookahead
                    and not seg_start[prev]
                    # the step past ``prev`` scores at most its start plus ``t``'s best emission
                    and _best(score, cand_ptr[t], cand_ptr[t + 1])
                    < _best(score, cand_ptr[prev_pt[prev]], cand_ptr[prev_pt[prev] + 1])
                    + _best(emis, cand_ptr[t], cand_ptr[t + 1])
                    - 2.0 * p.leave_out_cost
                    and _leave_out_visited(prev_pt[prev], prev, t, lat, tr, p, router, saved)
                ):
                    # visiting ``prev`` cost clearly more than leaving it out: a stray the route bent to
                    accepted[prev] = False
                    prev_pt[t] = prev_pt[prev]
                    used_bound[t] = saved.bound[0]
                prev = t
                nskip = 0
                t += 1
                continue
            if nskip == 0 and p.outlier_lookahead and t + 1 < m:
                q = -1 if seg_start[prev] else prev_pt[prev]
                kept = _drop_one(q, prev, t, lat, tr, p, router, saved)
                if kept >= 0:  # one of prev, t left out; t + 1 reached
                    if kept == t:
                        accepted[prev] = False
                        accepted[t] = True
                        prev_pt[t] = q
                        used_bound[t] = saved.bound[0]
                        if seg_start[prev]:
                            seg_start[prev] = False
                            seg_start[t] = True
                        prev_pt[t + 1] = t
                    else:
                        prev_pt[t + 1] = prev
                    accepted[t + 1] = True
                    used_bound[t + 1] = saved.bound[1]
                    prev = t + 1
                    nskip = 0
                    t += 2
                    continue
            if nskip == 0:
                s0 = t
            nskip += 1
            if nskip <= max_skip:
                t += 1
                continue
            restart = s0
        if nskip > 0 and restart == s0:
            # before splitting: maybe the last accepted points were the outliers (a drift onto a
            # road that does not lead on); reach s0 from up to max_skip points before them
            q = prev_pt[prev]
            back = 0
            while q >= 0 and back < max_skip:
                dq = math.hypot(pxy[s0, 0] - pxy[q, 0], pxy[s0, 1] - pxy[q, 1])
                if _far_gap(dq, ptime[s0] - ptime[q], p, back + 2) or _left_the_route(q, s0, lat, p):
                    break  # a jump even spread over its steps, or a run off the route
                reached, bound = _try_step(q, s0, dq, lat, p, inputs)
                if reached:
                    for r in range(q + 1, s0):
                        accepted[r] = False
                    accepted[s0] = True
                    prev_pt[s0] = q
                    used_bound[s0] = bound
                    restart = -1
                    break
                q = prev_pt[q]
                back += 1
            if restart < 0:
                prev = s0
                nskip = 0
                t = s0 + 1
                continue
        # a new piece starts at ``restart``
        accepted[restart] = True
        seg_start[restart] = True
        for j in range(cand_ptr[restart], cand_ptr[restart + 1]):
            score[j] = emis[j]
        prev = restart
        nskip = 0
        t = restart + 1
