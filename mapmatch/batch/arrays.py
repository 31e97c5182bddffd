"""The named tuples the batch matcher's compiled kernels take and return.

Dense integer indices inside (edge, candidate, lattice point), track indices only at the edges.
Each tuple groups arrays that travel together, so a kernel takes five arguments, not forty.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from mapmatch import model
from mapmatch.config import MatchConfig


class TrackPoints(NamedTuple):
    """The track in the map's CRS, one row per input point."""

    valid: NDArray[np.bool_]
    """Finite, in-range coordinates."""
    kept: NDArray[np.bool_]
    """Points in the lattice (the rest are interpolated afterwards)."""
    xy: NDArray[np.float64]
    time: NDArray[np.float64]
    """Seconds, NaN when unknown."""
    odo: NDArray[np.float64]
    """Cumulative odometer distance (metres), or empty when the track has none."""
    kidx: NDArray[np.int64]
    """Track indices of the kept points."""


class CandidateArrays(NamedTuple):
    """Road candidates of the kept points, sorted by point (``point`` indexes ``kidx``)."""

    point: NDArray[np.int64]
    edge: NDArray[np.int64]
    offset: NDArray[np.float64]
    xy: NDArray[np.float64]
    dist: NDArray[np.float64]
    emis: NDArray[np.float64]
    """Emission log-probabilities; empty: distance-only with :attr:`KernelParams.sigma`."""
    sigma: NDArray[np.float64]
    """Position σ per candidate; empty: :attr:`KernelParams.sigma` for all."""


class Lattice(NamedTuple):
    """The pruned candidates by lattice point (``ptr``) and the lattice points' measurements.

    Keep it at these eleven arrays: each array added, even unused, slows every compiled call
    that is handed the tuple; derive what a step needs from these, as its driving time."""

    ptr: NDArray[np.int64]
    edge: NDArray[np.int64]
    offset: NDArray[np.float64]
    xy: NDArray[np.float64]
    dist: NDArray[np.float64]
    emis: NDArray[np.float64]
    pts: NDArray[np.int64]
    """Track index of each lattice point."""
    pxy: NDArray[np.float64]
    ptime: NDArray[np.float64]
    podo: NDArray[np.float64]
    run: NDArray[np.float64]
    """(m, 10): :func:`mapmatch.batch.lattice.left_out_runs`, how far the kept points a step
    leaves out travel among themselves (the route is cut where they travel ``off_map_cut``)."""


class EdgeGeometry(NamedTuple):
    """Edge polylines: ``seg_xy[seg_ptr[e]:seg_ptr[e + 1]]`` is edge ``e``."""

    seg_xy: NDArray[np.float64]
    seg_ptr: NDArray[np.int64]
    seg_len: NDArray[np.float64]
    """:func:`mapmatch.batch.lattice.segment_lengths` (computed once per map)."""


class KernelParams(NamedTuple):
    """The batch section of :class:`mapmatch.config.MatchConfig`, as the kernels read it."""

    sigma: float
    """GPS σ (metres) for distance-only emissions computed in the kernel."""
    prune: float
    outlier: float
    transition: NDArray[np.float64]
    """:func:`mapmatch.model.transition_params`."""
    stop: NDArray[np.float64]
    """(stop speed, stop time, U-turn penalty across a stop)."""
    route_factor: float
    route_slack: float
    route_speed: float
    beta_per_s: float
    """Metres of β per second of a step's driving time (its mean fix interval)."""
    lp_cut_m: float
    gap_distance: float
    """Metres a faster step than ``split_speed`` must reach to split: ``split_speed`` times
    ``batch.outliers.max_skip_time`` (inf: distance never splits)."""
    max_skip: int
    max_skip_time: float
    """seconds after the last point kept before ``max_skip`` unreachable points split (0: none)."""
    outlier_lookahead: bool
    """Where a point is unreachable, also try leaving out the one before it."""
    leave_out_cost: float
    """Log-probability cost of a point left out, where two ways of leaving points out compete
    (½ ``batch.outliers.off_map_sigmas``²)."""
    reverse_tol: float
    one_way_tol: float
    """Metres a candidate may fall behind the previous one on a one-way edge and count as
    standing (``model.search_radius``: the previous place lies among the fix's own)."""
    split_speed: float
    """m/s; 0: no speed check on steps."""
    split_slack: float
    """Metres of the fixes' noise on top of the top speed: 2 ``off_map_sigmas`` σ."""
    split_route_speed: float
    """m/s; the top speed a route may need over its step's time, where the fixes move no
    faster (``batch.split.split_speed``; 0: routes are not judged by their own speed)."""
    detour_cost_max: float
    """Routes longer than the travelled distance by more than this many β are impossible:
    ``batch.outliers.off_map_sigmas``² (0: no limit, the joining call's)."""
    off_map_sigmas: float
    off_map_cut: float
    off_map_cut_fixes: int
    off_map_cut_speed: float
    off_map_bridge_slack: float
    """metres, twice ``batch.split.off_map_cut``; inf: any route bridges a run off the map."""


class Assembly(NamedTuple):
    """The matched route and per-point results, as arrays (see :mod:`mapmatch.batch.results`)."""

    p_edge: NDArray[np.int64]
    p_off: NDArray[np.float64]
    p_xy: NDArray[np.float64]
    p_dist: NDArray[np.float64]
    status: NDArray[np.int64]
    """0 unmatched, 1 matched, 2 interpolated."""
    splits: NDArray[np.int64]
    route_e: NDArray[np.int64]
    route_ptr: NDArray[np.int64]
    xy_all: NDArray[np.float64]
    rxy_ptr: NDArray[np.int64]
    length: float
    conf: float


def kernel_params(cfg: MatchConfig, sigma: float) -> KernelParams:
    """The kernels' parameters from a config (``sigma``: the one GPS σ, when it is one)."""
    b = cfg.batch
    return KernelParams(
        sigma=float(sigma),
        prune=float(b.outliers.emission_prune),
        outlier=float(b.outliers.outlier_distance),
        transition=model.transition_params(cfg),
        stop=np.array(  # as good as stopped (no heading), for as long as turning round takes
            [cfg.model.heading_min_speed, b.outliers.spike_max_time, b.route.stop_uturn_penalty],
            dtype=np.float64,
        ),
        route_factor=float(b.route.max_route_factor),
        route_slack=float(b.route.route_slack + b.route.turn_cost),  # the search counts turns as metres
        route_speed=float(b.route.route_speed),
        beta_per_s=float(b.route.beta_per_s),
        lp_cut_m=float(cfg.model.beta * b.route.route_lp_cut),
        # a jump: further than the top speed goes while fixes may be left out as outliers
        gap_distance=float(b.split.split_speed * b.outliers.max_skip_time) or np.inf,
        max_skip=int(b.outliers.max_skip),
        max_skip_time=float(b.outliers.max_skip_time),
        outlier_lookahead=bool(b.outliers.outlier_lookahead),
        leave_out_cost=float(b.outliers.leave_out_cost),
        reverse_tol=float(b.route.reverse_tolerance),
        one_way_tol=max(float(cfg.model.search_radius), float(b.route.reverse_tolerance)),
        split_speed=float(b.split.split_speed),
        # the fixes' noise on top of the top speed: each of the step's two fixes up to the
        # off-map limit from its road
        split_slack=2.0 * float(b.outliers.off_map_sigmas) * float(sigma),
        split_route_speed=float(b.split.split_speed),  # one top speed for both checks
        detour_cost_max=float(b.outliers.detour_cost_max),
        off_map_sigmas=float(b.outliers.off_map_sigmas),
        off_map_cut=float(b.split.off_map_cut),
        off_map_cut_fixes=int(b.split.off_map_cut_fixes),
        # cars leave the mapped road no faster than they turn round
        off_map_cut_speed=float(b.outliers.spike_speed) if b.outliers.spike_speed > 0 else np.inf,
        off_map_bridge_slack=float(b.split.bridge_slack) if b.split.bridge_slack > 0 else np.inf,
    )
