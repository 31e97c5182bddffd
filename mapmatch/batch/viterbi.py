"""The batch Viterbi search over the lattice (compiled), as stages.

- The search itself is :mod:`mapmatch.viterbi`'s, which knows nothing of roads: each step is
  its relaxation, the transitions supplied by the step-cost provider
  :mod:`mapmatch.batch.step` (the transition model over routes between candidates).
- The forward pass (:func:`_forward`), for each point: does the step start a new piece
  (:mod:`mapmatch.batch.split`)? If not, try the step; reached, ask the leave-out policy
  whether the point before was the outlier; unreachable, ask it what to leave out
  (:mod:`mapmatch.batch.leave_out`). A point no candidate of the previous kept point can reach
  is left out; after more than ``max_skip`` such points in a row, lasting ``max_skip_time``
  (:func:`~mapmatch.batch.leave_out.skip_more`), a new piece starts at the first of them.
- The backtrack (:func:`_backtrack`), each piece from its last point, the track's ends left
  out where visiting them costs more than leaving them out.
"""

from __future__ import annotations

import math

import numpy as np

from graph.jit import njit
from mapmatch.arena import UNCOUNTED, full_b1, full_f8, full_i8, int64, ref, take_b1, take_f8, take_i8
from mapmatch.batch.arrays import KernelParams, Lattice
from mapmatch.batch.leave_out import (
    Chosen,
    Detour,
    Pieces,
    Saved,
    Search,
    accept,
    leave_out_before_split,
    leave_out_one,
    reconsider_prev,
    skip_more,
    start_piece,
    track_end,
    track_start,
)
from mapmatch.batch.split import splits_before
from mapmatch.batch.step import Trellis, _try_step, step_inputs
from mapmatch.viterbi import backtrack


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
    """Exact Viterbi over the lattice, routing each step as it goes (:func:`_forward`, then
    :func:`_backtrack`; ``sig``: each lattice point's σ; working arrays from the arena ``ar``).
    Returns a :class:`~mapmatch.batch.leave_out.Chosen`: per lattice point the chosen
    candidate (-1 = left out), whether a piece starts there, whether the step into it is an
    along-road U-turn, and its route bound.
    """
    max_skip = p.max_skip
    m = len(lat.ptr) - 1
    nc = len(lat.emis)
    fw = Pieces(full_i8(ar, m, -1), full_b1(ar, m, False), full_b1(ar, m, False), full_f8(ar, m, 0.0))
    chosen = Chosen(full_i8(ar, m, -1), fw.seg_start, full_b1(ar, m, False), fw.used_bound)
    if m == 0:
        return chosen
    kmax = 1
    for t in range(m):
        kmax = max(kmax, lat.ptr[t + 1] - lat.ptr[t])
    tr = Trellis(
        full_f8(ar, nc, -np.inf),
        full_i8(ar, nc, -1),
        full_b1(ar, nc, False),
        take_i8(ar, kmax),
        take_f8(ar, kmax),
    )
    saved = Saved(take_f8(ar, kmax), take_i8(ar, kmax), take_b1(ar, kmax), take_f8(ar, 2))
    detour = Detour(
        take_i8(ar, max_skip + 1),
        take_i8(ar, max_skip + 1),
        take_f8(ar, max_skip + 1),
        take_f8(ar, max_skip + 1),
    )
    s = Search(lat, p, router, tr, saved, detour)
    _forward(s, fw)
    _backtrack(s, sig, fw, chosen)
    return chosen


@njit(**UNCOUNTED)
def _backtrack(s, sig, fw, chosen):  # type: ignore[no-untyped-def]
    """:func:`solve`'s backtrack, each piece from its last point (:func:`_piece_end`) by
    :func:`mapmatch.viterbi.backtrack`, into ``chosen``. The track's last points may be left
    out (:func:`~mapmatch.batch.leave_out.track_end`; a split's, beside a jump or a gap, are
    not: there the fixes are already in doubt), and a piece of one point at the track's start
    or end, beside another piece: one fix makes no route (a fix near some road before or after
    a run off the route). Then the track's first points
    (:func:`~mapmatch.batch.leave_out.track_start`)."""
    sr = ref(s)
    lat, p, tr = s.lat, s.p, s.tr
    ptr = lat.ptr
    choice = chosen.choice
    t = len(ptr) - 2
    while not fw.accepted[t]:
        t -= 1
    if p.outlier_lookahead:
        t = track_end(t, sr, sig, fw)
    last = t
    while True:
        j = _piece_end(ptr[t], ptr[t + 1], tr, lat, s.router.g)
        first = backtrack(tr.bp, fw.prev_pt, fw.seg_start, t, j, choice)
        r = t
        while r != first:
            chosen.via_u[r] = tr.bpu[choice[r]]
            r = fw.prev_pt[r]
        q = first - 1
        while q >= 0 and not fw.accepted[q]:
            q -= 1
        if p.outlier_lookahead and first == t and (q < 0) != (first == last):
            choice[first] = -1
            fw.seg_start[first] = False
        if q < 0:
            break
        t = q
    if p.outlier_lookahead:
        track_start(chosen, sr, sig)


@njit(**UNCOUNTED)
def _forward(s, fw):  # type: ignore[no-untyped-def]
    """:func:`solve`'s forward pass over the :class:`~mapmatch.batch.leave_out.Search` ``s``:
    every step scored, its points kept or left out and the pieces started, into ``fw``
    (:class:`~mapmatch.batch.leave_out.Pieces`).

    Compiled without reference counting (:data:`~mapmatch.arena.UNCOUNTED`), apart from
    :func:`solve`, which allocates: the inlined :func:`~mapmatch.batch.step._try_step` copies
    every tuple it is handed, and with reference counting each copy would cost a call per
    array, over a hundred a step."""
    sr = ref(s)  # the rules' view of it: one pointer
    lat, p = s.lat, s.p
    inputs = step_inputs(lat, s.tr, p, s.router)
    pxy = lat.pxy
    m = len(lat.ptr) - 1
    prev = int64(0)  # not 0: one compile of each kernel it is handed to (``mapmatch.arena.int64``)
    start_piece(prev, sr, fw)
    nskip = 0
    s0 = int64(-1)
    t = int64(1)
    d = 0.0
    while t < m or nskip > 1:
        restart = -1
        counted = False  # the run just passed ``max_skip`` points
        if t >= m:
            restart = s0  # several trailing points unreachable: they form their own piece
        else:
            d = math.hypot(pxy[t, 0] - pxy[prev, 0], pxy[t, 1] - pxy[prev, 1])
            if splits_before(prev, t, d, lat, p):
                restart = s0 if nskip > 0 else t
        if restart < 0:
            reached, bound = _try_step(prev, t, d, lat, p, inputs)
            if reached:
                accept(prev, t, bound, fw)
                reconsider_prev(prev, t, nskip, s0, sr, fw)
                prev = t
                nskip = 0
                t += 1
                continue
            if nskip == 0 and p.outlier_lookahead and t + 1 < m and leave_out_one(prev, t, sr, fw):
                prev = t + 1  # one of prev, t left out; t + 1 reached
                t += 2
                continue
            if nskip == 0:
                s0 = t
            nskip += 1
            if nskip <= p.max_skip or (nskip > p.max_skip + 1 and skip_more(prev, t, lat, p)):
                t += 1
                continue
            restart = s0
            counted = nskip == p.max_skip + 1
        if nskip > 0 and restart == s0 and leave_out_before_split(prev, s0, nskip, sr, fw):
            prev = s0
            nskip = 0
            t = s0 + 1
            continue
        if counted and skip_more(prev, t, lat, p):
            t += 1  # the points kept lead on: the run is judged by its time
            continue
        # a new piece starts at ``restart``
        start_piece(restart, sr, fw)
        prev = restart
        nskip = 0
        t = restart + 1
