"""Exact Viterbi over the lattice, routing each step as it goes (compiled).

A step scores every pair of candidates of two consecutive lattice points with the shared
transition model (:func:`mapmatch.model.transition_logp_one`) over the route distance
between them. Routes come from a table look-up within its bound (:mod:`mapmatch.route_table`),
else a bounded search whose bound shrinks as the targets' best scores rise
(:mod:`mapmatch.routing`). A point no
candidate of the previous point can reach is left out; a run of them splits the match.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import NDArray

from mapmatch.arena import full_b1, full_f8, full_i8, take_b1, take_f8, take_i8
from mapmatch.batch.arrays import KernelParams, Lattice
from mapmatch.model import transition_logp_one
from mapmatch.route_table import ubodt_lookup
from mapmatch.routing import _reset, _search, search_toward_inlined


class Trellis(NamedTuple):
    """The Viterbi scores and back-pointers per candidate, and one step's scratch."""

    score: NDArray[np.float64]
    bp: NDArray[np.int64]
    """Best predecessor candidate (-1: none)."""
    bpu: NDArray[np.bool_]
    """Whether the step from ``bp`` is a U-turn along the road."""
    order: NDArray[np.int64]
    best: NDArray[np.float64]


class StepCandidates(NamedTuple):
    """The lattice arrays a Viterbi step reads: each array a compiled call carries costs time
    (see :class:`~mapmatch.routing.RouteGraph`), and :class:`Lattice` has twelve."""

    edge: NDArray[np.int64]
    offset: NDArray[np.float64]
    limit: NDArray[np.float64]
    emis: NDArray[np.float64]


class StepRules(NamedTuple):
    """The parameters a Viterbi step reads besides the transition's (see
    :class:`~mapmatch.batch.arrays.KernelParams`)."""

    reverse_tol: float
    limit_factor: float
    limit_penalty: float


@njit(cache=True, nogil=True, inline="always")
def _over_limit(r, dt, limit, i, j, factor, penalty):  # type: ignore[no-untyped-def]
    """Log-probability cost of a step of ``r`` metres in ``dt`` s beyond ``factor`` times the
    higher speed limit of candidates ``i`` and ``j`` (0 without limits)."""
    if penalty <= 0 or len(limit) == 0 or not dt > 0:
        return 0.0
    a = limit[i]
    b = limit[j]
    v = a if not np.isfinite(b) or (np.isfinite(a) and a > b) else b
    if not np.isfinite(v):
        return 0.0
    return -penalty * max(r / dt - factor * v, 0.0)


@njit(cache=True, nogil=True)
def _step(a0, a1, b0, b1, cand, tr, params, node_uturn, trav, dt, beta0, bound, vcap, rules, router):  # type: ignore[no-untyped-def]
    """One Viterbi step from candidates ``a0:a1`` to ``b0:b1`` of ``cand``
    (:class:`StepCandidates`), routing as needed (routes longer than ``vcap``, the most the
    step's time allows, are impossible; ``beta0``: the step's base β, grown with its driving
    time).

    Sources are taken best score first. As every transition log-probability is <= 0, a source
    can only improve target ``j`` when its score beats ``best[j]``, and only through a route
    shorter than ``trav + beta * (score - best[j])``: the search bound shrinks accordingly and
    the result stays exact. Returns whether any target was reached.
    """
    g = router.g
    ws = router.ws
    table = router.table
    cedge = cand.edge
    coff = cand.offset
    score, bp, bpu, order, best = tr
    edge_len = g.edge_len
    edge_rev = g.edge_rev
    reverse_tol = rules.reverse_tol
    limit = cand.limit
    lf = rules.limit_factor
    lpen = rules.limit_penalty
    ka = a1 - a0
    kb = b1 - b0
    beta = beta0 + params[4] * trav  # the step's β (it grows with the distance)
    for i in range(ka):
        order[i] = a0 + i
    # insertion sort by descending score (k is small)
    for i in range(1, ka):
        x = order[i]
        q = i - 1
        while q >= 0 and score[order[q]] < score[x]:
            order[q + 1] = order[q]
            q -= 1
        order[q + 1] = x
    for j in range(kb):
        best[j] = -np.inf
        bp[b0 + j] = -1
        bpu[b0 + j] = False
    nuniq = 0
    for j in range(b0, b1):
        if ws.tgt[cedge[j]] == 0:
            ws.tgt[cedge[j]] = 1
            nuniq += 1
    for oi in range(ka):
        i = order[oi]
        si = score[i]
        if si == -np.inf:
            break
        worst = np.inf
        for j in range(kb):
            worst = min(worst, best[j])
        if worst >= si:
            break  # no remaining source can improve any target
        lim = bound
        if worst > -np.inf:
            lim = min(bound, trav + beta * (si - worst))
        e = cedge[i]
        o = coff[i]
        need = False
        for j in range(b0, b1):
            f = cedge[j]
            if f == e and coff[j] >= o - reverse_tol:
                r = max(coff[j] - o, 0.0)
                lp = transition_logp_one(r, trav, dt, params, False, beta0) if r <= vcap else -np.inf
                lp += _over_limit(r, dt, limit, i, j, lf, lpen)
                if si + lp > best[j - b0]:
                    best[j - b0] = si + lp
                    bp[j] = i
                    bpu[j] = False
            else:
                need = True
                r = abs(edge_len[e] - coff[j] - o)
                if f == edge_rev[e] and r <= vcap:
                    lp = transition_logp_one(r, trav, dt, params, True, beta0) + _over_limit(
                        r, dt, limit, i, j, lf, lpen
                    )
                    if node_uturn < params[3] and edge_len[e] - o <= reverse_tol and coff[j] <= reverse_tol:
                        # turning round at the junction (within reverse_tol) after a stop
                        lp += params[3] - node_uturn
                    if si + lp > best[j - b0]:
                        best[j - b0] = si + lp
                        bp[j] = i
                        bpu[j] = True
        if not need or edge_len[e] - o > lim:
            continue
        if lim <= table.delta:  # the table holds every route within the bound
            for j in range(b0, b1):
                f = cedge[j]
                if f == e and coff[j] >= o - reverse_tol:
                    continue
                r = edge_len[e] - o + ubodt_lookup(table, e, f) + coff[j]
                if r <= lim:
                    lp = transition_logp_one(r, trav, dt, params, False, beta0) + _over_limit(
                        r, dt, limit, i, j, lf, lpen
                    )
                    if si + lp > best[j - b0]:
                        best[j - b0] = si + lp
                        bp[j] = i
                        bpu[j] = False
            continue
        nt = search_toward_inlined(e, edge_len[e] - o, lim, nuniq, cedge[b0:b1], g, ws)
        for j in range(b0, b1):
            f = cedge[j]
            if f == e and coff[j] >= o - reverse_tol:
                continue
            r = ws.dist[f] + coff[j]
            if r <= lim:
                lp = transition_logp_one(r, trav, dt, params, False, beta0) + _over_limit(
                    r, dt, limit, i, j, lf, lpen
                )
                if si + lp > best[j - b0]:
                    best[j - b0] = si + lp
                    bp[j] = i
                    bpu[j] = False
        _reset(nt, ws)
    for j in range(b0, b1):
        ws.tgt[cedge[j]] = 0
    reached = False
    for j in range(kb):
        if best[j] > -np.inf:
            reached = True
            score[b0 + j] = best[j] + cand.emis[b0 + j]
        else:
            score[b0 + j] = -np.inf
    return reached


@njit(cache=True, nogil=True, inline="always")
def _step_scale(prev, t, d, lat, p):  # type: ignore[no-untyped-def]
    """The distance travelled from lattice point ``prev`` to ``t`` (``d`` metres apart; the
    odometer's where it has one), their time apart and the step's base β (grown with its
    driving time: the mean fix interval, as a stop's fixes are interpolated)."""
    trav = d
    od = lat.podo[t] - lat.podo[prev]
    if np.isfinite(od) and od > 0:
        trav = od
    dt = lat.ptime[t] - lat.ptime[prev]
    beta0 = p.transition[0]
    if dt > 0:
        beta0 += p.beta_per_s * dt / max(lat.pts[t] - lat.pts[prev], 1)
    return trav, dt, beta0


@njit(cache=True, nogil=True, inline="always")
def _try_step(prev, t, d, lat, tr, p, router):  # type: ignore[no-untyped-def]
    """The Viterbi step from lattice point ``prev`` to ``t`` (``d`` metres apart): a tight search
    bound first, the full bound only if nothing is reached. Returns (reached, full bound).

    Compiled into its callers, as the search is into :func:`_step`: one call less per step and
    per search (about 5 % fewer instructions per point at 30 s, callgrind on REAL track
    00000021). The reference counts of the arrays a step reads stay: callgrind still counts
    about 78 increments per step at the call of :func:`_step` and 63 inside it."""
    trav, dt, beta0 = _step_scale(prev, t, d, lat, p)
    vcap = np.inf  # the longest route the time between the fixes allows: the straight line
    if p.split_speed > 0 and dt > 0:  # plus the detour that time allows
        vcap = d + p.split_speed * dt + p.split_slack
    if p.detour_cost_max > 0:  # and the longest detour the transition allows
        vcap = min(vcap, trav + (beta0 + p.transition[4] * trav) * p.detour_cost_max)
    reach = p.route_factor * trav + p.route_slack
    if dt > 0:
        reach = max(reach, p.route_speed * dt)
    bound = min(reach, vcap)
    tight = min(bound, trav + p.lp_cut_m)
    stop = p.stop  # (stop speed, stop time, U-turn penalty across a stop)
    node_uturn = p.transition[3]
    if dt >= stop[1] and d < stop[0] * dt:
        node_uturn = min(node_uturn, stop[2])
    reached = False
    ptr = lat.ptr
    sc = StepCandidates(lat.edge, lat.offset, lat.limit, lat.emis)
    rules = StepRules(p.reverse_tol, p.limit_factor, p.limit_penalty)
    for npass in range(2):
        lim = tight if npass == 0 else bound
        if npass == 1 and lim <= tight:
            break
        reached = _step(
            ptr[prev], ptr[prev + 1], ptr[t], ptr[t + 1], sc, tr, p.transition, node_uturn, trav, dt, beta0,
            lim, vcap, rules, router,
        )  # fmt: skip
        if reached:
            break
    return reached, bound


class Saved(NamedTuple):
    """One point's Viterbi scores and back-pointers, kept while an alternative is tried."""

    score: NDArray[np.float64]
    bp: NDArray[np.int64]
    bpu: NDArray[np.bool_]
    bound: NDArray[np.float64]
    """Route bounds of the chosen alternative's two steps."""


@njit(cache=True, nogil=True, inline="always")
def _far_gap(d, dt, p, steps):  # type: ignore[no-untyped-def]
    """Whether ``d`` metres in ``dt`` seconds, over ``steps`` steps, is a gap that splits the
    track: longer than ``gap_distance`` a step, and faster on average than ``split_speed`` (a
    slower gap, a logger off or a sparse track, is driven: its route is searched as any step's).
    """
    if d <= p.gap_distance * steps:
        return False
    return p.split_speed <= 0 or not dt > 0 or d > p.split_speed * dt


@njit(cache=True, nogil=True)
def _joinable(a, b, lat, p):  # type: ignore[no-untyped-def]
    """Whether a step from lattice point ``a`` to ``b`` stays in one piece; and its distance."""
    d = math.hypot(lat.pxy[b, 0] - lat.pxy[a, 0], lat.pxy[b, 1] - lat.pxy[a, 1])
    gap_time = p.gap_time if p.gap_time > 0 else np.inf
    dt = lat.ptime[b] - lat.ptime[a]
    ok = not _far_gap(d, dt, p, 1) and dt <= gap_time
    for r in range(a + 1, b + 1):
        ok = ok and not lat.cut[r]
    return ok, d


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


@njit(cache=True, nogil=True)
def _best(score, a, b):  # type: ignore[no-untyped-def]
    """The highest of ``score[a:b]``."""
    out = -np.inf
    for j in range(a, b):
        out = max(out, score[j])
    return out


@njit(cache=True, nogil=True)
def _drop_one(q, prev, t, lat, tr, p, router, saved):  # type: ignore[no-untyped-def]
    """``t`` is unreachable from ``prev``: leave out ``t`` (step ``prev`` -> ``t + 1``) or
    ``prev`` (steps ``q`` -> ``t`` -> ``t + 1``; ``q`` -1: ``prev`` starts its piece, and ``t``
    starts it instead), whichever scores higher at ``t + 1``.

    Returns the point kept of the two (-1: neither reaches ``t + 1``; scores at ``t`` and
    ``t + 1`` are then to be recomputed). ``saved.bound`` gets the chosen steps' route bounds.
    """
    ptr = lat.ptr
    b0, b1 = ptr[t + 1], ptr[t + 2]
    s_drop_t = -np.inf
    ok, d = _joinable(prev, t + 1, lat, p)
    if ok:
        reached, bound = _try_step(prev, t + 1, d, lat, tr, p, router)
        if reached:
            saved.bound[1] = bound
            s_drop_t = _save(tr, saved, b0, b1)
    s_drop_prev = -np.inf
    ok1, d1 = _joinable(q, t, lat, p) if q >= 0 else (True, 0.0)
    ok2, d2 = _joinable(t, t + 1, lat, p)
    if ok1 and ok2:
        r1, bound1 = True, 0.0
        if q >= 0:
            r1, bound1 = _try_step(q, t, d1, lat, tr, p, router)
        else:  # ``t`` starts the piece
            for j in range(ptr[t], ptr[t + 1]):
                tr.score[j] = lat.emis[j]
                tr.bp[j] = -1
        if r1:
            r2, bound2 = _try_step(t, t + 1, d2, lat, tr, p, router)
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


@njit(cache=True, nogil=True)
def _leave_out_visited(q, prev, t, lat, tr, p, router, saved):  # type: ignore[no-untyped-def]
    """``t`` was reached from ``prev``, and ``prev`` from ``q``, so dearly that the step from
    ``q`` straight to ``t`` could win (:func:`solve` checks the bound): score ``t`` from ``q``
    too, leaving ``prev`` out at ``p.leave_out_cost``, and keep that if it scores higher by more
    than the cost (a clear gain, as in :func:`_leave_out_prev`). Returns whether it did
    (``saved.bound[0]`` gets the step's route bound); if not, the scores at ``t`` are as they
    were."""
    ptr = lat.ptr
    b0, b1 = ptr[t], ptr[t + 1]
    kept = _save(tr, saved, b0, b1)
    ok, d = _joinable(q, t, lat, p)
    if ok:
        reached, bound = _try_step(q, t, d, lat, tr, p, router)
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


@njit(cache=True, nogil=True)
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
            nt = _search(e, g.edge_len[e] - o, bound + 1.0, 1, g, ws)
            ws.tgt[f] = 0
            r = ws.dist[f] + of
            _reset(nt, ws)
        if not np.isfinite(r):
            return 0.0
    return abs(r - trav) / (beta0 + p.transition[4] * trav)


@njit(cache=True, nogil=True)
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


class Detour(NamedTuple):
    """Per point of a run left out (index from its first): the point its best step came from
    (-1: none reaches it), the points left out on the way, the score less their cost, and the
    step's route bound (:func:`_leave_out_prev`)."""

    pred: NDArray[np.int64]
    left_out: NDArray[np.int64]
    score: NDArray[np.float64]
    bound: NDArray[np.float64]


@njit(cache=True, nogil=True)
def _leave_out_prev(q, s0, t, lat, tr, p, router, saved, dt):  # type: ignore[no-untyped-def]
    """``t`` was reached from ``prev = s0 - 1`` leaving out the points ``s0 .. t - 1``: try
    leaving out ``prev`` instead, stepping from ``q`` (the point before it) through those
    points to ``t``, each step from whichever earlier point scores best at it, each point left
    out costing ``p.leave_out_cost``. Returns whether that scores higher at ``t`` by more than
    that cost (a choice made at ``t`` binds the points after it: only a clear gain is taken),
    with the chosen steps in ``dt`` (:class:`Detour`); if not, the scores at ``t`` are as they
    were."""
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
            reached, bound = _try_step(src, r, d, lat, tr, p, router)
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
            _try_step(src, r, d, lat, tr, p, router)
    if dt.pred[t - s0] >= 0 and dt.score[t - s0] > kept + cost:  # by more than one fix's worth
        return True
    _restore(tr, saved, b0, b1)
    return False


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
    emis = lat.emis
    pxy = lat.pxy
    gap_time = p.gap_time if p.gap_time > 0 else np.inf
    ptime = lat.ptime
    max_skip = p.max_skip
    m = len(cand_ptr) - 1
    nc = len(emis)
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
    score = tr.score
    bp = tr.bp
    bpu = tr.bpu
    saved = Saved(take_f8(ar, kmax), take_i8(ar, kmax), take_b1(ar, kmax), take_f8(ar, 2))
    detour = Detour(
        take_i8(ar, max_skip + 1),
        take_i8(ar, max_skip + 1),
        take_f8(ar, max_skip + 1),
        take_f8(ar, max_skip + 1),
    )
    prev = 0
    accepted[0] = True
    seg_start[0] = True
    for j in range(cand_ptr[0], cand_ptr[1]):
        score[j] = emis[j]
    nskip = 0
    s0 = -1
    t = 1
    d = 0.0
    while t < m or nskip > 1:
        restart = -1
        if t >= m:
            restart = s0  # several trailing points unreachable: they form their own piece
        else:
            d = math.hypot(pxy[t, 0] - pxy[prev, 0], pxy[t, 1] - pxy[prev, 1])
            dt = ptime[t] - ptime[prev]
            if _far_gap(d, dt, p, 1) or lat.cut[t] or dt > gap_time:
                restart = s0 if nskip > 0 else t
        if restart < 0:
            reached, bound = _try_step(prev, t, d, lat, tr, p, router)
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
                if _far_gap(dq, ptime[s0] - ptime[q], p, back + 2):  # a jump even spread over its steps
                    break
                reached, bound = _try_step(q, s0, dq, lat, tr, p, router)
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
    # backtrack, each piece from its last point; the track's own ends may be left out (a
    # split's, beside a jump or a gap, are not: there the fixes are already in doubt)
    t = m - 1
    while not accepted[t]:
        t -= 1
    if p.outlier_lookahead:
        t = _track_end(t, tr, lat, p, router, sig, prev_pt, seg_start, used_bound)
    j = cand_ptr[t] + np.argmax(score[cand_ptr[t] : cand_ptr[t + 1]])
    later = -1  # the point after ``t`` in its piece
    while True:
        choice[t] = j
        if seg_start[t]:
            q = t - 1
            while q >= 0 and not accepted[q]:
                q -= 1
            cost = 0.0
            if p.outlier_lookahead and later >= 0 and q < 0:
                nj = choice[later]
                cost = _emission_cost(j, t, lat, sig)
                cost += _detour_cost(t, j, later, nj, via_u[later], used_bound[later], lat, p, router)
            if cost > p.leave_out_cost:
                # the track's first point costs more than its absence: the next one starts it
                choice[t] = -1
                seg_start[t] = False
                seg_start[later] = True
                via_u[later] = False
            if q < 0:
                break
            t = q
            j = cand_ptr[t] + np.argmax(score[cand_ptr[t] : cand_ptr[t + 1]])
            later = -1
        else:
            via_u[t] = bpu[j]
            later = t
            j = bp[j]
            t = prev_pt[t]
    return choice, seg_start, via_u, used_bound
