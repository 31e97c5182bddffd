"""The leave-out rules of the batch Viterbi search (compiled): which fixes the search leaves
out, each a public policy the forward pass (:mod:`mapmatch.batch.viterbi`) asks.

- :func:`reconsider_prev`, once a point is reached: was the point before it the outlier?
  Either the fix before a run left out (:func:`leave_out_prev`), or a stray fix the route bent
  to (:func:`leave_out_visited`).
- :func:`leave_out_one`, when a point is unreachable: leave out it or the point before it,
  whichever reaches the next point better (:func:`drop_one`).
- :func:`skip_more`, once more than ``max_skip`` points in a row are unreachable: may the
  run grow, or does the track split? (its time since the last point kept).
- :func:`leave_out_before_split`, before a run of unreachable points splits the match: maybe
  the last points kept were the outliers (a drift onto a road that does not lead on).
- :func:`track_end` and :func:`track_start`: the track's first and last fixes are left out
  where visiting them costs more than leaving them out.

Each fix left out costs ``leave_out_cost`` where leaving out competes with visiting. The rules
read a :class:`Search`, by one pointer (:func:`~mapmatch.arena.ref`: no copy of its arrays per
call), and write the forward pass's :class:`Pieces`. Compiled without reference
counting (:data:`~mapmatch.arena.UNCOUNTED`), as the forward pass that calls them.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.jit import njit
from mapmatch.arena import UNCOUNTED, deref, int64
from mapmatch.batch.arrays import KernelParams, Lattice
from mapmatch.batch.split import far_gap, joinable, left_the_route
from mapmatch.batch.step import Trellis, _step_scale, _try_step, standing_tol, step_inputs
from mapmatch.route_table import ubodt_lookup
from mapmatch.routing import Router, _reset, _search
from mapmatch.viterbi import start_column


class Saved(NamedTuple):
    """One point's Viterbi scores and back-pointers, kept while an alternative is tried."""

    score: NDArray[np.float64]
    bp: NDArray[np.int64]
    bpu: NDArray[np.bool_]
    bound: NDArray[np.float64]
    """Route bounds of the chosen alternative's two steps."""


class Detour(NamedTuple):
    """Per point of a run left out (index from its first): the point its best step came from
    (-1: none reaches it), the points left out on the way, the score less their cost, and the
    step's route bound (:func:`leave_out_prev`)."""

    pred: NDArray[np.int64]
    left_out: NDArray[np.int64]
    score: NDArray[np.float64]
    bound: NDArray[np.float64]


class Search(NamedTuple):
    """What the forward pass and its rules read: the lattice, the parameters, the router, the
    scores (:class:`~mapmatch.batch.step.Trellis`) and the rules' scratch."""

    lat: Lattice
    p: KernelParams
    router: Router
    tr: Trellis
    saved: Saved
    detour: Detour


class Pieces(NamedTuple):
    """The forward pass's outcome per lattice point."""

    prev_pt: NDArray[np.int64]
    """The point the step into it came from (-1: none)."""
    accepted: NDArray[np.bool_]
    """Kept (not left out)."""
    seg_start: NDArray[np.bool_]
    """It starts a piece."""
    used_bound: NDArray[np.float64]
    """The route bound of the step into it."""


class Chosen(NamedTuple):
    """The search's answer per lattice point (:func:`~mapmatch.batch.viterbi.solve`)."""

    choice: NDArray[np.int64]
    """The chosen candidate (-1: left out)."""
    seg_start: NDArray[np.bool_]
    via_u: NDArray[np.bool_]
    """The step into it is an along-road U-turn."""
    used_bound: NDArray[np.float64]


@njit(cache=True, nogil=True, inline="always")
def accept(prev, t, bound, fw):  # type: ignore[no-untyped-def]
    """Point ``t`` kept, reached from ``prev`` by a step of route bound ``bound``."""
    fw.accepted[t] = True
    fw.prev_pt[t] = prev
    fw.used_bound[t] = bound


@njit(cache=True, nogil=True, inline="always")
def start_piece(t, sr, fw):  # type: ignore[no-untyped-def]
    """Point ``t`` kept, starting a piece: its candidates score their emissions."""
    s = deref(sr)
    fw.accepted[t] = True
    fw.seg_start[t] = True
    ptr = s.lat.ptr
    start_column(s.tr.score, s.lat.emis, ptr[t], ptr[t + 1])


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
def best_score(score, a, b):  # type: ignore[no-untyped-def]
    """The highest of ``score[a:b]``."""
    out = -np.inf
    for j in range(a, b):
        out = max(out, score[j])
    return out


@njit(**UNCOUNTED)
def drop_one(q, prev, t, sr):  # type: ignore[no-untyped-def]
    """``t`` is unreachable from ``prev``: leave out ``t`` (step ``prev`` -> ``t + 1``) or
    ``prev`` (steps ``q`` -> ``t`` -> ``t + 1``; ``q`` -1: ``prev`` starts its piece, and ``t``
    starts it instead), whichever scores higher at ``t + 1`` (``s``: the :class:`Search`).

    Returns the point kept of the two (-1: neither reaches ``t + 1``; scores at ``t`` and
    ``t + 1`` are then to be recomputed). ``saved.bound`` gets the chosen steps' route bounds.
    """
    s = deref(sr)
    lat, p, tr, saved = s.lat, s.p, s.tr, s.saved
    inputs = step_inputs(lat, tr, p, s.router)
    ptr = lat.ptr
    b0, b1 = ptr[t + 1], ptr[t + 2]
    s_drop_t = -np.inf
    ok, d = joinable(prev, t + 1, lat, p)
    if ok:
        reached, bound = _try_step(prev, t + 1, d, lat, p, inputs)
        if reached:
            saved.bound[1] = bound
            s_drop_t = _save(tr, saved, b0, b1)
    s_drop_prev = -np.inf
    ok1, d1 = joinable(q, t, lat, p) if q >= 0 else (True, 0.0)
    ok2, d2 = joinable(t, t + 1, lat, p)
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
                s_drop_prev = best_score(tr.score, b0, b1)
                if s_drop_prev > s_drop_t:
                    saved.bound[0] = bound1
                    saved.bound[1] = bound2
                    return t
    if s_drop_t == -np.inf:
        return -1
    _restore(tr, saved, b0, b1)
    return prev


@njit(**UNCOUNTED)
def leave_out_one(prev, t, sr, fw):  # type: ignore[no-untyped-def]
    """``t`` is unreachable from ``prev``: :func:`drop_one` leaves out one of them if then
    ``t + 1`` is reached, and the steps chosen go into ``fw`` (:class:`Pieces`). Returns
    whether it did (the search goes on after ``t + 1``)."""
    s = deref(sr)
    q = -1 if fw.seg_start[prev] else fw.prev_pt[prev]
    kept = drop_one(q, prev, t, sr)
    if kept < 0:
        return False
    if kept == t:
        fw.accepted[prev] = False
        accept(q, t, s.saved.bound[0], fw)
        if fw.seg_start[prev]:
            fw.seg_start[prev] = False
            fw.seg_start[t] = True
        fw.prev_pt[t + 1] = t
    else:
        fw.prev_pt[t + 1] = prev
    fw.accepted[t + 1] = True
    fw.used_bound[t + 1] = s.saved.bound[1]
    return True


@njit(cache=True, nogil=True, inline="always")
def reconsider_prev(prev, t, nskip, s0, sr, fw):  # type: ignore[no-untyped-def]
    """``t`` was just reached from ``prev`` (after ``nskip`` points left out from ``s0``): maybe
    ``prev`` was the outlier, not the points after it. After a run left out (of at most
    ``max_skip`` points: a longer one would cost a step per pair of its points), the points from
    ``s0`` to ``t`` stepped to from the point before ``prev`` (:func:`leave_out_prev`); after
    none, a ``prev`` the route bent to that is clearly dearer than stepping past it
    (:func:`leave_out_visited`, tried only where the bound allows a gain). ``fw`` gets the
    steps kept. Compiled into the forward pass, as it is asked at every step."""
    s = deref(sr)
    p = s.p
    if not p.outlier_lookahead or fw.seg_start[prev]:
        return
    q = fw.prev_pt[prev]
    if 1 < nskip <= p.max_skip and leave_out_prev(q, s0, t, sr):
        fw.accepted[prev] = False
        r = t
        while r >= s0:
            accept(s.detour.pred[r - s0], r, s.detour.bound[r - s0], fw)
            r = fw.prev_pt[r]
        return
    if nskip != 0:
        return
    ptr = s.lat.ptr
    # the step past ``prev`` scores at most its start plus ``t``'s best emission
    reach = best_score(s.tr.score, ptr[q], ptr[q + 1]) + best_score(s.lat.emis, ptr[t], ptr[t + 1])
    if best_score(s.tr.score, ptr[t], ptr[t + 1]) < reach - 2.0 * p.leave_out_cost and leave_out_visited(
        q, prev, t, sr
    ):
        # visiting ``prev`` cost clearly more than leaving it out: a stray the route bent to
        fw.accepted[prev] = False
        fw.prev_pt[t] = q
        fw.used_bound[t] = s.saved.bound[0]


@njit(cache=True, nogil=True, inline="always")
def skip_more(prev, t, lat, p):  # type: ignore[no-untyped-def]
    """Whether a run of more than ``max_skip`` unreachable points, up to lattice point ``t``,
    may still be left out rather than split from ``prev``, the last point kept: while ``t`` lies
    at most ``max_skip_time`` seconds after ``prev`` (asked once the points kept before the run
    are not the outliers, :func:`leave_out_before_split`). The time a vehicle spends off the
    route's roads is what its fixes tell, whatever their rate: a dense track is not split where
    the same drive sampled sparsely is bridged (no times: the count alone)."""
    return lat.ptime[t] - lat.ptime[prev] <= p.max_skip_time


@njit(**UNCOUNTED)
def leave_out_before_split(prev, s0, run, sr, fw):  # type: ignore[no-untyped-def]
    """A run of ``run`` points from ``s0`` is unreachable from ``prev`` and would start a new
    piece: maybe the last points kept were the outliers (a drift onto a road that does not lead
    on). Reach ``s0`` from up to ``max_skip`` points before ``prev``, leaving out the points
    kept between, while they are fewer than the run (not across a jump, even spread over its
    steps, nor a run off the route). A split keeps every fix: where leaving out the points
    kept saves no more fixes than it drops, the fixes are two stretches of one drive, not a
    drift and its way back (fixes far back along a one-way, after the car drove on). Returns
    whether it did (``fw`` then has the step)."""
    s = deref(sr)
    lat, p = s.lat, s.p
    inputs = step_inputs(lat, s.tr, p, s.router)
    pxy, ptime = lat.pxy, lat.ptime
    q = fw.prev_pt[prev]
    back = 0  # the points kept from ``q`` to ``prev`` left out: ``back + 1``
    while q >= 0 and back < p.max_skip and back + 1 < run:
        dq = math.hypot(pxy[s0, 0] - pxy[q, 0], pxy[s0, 1] - pxy[q, 1])
        if far_gap(dq, ptime[s0] - ptime[q], p, back + 2) or left_the_route(q, s0, lat, p):
            return False
        reached, bound = _try_step(q, s0, dq, lat, p, inputs)
        if reached:
            for r in range(q + 1, s0):
                fw.accepted[r] = False
            accept(q, s0, bound, fw)
            return True
        q = fw.prev_pt[q]
        back += 1
    return False


@njit(**UNCOUNTED)
def leave_out_visited(q, prev, t, sr):  # type: ignore[no-untyped-def]
    """``t`` was reached from ``prev``, and ``prev`` from ``q``, so dearly that the step from
    ``q`` straight to ``t`` could win (:func:`reconsider_prev` checks the bound): score ``t``
    from ``q`` too, leaving ``prev`` out at ``p.leave_out_cost``, and keep that if it scores
    higher by more than the cost (a clear gain, as in :func:`leave_out_prev`). Returns whether
    it did (``saved.bound[0]`` gets the step's route bound); if not, the scores at ``t`` are as
    they were."""
    s = deref(sr)
    lat, p, tr, saved = s.lat, s.p, s.tr, s.saved
    inputs = step_inputs(lat, tr, p, s.router)
    ptr = lat.ptr
    b0, b1 = ptr[t], ptr[t + 1]
    kept = _save(tr, saved, b0, b1)
    ok, d = joinable(q, t, lat, p)
    if ok:
        reached, bound = _try_step(q, t, d, lat, p, inputs)
        if reached and best_score(tr.score, b0, b1) - p.leave_out_cost > kept + p.leave_out_cost:
            saved.bound[0] = bound
            return True
    _restore(tr, saved, b0, b1)
    return False


@njit(cache=True, nogil=True, inline="always")
def emission_cost(c, t, lat, sig):  # type: ignore[no-untyped-def]
    """What candidate ``c`` of lattice point ``t`` costs against a fix on its road: its
    emission's distance and heading terms (``sig``: each lattice point's σ)."""
    return -(lat.emis[c] + math.log(sig[t]))


@njit(**UNCOUNTED)
def detour_cost(a, i, b, j, uturn, bound, sr):  # type: ignore[no-untyped-def]
    """The detour of the step from lattice point ``a`` (candidate ``i``) to ``b`` (candidate
    ``j``; ``uturn``: an along-road U-turn; ``bound``: its route bound) over the distance
    travelled, in β: the transition's cost without its speed terms, which tell of the
    timestamps, not of the road (0 if no route is found)."""
    s = deref(sr)
    lat, p, router = s.lat, s.p, s.router
    d = math.hypot(lat.pxy[b, 0] - lat.pxy[a, 0], lat.pxy[b, 1] - lat.pxy[a, 1])
    trav, _dt, beta0 = _step_scale(a, b, d, lat, p)
    e, o = lat.edge[i], lat.offset[i]
    f, of = lat.edge[j], lat.offset[j]
    g = router.g
    if uturn:
        r = abs(g.edge_len[e] - of - o)
    elif f == e and of >= o - standing_tol(e, g.edge_rev, p.reverse_tol, p.one_way_tol):
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
def track_end(t, sr, sig, fw):  # type: ignore[no-untyped-def]
    """The track's last kept point, its last being lattice point ``t``: points at its end are
    left out while visiting one costs more than ``leave_out_cost``, its emission's cost plus
    its step's detour (a fix in a car park by some road, reached by a way round). ``fw``: the
    forward pass's :class:`Pieces`."""
    s = deref(sr)
    ptr = s.lat.ptr
    tr = s.tr
    while not fw.seg_start[t]:
        j = ptr[t] + np.argmax(tr.score[ptr[t] : ptr[t + 1]])
        a = fw.prev_pt[t]
        if tr.bp[j] < 0 or a < 0:
            break
        cost = emission_cost(j, t, s.lat, sig)
        cost += detour_cost(a, tr.bp[j], t, j, tr.bpu[j], fw.used_bound[t], sr)
        if cost <= s.p.leave_out_cost:
            break
        t = a
    return t


@njit(**UNCOUNTED)
def track_start(ch, sr, sig):  # type: ignore[no-untyped-def]
    """The mirror of :func:`track_end`, on the chosen path (``ch``: :class:`Chosen`): the
    track's first points are left out while visiting one costs more than ``leave_out_cost``
    (its emission's cost plus its step's detour: a fix in a car park by some road, left by a
    way round). The next point then starts the route, its candidate chosen again for the step
    after it, as the Viterbi search would from a track starting there. A first piece left with
    one point beside another piece is left out (one fix makes no route)."""
    s = deref(sr)
    lat, p, tr = s.lat, s.p, s.tr
    inputs = step_inputs(lat, tr, p, s.router)
    choice, seg_start, via_u = ch.choice, ch.seg_start, ch.via_u
    m = len(choice)
    st = 0
    while st < m and choice[st] < 0:
        st += 1
    while st < m:
        n = st + 1
        while n < m and choice[n] < 0:
            n += 1
        if n == m or seg_start[n]:
            return
        i, j = choice[st], choice[n]
        cost = emission_cost(i, st, lat, sig)
        cost += detour_cost(st, i, n, j, via_u[n], ch.used_bound[n], sr)
        if cost <= p.leave_out_cost:
            return
        choice[st] = -1
        seg_start[st] = False
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
        start_column(tr.score, lat.emis, lat.ptr[n], lat.ptr[n + 1])
        d = math.hypot(lat.pxy[nn, 0] - lat.pxy[n, 0], lat.pxy[nn, 1] - lat.pxy[n, 1])
        reached, bound = _try_step(n, nn, d, lat, p, inputs)
        k = choice[nn]
        if reached and tr.bp[k] >= 0:
            choice[n] = tr.bp[k]
            via_u[nn] = tr.bpu[k]
            ch.used_bound[nn] = bound
        st = n


@njit(**UNCOUNTED)
def leave_out_prev(q, s0, t, sr):  # type: ignore[no-untyped-def]
    """``t`` was reached from ``prev = s0 - 1`` leaving out the points ``s0 .. t - 1``: try
    leaving out ``prev`` instead, stepping from ``q`` (the point before it) through those
    points to ``t``, each step from whichever earlier point scores best at it, each point left
    out costing ``p.leave_out_cost``. Returns whether that scores higher at ``t`` by more than
    that cost (a choice made at ``t`` binds the points after it: only a clear gain is taken),
    with the chosen steps in ``s.detour`` (:class:`Detour`); if not, the scores at ``t`` are as
    they were."""
    s = deref(sr)
    lat, p, tr, dt = s.lat, s.p, s.tr, s.detour
    inputs = step_inputs(lat, tr, p, s.router)
    ptr = lat.ptr
    b0, b1 = ptr[t], ptr[t + 1]
    kept = _save(tr, s.saved, b0, b1)
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
            ok, d = joinable(src, r, lat, p)
            if not ok:
                continue
            reached, bound = _try_step(src, r, d, lat, p, inputs)
            last = src
            if not reached:
                continue
            lo = k + 1 if i < 0 else dt.left_out[i] + k - i - 1  # ``prev`` counts when from q
            sc = best_score(tr.score, ptr[r], ptr[r + 1])
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
    _restore(tr, s.saved, b0, b1)
    return False
