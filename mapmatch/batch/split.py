"""Where the batch match splits into pieces (compiled): a step across a jump (:func:`far_gap`),
or one whose left-out fixes left the route's roads and came back (:func:`left_the_route`),
starts a new piece (:func:`splits_before`); a step that leaves out a run of fixes off the map
is bridged only by a route near their path (:func:`run_path`).

The forward pass (:mod:`mapmatch.batch.viterbi`) asks :func:`splits_before` before each step,
and the leave-out rules (:mod:`mapmatch.batch.leave_out`) :func:`joinable` before each step
they try.
"""

from __future__ import annotations

import math

import numpy as np

from graph.jit import njit


@njit(cache=True, nogil=True, inline="always")
def splits_before(prev, t, d, lat, p):  # type: ignore[no-untyped-def]
    """Whether the step from lattice point ``prev`` to ``t`` (``d`` metres apart) starts a new
    piece: a jump (:func:`far_gap`) or a run off the route (:func:`left_the_route`)."""
    dt = lat.ptime[t] - lat.ptime[prev]
    return far_gap(d, dt, p, 1) or left_the_route(prev, t, lat, p)


@njit(cache=True, nogil=True, inline="always")
def far_gap(d, dt, p, steps):  # type: ignore[no-untyped-def]
    """Whether ``d`` metres in ``dt`` seconds, over ``steps`` steps, is a gap that splits the
    track: longer than ``gap_distance`` a step (``split_speed`` times ``max_skip_time``), and
    faster on average than ``split_speed`` (a slower gap, a logger off or a sparse track, is
    driven: its route is searched as any step's).
    """
    if d <= p.gap_distance * steps:
        return False
    return p.split_speed <= 0 or not dt > 0 or d > p.split_speed * dt


@njit(cache=True, nogil=True)
def joinable(a, b, lat, p):  # type: ignore[no-untyped-def]
    """Whether a step from lattice point ``a`` to ``b`` stays in one piece; and its distance."""
    d = math.hypot(lat.pxy[b, 0] - lat.pxy[a, 0], lat.pxy[b, 1] - lat.pxy[a, 1])
    dt = lat.ptime[b] - lat.ptime[a]
    ok = not far_gap(d, dt, p, 1)
    # only the runs between consecutive lattice points (fixes off the map): the fixes a choice
    # to leave out drops are weighed by their cost instead
    for r in range(a + 1, b + 1):
        ok = ok and not left_the_route(r - 1, r, lat, p)
    return ok, d


@njit(cache=True, nogil=True)
def run_path(a, b, lat, p):  # type: ignore[no-untyped-def]
    """The path of a step from lattice point ``a`` to ``b`` through the fixes it leaves out,
    from fix ``a`` through them to fix ``b``, where they are a run :func:`left_the_route`
    weighs (``off_map_cut_fixes`` or more, travelling ``off_map_cut`` among themselves); else
    inf."""
    run = lat.run
    if not (p.off_map_cut > 0 and run[b, 2] - run[a, 3] + 1 >= p.off_map_cut_fixes):
        return np.inf
    travel = run[b, 0] - run[a, 1]
    if travel < p.off_map_cut:
        return np.inf
    return travel + run_legs(a, b, lat)


@njit(cache=True, nogil=True, inline="always")
def run_legs(a, b, lat):  # type: ignore[no-untyped-def]
    """The legs from fix ``a`` to the first fix a step to ``b`` leaves out, and from its last
    to fix ``b``."""
    run = lat.run
    return math.hypot(run[a, 8] - lat.pxy[a, 0], run[a, 9] - lat.pxy[a, 1]) + math.hypot(
        lat.pxy[b, 0] - run[b, 6], lat.pxy[b, 1] - run[b, 7]
    )


@njit(cache=True, nogil=True, inline="always")
def left_the_route(a, b, lat, p):  # type: ignore[no-untyped-def]
    """Whether the fixes a step from lattice point ``a`` to ``b`` leaves out (off the map, or
    no road of the route reaches them), ``off_map_cut_fixes`` or more, travel ``off_map_cut``
    among themselves, or last as long as that takes at ``off_map_cut_speed`` (``spike_speed``)
    and travel it with their legs to ``a`` and ``b``: the track left the route's roads and came back, and the
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
    if travel < p.off_map_cut and travel + run_legs(a, b, lat) < p.off_map_cut:
        return False
    # the run's speed from its first fix to its last (its path would count the noise)
    net = math.hypot(run[b, 6] - run[a, 8], run[b, 7] - run[a, 9])
    return not net > p.off_map_cut_speed * (run[b, 4] - run[a, 5])
