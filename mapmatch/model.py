"""The one probabilistic model shared by online filtering and batch Viterbi.

Emission: log p(z | c) = -½ (d/σ)² + κ · (cos(ψ − bearing(c)) − 1), with κ = 1/σψ² (von Mises),
0 when there is no usable heading.
Transition: log p(c_t | c_{t-1}) = −|route_dist − travelled| / β (Newson & Krumm 2009), where
travelled is the odometer distance when given, else the straight-line distance; minus a
U-turn penalty and a speed-plausibility penalty; forbidden moves are −inf.

Each formula is written once, as a scalar function in plain float math: the online filter
calls it as it is, the batch kernels call its compiled form, and the numpy wrappers
(:func:`emission_logp`, :func:`transition_logp`, :func:`heading_kappa`) apply it over arrays.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graph.jit import njit
from mapmatch.config import MatchConfig

NEG_INF = -np.inf

MAD_TO_SIGMA = 1.4826
"""σ of a normal distribution over the median of its absolute values (1 / Φ⁻¹(3/4))."""


def heading_kappa_one(sigma_deg: float, floor_deg: float) -> float:
    """Concentration κ of the heading term for a heading σ in degrees, floored at ``floor_deg``
    (the one formula: :func:`heading_kappa`, the batch kernels and the online step call it)."""
    return 1.0 / math.radians(max(sigma_deg, floor_deg)) ** 2


heading_kappa_compiled = njit(cache=True)(heading_kappa_one)


def heading_kappa(
    heading: ArrayLike, heading_sigma: ArrayLike, speed: ArrayLike, config: MatchConfig
) -> NDArray[np.float64]:
    """Concentration κ of the heading term per fix: 0 where the heading is missing or not
    trusted (the batch matcher's rules: ``model.heading_sigma`` by default, floored at
    ``batch.track.track_heading_sigma_floor_deg``)."""
    h, s, v = np.broadcast_arrays(
        np.asarray(heading, dtype=np.float64),
        np.asarray(heading_sigma, dtype=np.float64),
        np.asarray(speed, dtype=np.float64),
    )
    s = np.where(np.isnan(s), config.model.heading_sigma, s)
    k = _vector(heading_kappa_one)(s, config.batch.track.track_heading_sigma_floor_deg)
    slow = ~np.isnan(v) & (v < config.model.heading_min_speed)
    return np.asarray(np.where(np.isnan(h) | slow, 0.0, k), dtype=np.float64)


def _vector(f: Callable[..., float]) -> Callable[..., NDArray[np.float64]]:
    """The scalar model function ``f`` over arrays (broadcast), for the numpy wrappers."""
    return np.vectorize(f, otypes=[np.float64])  # type: ignore[return-value]


def position_sigma(pos_sigma: ArrayLike, config: MatchConfig) -> NDArray[np.float64]:
    """σ in metres per fix: the fix's own accuracy (floored at ``batch.track.track_pos_sigma_floor``), or
    the configured default."""
    s = np.asarray(pos_sigma, dtype=np.float64)
    floored = np.maximum(s, config.batch.track.track_pos_sigma_floor)
    return np.where(np.isnan(s) | (s <= 0), config.model.gps_sigma, floored)


def track_sigma(nearest: NDArray[np.float64], sigma: float, most: float) -> float:
    """A track's position σ from its fixes' distances to their nearest road: ``sigma``, or
    where larger (up to ``most``; 0: never) :data:`MAD_TO_SIGMA` times their median (Newson
    and Krumm's robust estimate). Compiled for the batch kernels as :data:`track_sigma_compiled`."""
    if most <= sigma or len(nearest) == 0:
        return sigma
    return min(max(sigma, MAD_TO_SIGMA * float(np.median(nearest))), most)


track_sigma_compiled = njit(cache=True)(track_sigma)


def emission_logp(
    dist: ArrayLike,
    sigma: ArrayLike,
    heading: ArrayLike,
    bearing: ArrayLike,
    kappa: ArrayLike,
) -> NDArray[np.float64]:
    """Emission log-probability of candidates (unnormalised).

    Parameters
    ----------
    dist
        Distance in metres from the fix to the candidate position.
    sigma
        Position σ in metres (broadcast).
    heading
        Fix heading in degrees (broadcast); NaN where unknown.
    bearing
        Road bearing at the candidate, in the direction of travel, degrees.
    kappa
        Heading concentration from :func:`heading_kappa` (0 disables the heading term).
    """
    return _vector(emission_one)(dist, sigma, heading, bearing, kappa)


def emission_one(dist: float, sigma: float, heading: float, bearing: float, kappa: float) -> float:
    """The emission log-probability of one candidate (unnormalised), in plain float math: the
    one formula, which the online hot path calls as it is, the batch kernels compiled
    (:func:`emission_logp_one`) and :func:`emission_logp` over arrays. The heading term counts
    where it is known and finite."""
    head = 0.0
    if kappa > 0.0 and not math.isnan(heading):
        t = kappa * (math.cos(math.radians(heading - bearing)) - 1.0)
        if math.isfinite(t):
            head = t
    return -0.5 * (dist / sigma) ** 2 - math.log(sigma) + head


emission_logp_one = njit(cache=True)(emission_one)


def transition_one(
    route_dist: float,
    travelled: float,
    dt: float,
    beta: float,
    beta_per_m: float,
    max_speed: float,
    speed_penalty: float,
) -> float:
    """:func:`transition_logp` for one pair without the U-turn term, in plain float math (the
    online hot path); :func:`transition_logp_one` compiles the same function."""
    lp = -abs(route_dist - travelled) / (beta + beta_per_m * travelled)
    if dt > 0.0:
        lp -= speed_penalty * max(route_dist / dt - max_speed, 0.0)
    return lp


_transition_one = njit(cache=True)(transition_one)
transition_one_compiled = _transition_one  # for other compiled kernels


def transition_logp(
    route_dist: ArrayLike,
    travelled: ArrayLike,
    dt: ArrayLike,
    config: MatchConfig,
    *,
    uturn: ArrayLike | bool = False,
) -> NDArray[np.float64]:
    """Transition log-probability between candidates of consecutive fixes.

    Parameters
    ----------
    route_dist
        Network distance in metres between the two candidate positions (inf = unreachable).
    travelled
        Odometer distance when given, else the straight-line distance between the fixes.
    dt
        Seconds between the fixes (NaN or 0 disables the speed check).
    config
        Supplies β, the U-turn penalty and the speed limits.
    uturn
        True where the move reverses direction on the same road.
    """
    m = config.model

    def one(r: float, d: float, t: float, u: bool) -> float:
        if not math.isfinite(r):
            return NEG_INF
        lp = transition_one(r, d, t, m.beta, m.beta_per_m, m.max_speed, m.speed_penalty)
        return lp - m.uturn_penalty if u else lp

    return _vector(one)(route_dist, travelled, dt, uturn)


def normalise_log(lp: ArrayLike) -> NDArray[np.float64]:
    """Probabilities from log-probabilities (softmax); uniform if all are −inf."""
    a = np.asarray(lp, dtype=np.float64)
    if a.size == 0:
        return a
    m = np.max(a)
    if not np.isfinite(m):
        return np.full(a.shape, 1.0 / a.size)
    p = np.exp(a - m)
    return p / p.sum()


def transition_params(config: MatchConfig) -> NDArray[np.float64]:
    """The transition parameters as an array for :func:`transition_logp_one`."""
    return np.array(
        [
            config.model.beta,
            config.model.max_speed,
            config.model.speed_penalty,
            config.model.uturn_penalty,
            config.model.beta_per_m,
        ],
        dtype=np.float64,
    )


@njit(cache=True, inline="always")  # inlined: no reference count of ``params`` per pair
def transition_logp_one(
    route_dist: float, travelled: float, dt: float, params: NDArray[np.float64], uturn: bool, beta: float
) -> float:
    """:func:`transition_logp` for one pair, compiled (for loops that route and score together).

    ``params`` comes from :func:`transition_params`; ``beta`` is the step's base β, ``params[0]``
    or more (the batch's grows with the step's time). With ``params[0]`` the result equals
    :func:`transition_logp`.
    """
    if not np.isfinite(route_dist):
        return -np.inf
    lp = _transition_one(route_dist, travelled, dt, beta, params[4], params[1], params[2])
    if uturn:
        lp -= params[3]
    return lp
