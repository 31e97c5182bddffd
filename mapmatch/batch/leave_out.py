"""Which fixes the Viterbi search leaves out (compiled): an unreachable fix or the one before
it (:func:`_drop_one`), a stray fix the route bent to (:func:`_leave_out_visited`), the fix
before a run left out (:func:`_leave_out_prev`), and the track's first and last fixes where
visiting them costs more than leaving them out (:func:`_track_end`). Each fix left out costs
``leave_out_cost`` where leaving out competes with visiting.

Compiled without reference counting (:data:`~mapmatch.arena.UNCOUNTED`), as the Viterbi
search's forward pass that calls them (:func:`mapmatch.batch.viterbi._forward`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.jit import njit
from mapmatch.arena import UNCOUNTED, int64
from mapmatch.batch.step import _joinable, _step_scale, _try_step, step_inputs
from mapmatch.route_table import ubodt_lookup
from mapmatch.routing import _reset, _search


class Saved(NamedTuple):
    """One point's Viterbi scores and back-pointers, kept while an alternative is tried."""

    score: NDArray[np.float64]
    bp: NDArray[np.int64]
    bpu: NDArray[np.bool_]
    bound: NDArray[np.float64]
    """Route bounds of the chosen alternative's two steps."""


@njit(cache=True, nogil=True, inline="always")
def _save(tr, saved, b0, b1):  # type: ignore[no-untyped-def]
    """Keep the scores and back-pointers of candidates ``b0:b1`` in ``saved``; returns their best
    score."""
    best = -np.inf
    for j in range(b1 - b0):
        saved.score[j] = tr.score[b0 + j]
        saved.bp[j] = tr.bp[b0 + j]
        saved.bpu[j] = tr.bpu[b0 + j]
        best = max(best, tr.score[b0 + j])
    return best


@njit(cache=True, nogil=True, inline="always")
def _restore(tr, saved, b0, b1):  # type: ignore[no-untyped-def]
    """Put back what :func:`_save` kept."""
    for j in range(b1 - b0):
        tr.score[b0 + j] = saved.score[j]
        tr.bp[b0 + j] = saved.bp[j]
        tr.bpu[b0 + j] = saved.bpu[j]


@njit(**UNCOUNTED)
def _best(score, a, b):  # type: ignore[no-untyped-def]
    """The highest of ``score[a:b]``."""
    out = -np.inf
    for j in range(a, b):
        out = max(out, score[j])
    return out


@njit(**UNCOUNTED)
def _drop_one(q, prev, t, lat, tr, p, router, saved):  # type: ignore[no-untyped-def]
    """``t`` is unreachable from ``prev``: leave out ``t`` (step ``prev`` -> ``t + 1``) or
    ``prev`` (steps ``q`` -> ``t`` -> ``t + 1``; ``q`` -1: ``prev`` starts its piece, and ``t``
    starts it instead), whichever scores higher at ``t + 1``.

    Returns the point kept of the two (-1: neither reaches ``t + 1``; scores at ``t`` and
    ``t + 1`` are then to be recomputed). ``saved.bound`` gets the chosen steps' route bounds.
    """
    inputs = step_inputs(lat, tr, p, router)
    ptr = lat.ptr
    b0, b1 = ptr[t + 1], ptr[t + 2]
    s_drop_t = -np.inf
    ok, d = _joinable(prev, t + 1, lat, p)
    if ok:
        reached, bound = _try_step(prev, t + 1, d, lat, p, inputs)
        if reached:
            saved.bound[1] = bound
            s_drop_t = _save(tr, saved, b0, b1)
    s_drop_prev = -np.inf
    ok1, d1 = _joinable(q, t, lat, p) if q >= 0 else (True, 0.0)
    ok2, d2 = _joinable(t, t + 1, lat, p)
    if ok1 and ok2:
        r1, bound1 = True, 0.0
        if q >= 0:
            r1, bound1 = _try_step(q, t, d1, lat, p, inputs)
        else:  # ``t`` starts the piece
            for j in range(ptr[t], ptr[t + 1]):
                tr.score[j] = lat.emis[j]
                tr.bp[j] = -1
        if r1:
            r2, bound2 = _try_step(t, t + 1, d2, lat, p, inputs)
            if r2:
                s_drop_prev = _best(tr.score, b0, b1)
                if s_drop_prev > s_drop_t:
                    saved.bound[0] = bound1
                    saved.bound[1] = bound2
                    return t
    if s_drop_t == -np.inf:
        return -1
    _restore(tr, saved, b0, b1)
    return prev


@njit(**UNCOUNTED)
def _leave_out_visited(q, prev, t, lat, tr, p, router, saved):  # type: ignore[no-untyped-def]
    """``t`` was reached from ``prev``, and ``prev`` from ``q``, so dearly that the step from
    ``q`` straight to ``t`` could win (:func:`solve` checks the bound): score ``t`` from ``q``
    too, leaving ``prev`` out at ``p.leave_out_cost``, and keep that if it scores higher by more
    than the cost (a clear gain, as in :func:`_leave_out_prev`). Returns whether it did
    (``saved.bound[0]`` gets the step's route bound); if not, the scores at ``t`` are as they
    were."""
    inputs = step_inputs(lat, tr, p, router)
    ptr = lat.ptr
    b0, b1 = ptr[t], ptr[t + 1]
    kept = _save(tr, saved, b0, b1)
    ok, d = _joinable(q, t, lat, p)
    if ok:
        reached, bound = _try_step(q, t, d, lat, p, inputs)
        if reached and _best(tr.score, b0, b1) - p.leave_out_cost > kept + p.leave_out_cost:
            saved.bound[0] = bound
            return True
    _restore(tr, saved, b0, b1)
    return False


@njit(cache=True, nogil=True, inline="always")
def _emission_cost(c, t, lat, sig):  # type: ignore[no-untyped-def]
    """What candidate ``c`` of lattice point ``t`` costs against a fix on its road: its
    emission's distance and heading terms (``sig``: each lattice point's σ)."""
    return -(lat.emis[c] + math.log(sig[t]))


@njit(**UNCOUNTED)
def _detour_cost(a, i, b, j, uturn, bound, lat, p, router):  # type: ignore[no-untyped-def]
    """The detour of the step from lattice point ``a`` (candidate ``i``) to ``b`` (candidate
    ``j``; ``uturn``: an along-road U-turn; ``bound``: its route bound) over the distance
    travelled, in β: the transition's cost without its speed terms, which tell of the
    timestamps, not of the road (0 if no route is found)."""
    d = math.hypot(lat.pxy[b, 0] - lat.pxy[a, 0], lat.pxy[b, 1] - lat.pxy[a, 1])
    trav, _dt, beta0 = _step_scale(a, b, d, lat, p)
    e, o = lat.edge[i], lat.offset[i]
    f, of = lat.edge[j], lat.offset[j]
    g = router.g
    if uturn:
        r = abs(g.edge_len[e] - of - o)
    elif f == e and of >= o - p.reverse_tol:
        r = max(of - o, 0.0)
    else:
        r = np.inf
        if router.table.delta > 0:
            r = g.edge_len[e] - o + ubodt_lookup(router.table, e, f) + of
        if not np.isfinite(r) and bound > router.table.delta:  # beyond the table: searched
            ws = router.ws
            ws.tgt[f] = 1
            nt = _search(e, g.edge_len[e] - o, bound + 1.0, int64(1), g, ws)
            ws.tgt[f] = 0
            r = ws.dist[f] + of
            _reset(nt, ws)
        if not np.isfinite(r):
            return 0.0
    return abs(r - trav) / (beta0 + p.transition[4] * trav)


@njit(**UNCOUNTED)
def _track_end(t, tr, lat, p, router, sig, prev_pt, seg_start, used_bound):  # type: ignore[no-untyped-def]
    """The track's last kept point, its last being lattice point ``t``: points at its end are
    left out while visiting one costs more than ``leave_out_cost``, its emission's cost plus
    its step's detour (a fix in a car park by some road, reached by a way round)."""
    ptr = lat.ptr
    while not seg_start[t]:
        j = ptr[t] + np.argmax(tr.score[ptr[t] : ptr[t + 1]])
        a = prev_pt[t]
        if tr.bp[j] < 0 or a < 0:
            break
        cost = _emission_cost(j, t, lat, sig)
        cost += _detour_cost(a, tr.bp[j], t, j, tr.bpu[j], used_bound[t], lat, p, router)
        if cost <= p.leave_out_cost:
            break
        t = a
    return t


@njit(**UNCOUNTED)
def _track_start(choice, seg_start, via_u, used_bound, tr, lat, p, router, sig):  # type: ignore[no-untyped-def]
    """The mirror of :func:`_track_end`, on the chosen path (``choice`` etc. as
    :func:`~mapmatch.batch.viterbi.solve` returns them): the track's first points are left
    out while visiting one costs more than ``leave_out_cost`` (its emission's cost plus its
    step's detour: a fix in a car park by some road, left by a way round). The next point
    then starts the route, its candidate chosen again for the step after it, as the Viterbi
    search would from a track starting there. A first piece left with one point beside
    another piece is left out (one fix makes no route)."""
    inputs = step_inputs(lat, tr, p, router)
    m = len(choice)
    ptr = lat.ptr
    s = 0
    while s < m and choice[s] < 0:
        s += 1
    while s < m:
        n = s + 1
        while n < m and choice[n] < 0:
            n += 1
        if n == m or seg_start[n]:
            return
        i, j = choice[s], choice[n]
        cost = _emission_cost(i, s, lat, sig)
        cost += _detour_cost(s, i, n, j, via_u[n], used_bound[n], lat, p, router)
        if cost <= p.leave_out_cost:
            return
        choice[s] = -1
        seg_start[s] = False
        seg_start[n] = True
        via_u[n] = False
        nn = n + 1
        while nn < m and choice[nn] < 0:
            nn += 1
        if nn == m:
            return
        if seg_start[nn]:  # ``n`` alone beside another piece
            choice[n] = -1
            seg_start[n] = False
            return
        for k in range(ptr[n], ptr[n + 1]):
            tr.score[k] = lat.emis[k]
        d = math.hypot(lat.pxy[nn, 0] - lat.pxy[n, 0], lat.pxy[nn, 1] - lat.pxy[n, 1])
        reached, bound = _try_step(n, nn, d, lat, p, inputs)
        k = choice[nn]
        if reached and tr.bp[k] >= 0:
            choice[n] = tr.bp[k]
            via_u[nn] = tr.bpu[k]
            used_bound[nn] = bound
        s = n


class Detour(NamedTuple):
    """Per point of a run left out (index from its first): the point its best step came from
    (-1: none reaches it), the points left out on the way, the score less their cost, and the
    step's route bound (:func:`_leave_out_prev`)."""

    pred: NDArray[np.int64]
    left_out: NDArray[np.int64]
    score: NDArray[np.float64]
    bound: NDArray[np.float64]


@njit(**UNCOUNTED)
def _leave_out_prev(q, s0, t, lat, tr, p, router, saved, dt):  # type: ignore[no-untyped-def]
    """``t`` was reached from ``prev = s0 - 1`` leaving out the points ``s0 .. t - 1``: try
    leaving out ``prev`` instead, stepping from ``q`` (the point before it) through those
    points to ``t``, each step from whichever earlier point scores best at it, each point left
    out costing ``p.leave_out_cost``. Returns whether that scores higher at ``t`` by more than
    that cost (a choice made at ``t`` binds the points after it: only a clear gain is taken),
    with the chosen steps in ``dt`` (:class:`Detour`); if not, the scores at ``t`` are as they
    were."""
    inputs = step_inputs(lat, tr, p, router)
    ptr = lat.ptr
    b0, b1 = ptr[t], ptr[t + 1]
    kept = _save(tr, saved, b0, b1)
    cost = p.leave_out_cost
    kept -= (t - s0) * cost
    for r in range(s0, t + 1):
        k = r - s0
        dt.pred[k] = -1
        dt.score[k] = -np.inf
        last = -1
        for i in range(-1, k):  # from q (-1), then from each point of the run a step reached
            src = q if i < 0 else s0 + i
            if i >= 0 and dt.pred[i] < 0:
                continue
            ok, d = _joinable(src, r, lat, p)
            if not ok:
                continue
            reached, bound = _try_step(src, r, d, lat, p, inputs)
            last = src
            if not reached:
                continue
            lo = k + 1 if i < 0 else dt.left_out[i] + k - i - 1  # ``prev`` counts when from q
            sc = _best(tr.score, ptr[r], ptr[r + 1])
            if sc - lo * cost > dt.score[k]:
                dt.pred[k] = src
                dt.left_out[k] = lo
                dt.score[k] = sc - lo * cost
                dt.bound[k] = bound
        src = dt.pred[k]
        if src >= 0 and src != last:  # the scores at ``r`` are the last try's: redo the best
            d = math.hypot(lat.pxy[r, 0] - lat.pxy[src, 0], lat.pxy[r, 1] - lat.pxy[src, 1])
            _try_step(src, r, d, lat, p, inputs)
    if dt.pred[t - s0] >= 0 and dt.score[t - s0] > kept + cost:  # by more than one fix's worth
        return True
    _restore(tr, saved, b0, b1)
    return False
