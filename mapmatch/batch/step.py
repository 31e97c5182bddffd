"""One Viterbi step: every pair of candidates of two lattice points scored with the shared
transition model (:func:`mapmatch.model.transition_logp_one`) over the route between them
(compiled).

Routes come from a table look-up within its bound (:mod:`mapmatch.route_table`), else a bounded
search whose bound shrinks as the targets' best scores rise (:mod:`mapmatch.routing`). A route
longer than the time between the fixes allows, or whose detour costs more than
``detour_cost_max`` β, or longer than the path through a run of fixes off the map it
bridges by ``off_map_bridge_slack``, is no route. :func:`_joinable`, :func:`_far_gap` and
:func:`_left_the_route` (the fixes a step leaves out left the route's roads) say whether a step
stays in one piece of the match.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.jit import njit
from mapmatch.arena import UNCOUNTED, deref, ref
from mapmatch.model import transition_logp_one
from mapmatch.route_table import ubodt_lookup
from mapmatch.routing import LOWER_BOUND_SCALE, Router, _reset, search_toward_inlined


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


class StepInputs(NamedTuple):
    """What every Viterbi step of a kernel reads besides its candidates' places and scale:
    :func:`_step` gets it by one pointer (:func:`step_inputs`)."""

    cand: StepCandidates
    tr: Trellis
    params: NDArray[np.float64]
    """The transition's parameters (:attr:`~mapmatch.batch.arrays.KernelParams.transition`)."""
    rules: StepRules
    router: Router


@njit(cache=True, nogil=True, inline="always")
def step_inputs(lat, tr, p, router):  # type: ignore[no-untyped-def]
    """:class:`StepInputs` in the calling kernel's frame, for its :func:`_try_step` calls
    (:func:`~mapmatch.arena.ref`): made once, before the steps, not copied for each. Compiled
    into its caller, whose frame holds the copy the pointer points to."""
    sc = StepCandidates(lat.edge, lat.offset, lat.limit, lat.emis)
    rules = StepRules(p.reverse_tol, p.limit_factor, p.limit_penalty)
    return ref(StepInputs(sc, tr, p.transition, rules, router))


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


@njit(**UNCOUNTED)
def _step(a0, a1, b0, b1, inputs, node_uturn, trav, dt, beta0, bound, vcap):  # type: ignore[no-untyped-def]
    """One Viterbi step from candidates ``a0:a1`` to ``b0:b1`` of the candidates of ``inputs``
    (:class:`StepInputs`, by :func:`~mapmatch.arena.ref`), routing as needed (routes longer
    than ``vcap``, the most the step's time allows, are impossible; ``beta0``: the step's base
    β, grown with its driving time).

    Sources are taken best score first. As every transition log-probability is <= 0, a source
    can only improve target ``j`` when its score beats ``best[j]``, and only through a route
    shorter than ``trav + beta * (score - best[j])``: the search bound shrinks accordingly and
    the result stays exact. Returns whether any target was reached. Compiled without reference
    counting (:data:`~mapmatch.arena.UNCOUNTED`).
    """
    cand, tr, params, rules, router = deref(inputs)
    g = router.g
    ws = router.ws
    table = router.table
    cedge = cand.edge
    coff = cand.offset
    score, bp, bpu, order, best = tr
    edge_len = g.edge_len
    edge_rev = g.edge_rev
    exy = g.edge_xy
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
        rest = edge_len[e] - o  # the way left along e to its end node
        if not need or rest > lim:
            continue
        via_table = lim <= table.delta  # the table holds every route within the bound
        nt = 0
        if not via_table:
            nt = search_toward_inlined(e, rest, lim, nuniq, cedge[b0:b1], g, ws)
        xe, ye = exy[e, 2], exy[e, 3]
        for j in range(b0, b1):
            f = cedge[j]
            if f == e and coff[j] >= o - reverse_tol:
                continue
            if via_table:
                # no look-up (cold memory) where even the straight line from e's end to f's start
                # is too long: beyond trav + beta * (si - best[j]), as lp <= -|r - trav| / beta,
                # no route improves target j
                ex = xe - exy[f, 0]
                ey = ye - exy[f, 1]
                lim_j = min(lim, trav + beta * (si - best[j - b0]) + 1e-6)
                if rest + math.sqrt(ex * ex + ey * ey) * LOWER_BOUND_SCALE + coff[j] > lim_j:
                    continue
            r = (rest + ubodt_lookup(table, e, f) if via_table else ws.dist[f]) + coff[j]
            if r <= lim:
                lp = transition_logp_one(r, trav, dt, params, False, beta0) + _over_limit(
                    r, dt, limit, i, j, lf, lpen
                )
                if si + lp > best[j - b0]:
                    best[j - b0] = si + lp
                    bp[j] = i
                    bpu[j] = False
        if not via_table:
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
def _try_step(prev, t, d, lat, p, inputs):  # type: ignore[no-untyped-def]
    """The Viterbi step from lattice point ``prev`` to ``t`` (``d`` metres apart): a tight search
    bound first, the full bound only if nothing is reached. Returns (reached, full bound).
    ``inputs``: the caller's :func:`step_inputs`.

    Compiled into its callers, as the search is into :func:`_step`: one call less per step and
    per search. Its callers and :func:`_step` are compiled without reference counting
    (:data:`~mapmatch.arena.UNCOUNTED`): inlined, it copies every tuple it is handed, and
    numba would count a reference to each of their arrays, a few hundred calls a step."""
    trav, dt, beta0 = _step_scale(prev, t, d, lat, p)
    vcap = np.inf  # the longest route the time between the fixes allows: the straight line
    if p.split_speed > 0 and dt > 0:  # plus the detour that time allows
        vcap = d + p.split_speed * dt + p.split_slack
    if p.split_route_speed > 0 and dt > 0 and d <= p.split_route_speed * dt:
        # a route a car could drive in the time (where the fixes could: else their clock is in doubt)
        vcap = min(vcap, p.split_route_speed * dt + p.split_slack)
    if p.detour_cost_max > 0:  # and the longest detour the transition allows
        vcap = min(vcap, trav + (beta0 + p.transition[4] * trav) * p.detour_cost_max)
    # a run of fixes off the map is bridged only near the path its fixes trace (the count
    # here, the rest a call: compiled into every caller, it would slow every call)
    if lat.run[t, 2] - lat.run[prev, 3] + 1 >= p.off_map_cut_fixes:
        vcap = min(vcap, _run_path(prev, t, lat, p) + p.off_map_bridge_slack)
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
    for npass in range(2):
        lim = tight if npass == 0 else bound
        if npass == 1 and lim <= tight:
            break
        a0, a1, b0, b1 = ptr[prev], ptr[prev + 1], ptr[t], ptr[t + 1]
        reached = _step(a0, a1, b0, b1, inputs, node_uturn, trav, dt, beta0, lim, vcap)
        if reached:
            break
    return reached, bound


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
    ok = not _far_gap(d, dt, p, 1) and not dt > gap_time  # no time (NaN) is no gap, as in the forward pass
    # only the runs between consecutive lattice points (fixes off the map): the fixes a choice
    # to leave out drops are weighed by their cost instead
    for r in range(a + 1, b + 1):
        ok = ok and not _left_the_route(r - 1, r, lat, p)
    return ok, d


@njit(cache=True, nogil=True)
def _run_path(a, b, lat, p):  # type: ignore[no-untyped-def]
    """The path of a step from lattice point ``a`` to ``b`` through the fixes it leaves out,
    from fix ``a`` through them to fix ``b``, where they are a run :func:`_left_the_route`
    weighs (``off_map_cut_fixes`` or more, travelling ``off_map_cut`` among themselves); else
    inf."""
    run = lat.run
    if not (p.off_map_cut > 0 and run[b, 2] - run[a, 3] + 1 >= p.off_map_cut_fixes):
        return np.inf
    travel = run[b, 0] - run[a, 1]
    if travel < p.off_map_cut:
        return np.inf
    return travel + _run_legs(a, b, lat)


@njit(cache=True, nogil=True, inline="always")
def _run_legs(a, b, lat):  # type: ignore[no-untyped-def]
    """The legs from fix ``a`` to the first fix a step to ``b`` leaves out, and from its last
    to fix ``b``."""
    run = lat.run
    return math.hypot(run[a, 8] - lat.pxy[a, 0], run[a, 9] - lat.pxy[a, 1]) + math.hypot(
        lat.pxy[b, 0] - run[b, 6], lat.pxy[b, 1] - run[b, 7]
    )


@njit(cache=True, nogil=True, inline="always")
def _left_the_route(a, b, lat, p):  # type: ignore[no-untyped-def]
    """Whether the fixes a step from lattice point ``a`` to ``b`` leaves out (off the map, or
    no road of the route reaches them), ``off_map_cut_fixes`` or more, travel ``off_map_cut``
    among themselves, or last as long as that takes at ``off_map_cut_speed`` and travel it with
    their legs to ``a`` and ``b``: the track left the route's roads and came back, and the
    route is cut there, not routed round."""
    run = lat.run
    # most steps leave out no fix: the count first
    if not (p.off_map_cut > 0 and run[b, 2] - run[a, 3] + 1 >= p.off_map_cut_fixes):
        return False
    travel = run[b, 0] - run[a, 1]
    lasted = run[b, 4] - run[a, 5] >= p.off_map_cut / p.off_map_cut_speed
    if not (travel >= p.off_map_cut or lasted):
        return False
    # a run that lasts but travels little: with its legs from and back to the route it must
    # travel ``off_map_cut`` too (a car parked by the road is not cut off it)
    if travel < p.off_map_cut and travel + _run_legs(a, b, lat) < p.off_map_cut:
        return False
    # the run's speed from its first fix to its last (its path would count the noise)
    net = math.hypot(run[b, 6] - run[a, 8], run[b, 7] - run[a, 9])
    return not net > p.off_map_cut_speed * (run[b, 4] - run[a, 5])
