"""One Viterbi step: every pair of candidates of two lattice points scored with the shared
transition model (:func:`mapmatch.model.transition_logp_one`) over the route between them
(compiled).

Routes come from a table look-up within its bound (:mod:`mapmatch.route_table`), else a bounded
search whose bound shrinks as the targets' best scores rise (:mod:`mapmatch.routing`). A route
longer than the time between the fixes allows, or whose detour costs more than
``detour_cost_max`` β, or longer than the path through a run of fixes off the map it
bridges by ``off_map_bridge_slack``, is no route (:mod:`mapmatch.batch.split` says whether a
step stays in one piece of the match).

This module is the search's step-cost provider: it works out each transition's
log-probability, and :mod:`mapmatch.viterbi`'s relaxation keeps the best.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.jit import njit
from mapmatch.arena import UNCOUNTED, deref, ref
from mapmatch.batch.split import run_path
from mapmatch.model import transition_logp_one
from mapmatch.route_table import ubodt_lookup
from mapmatch.routing import LOWER_BOUND_SCALE, Router, _reset, search_toward_inlined
from mapmatch.viterbi import close_column, open_column, relax, sources_best_first, worst_target


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
    emis: NDArray[np.float64]


class StepRules(NamedTuple):
    """The parameters a Viterbi step reads besides the transition's (see
    :class:`~mapmatch.batch.arrays.KernelParams`)."""

    reverse_tol: float
    one_way_tol: float


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
    sc = StepCandidates(lat.edge, lat.offset, lat.emis)
    rules = StepRules(p.reverse_tol, p.one_way_tol)
    return ref(StepInputs(sc, tr, p.transition, rules, router))


class StepLeg(NamedTuple):
    """One step's scale, as :func:`_try_step` works it out for :func:`_step`."""

    trav: float
    """Metres travelled between the fixes (the odometer's where it has one)."""
    dt: float
    """Seconds between the fixes."""
    beta0: float
    """The step's base β, grown with its driving time."""
    beta: float
    """The step's β: ``beta0`` grown with the distance travelled."""
    node_uturn: float
    """The log-probability cost of turning round at a junction (less after a stop)."""
    vcap: float
    """The longest route the step allows (metres): longer ones are impossible."""


class StepView(NamedTuple):
    """What :func:`_along_road` and :func:`_routed` read of the candidates, the scores and the
    rules, made once per step by :func:`_step` from its :class:`StepInputs`."""

    edge: NDArray[np.int64]
    offset: NDArray[np.float64]
    best: NDArray[np.float64]
    bp: NDArray[np.int64]
    bpu: NDArray[np.bool_]
    params: NDArray[np.float64]
    rules: StepRules


@njit(**UNCOUNTED)
def _step(a0, a1, b0, b1, inputs, leg, bound):  # type: ignore[no-untyped-def]
    """One Viterbi step from candidates ``a0:a1`` to ``b0:b1`` of the candidates of ``inputs``
    (:class:`StepInputs`, by :func:`~mapmatch.arena.ref`): the generic relaxation of
    :mod:`mapmatch.viterbi`, its transitions supplied along the road (:func:`_along_road`) and
    by routing within ``bound`` metres (:func:`_routed`); ``leg``: the step's
    :class:`StepLeg`.

    Sources are taken best score first. As every transition log-probability is <= 0, a source
    can only improve target ``j`` when its score beats ``best[j]``, and only through a route
    shorter than ``trav + beta * (score - best[j])``: the search bound shrinks accordingly and
    the result stays exact. Returns whether any target was reached. Compiled without reference
    counting (:data:`~mapmatch.arena.UNCOUNTED`).
    """
    cand, tr, params, rules, router = deref(inputs)
    ws = router.ws
    cedge = cand.edge
    g = router.g
    v = StepView(cedge, cand.offset, tr.best, tr.bp, tr.bpu, params, rules)
    sources_best_first(tr.score, a0, a1, tr.order)
    open_column(tr.best, tr.bp, b0, b1)
    nuniq = 0
    for j in range(b0, b1):
        tr.bpu[j] = False
        if ws.tgt[cedge[j]] == 0:
            ws.tgt[cedge[j]] = 1
            nuniq += 1
    for oi in range(a1 - a0):
        i = tr.order[oi]
        si = tr.score[i]
        if si == -np.inf:
            break
        worst = worst_target(tr.best, b1 - b0)
        if worst >= si:
            break  # no remaining source can improve any target
        lim = bound
        if worst > -np.inf:
            lim = min(bound, leg.trav + leg.beta * (si - worst))
        need = _along_road(i, si, b0, b1, v, g.edge_len, g.edge_rev, leg)
        rest = g.edge_len[cedge[i]] - cand.offset[i]  # the way left along its edge
        if need and not rest > lim:
            _routed(i, si, lim, (b0, b1, nuniq), v, router, leg)
    for j in range(b0, b1):
        ws.tgt[cedge[j]] = 0
    return close_column(tr.best, tr.score, cand.emis, b0, b1)


@njit(cache=True, nogil=True, inline="always")
def standing_tol(e, edge_rev, reverse_tol, one_way_tol):  # type: ignore[no-untyped-def]
    """Metres a candidate may fall behind the previous one on edge ``e`` and count as standing:
    ``reverse_tol`` on a two-way road, where a U-turn is the other reading of a fix further
    back; ``one_way_tol`` on a one-way edge, which no vehicle drives backwards: a fix a little
    back along it is noise about the place the vehicle stands at, within the fix's search
    radius (the transition charges the fixes' distance apart against the route's 0 m, and
    leaving the fix out competes as for any fix), not a fix to leave out at the cost of the
    place the vehicle reached."""
    return reverse_tol if edge_rev[e] >= 0 else one_way_tol


@njit(cache=True, nogil=True, inline="always")
def _along_road(i, si, b0, b1, v, edge_len, edge_rev, leg):  # type: ignore[no-untyped-def]
    """The transitions from source candidate ``i`` (score ``si``) that need no route: to the
    targets ``b0:b1`` ahead on its own edge (or behind it, standing: :func:`standing_tol`) and, turning
    round, on its reverse edge, each relaxed (:func:`mapmatch.viterbi.relax`; ``v``: the
    step's :class:`StepView`). Returns whether some target needs a route."""
    rules = v.rules
    params = v.params
    e = v.edge[i]
    o = v.offset[i]
    need = False
    tol = standing_tol(e, edge_rev, rules.reverse_tol, rules.one_way_tol)
    for j in range(b0, b1):
        f = v.edge[j]
        if f == e and v.offset[j] >= o - tol:
            r = max(v.offset[j] - o, 0.0)
            lp = -np.inf
            if r <= leg.vcap:
                lp = transition_logp_one(r, leg.trav, leg.dt, params, False, leg.beta0)
            if relax(v.best, v.bp, b0, j, i, si + lp):
                v.bpu[j] = False
        else:
            need = True
            r = abs(edge_len[e] - v.offset[j] - o)
            if f == edge_rev[e] and r <= leg.vcap:
                lp = transition_logp_one(r, leg.trav, leg.dt, params, True, leg.beta0)
                near_end = edge_len[e] - o <= rules.reverse_tol and v.offset[j] <= rules.reverse_tol
                if leg.node_uturn < params[3] and near_end:
                    # turning round at the junction (within reverse_tol) after a stop
                    lp += params[3] - leg.node_uturn
                if relax(v.best, v.bp, b0, j, i, si + lp):
                    v.bpu[j] = True
    return need


@njit(cache=True, nogil=True, inline="always")
def _routed(i, si, lim, targets, v, router, leg):  # type: ignore[no-untyped-def]
    """The transitions from source candidate ``i`` (score ``si``) over routes of at most ``lim``
    metres to the targets :func:`_along_road` left (``targets``: ``b0, b1`` and how many
    distinct edges they are on), each relaxed: from the route table where it holds every route
    within the bound, else by a bounded search."""
    b0, b1, nuniq = targets
    g = router.g
    ws = router.ws
    table = router.table
    cedge = v.edge
    coff = v.offset
    exy = g.edge_xy
    e = cedge[i]
    o = coff[i]
    rest = g.edge_len[e] - o  # the way left along e to its end node
    via_table = lim <= table.delta  # the table holds every route within the bound
    tol = standing_tol(e, g.edge_rev, v.rules.reverse_tol, v.rules.one_way_tol)
    nt = 0
    if not via_table:
        nt = search_toward_inlined(e, rest, lim, nuniq, cedge[b0:b1], g, ws)
    xe, ye = exy[e, 2], exy[e, 3]
    for j in range(b0, b1):
        f = cedge[j]
        if f == e and coff[j] >= o - tol:
            continue
        if via_table:
            # no look-up (cold memory) where even the straight line from e's end to f's start
            # is too long: beyond trav + beta * (si - best[j]), as lp <= -|r - trav| / beta,
            # no route improves target j
            ex = xe - exy[f, 0]
            ey = ye - exy[f, 1]
            lim_j = min(lim, leg.trav + leg.beta * (si - v.best[j - b0]) + 1e-6)
            if rest + math.sqrt(ex * ex + ey * ey) * LOWER_BOUND_SCALE + coff[j] > lim_j:
                continue
        r = (rest + ubodt_lookup(table, e, f) if via_table else ws.dist[f]) + coff[j]
        if r <= lim:
            lp = transition_logp_one(r, leg.trav, leg.dt, v.params, False, leg.beta0)
            if relax(v.best, v.bp, b0, j, i, si + lp):
                v.bpu[j] = False
    if not via_table:
        _reset(nt, ws)


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
        vcap = min(vcap, run_path(prev, t, lat, p) + p.off_map_bridge_slack)
    reach = p.route_factor * trav + p.route_slack
    if dt > 0:
        reach = max(reach, p.route_speed * dt)
    bound = min(reach, vcap)
    tight = min(bound, trav + p.lp_cut_m)
    stop = p.stop  # (stop speed, stop time, U-turn penalty across a stop)
    node_uturn = p.transition[3]
    if dt >= stop[1] and d < stop[0] * dt:
        node_uturn = min(node_uturn, stop[2])
    leg = StepLeg(trav, dt, beta0, beta0 + p.transition[4] * trav, node_uturn, vcap)
    reached = False
    ptr = lat.ptr
    for npass in range(2):
        lim = tight if npass == 0 else bound
        if npass == 1 and lim <= tight:
            break
        a0, a1, b0, b1 = ptr[prev], ptr[prev + 1], ptr[t], ptr[t + 1]
        reached = _step(a0, a1, b0, b1, inputs, leg, lim)
        if reached:
            break
    return reached, bound
