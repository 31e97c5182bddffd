"""The per-fix quantities and configuration the compiled placement kernels read, as one named
tuple built once per fix.

numba's on-disk cache keys a kernel by its argument types, not by the fields' names: after
changing :class:`PlaceParams`, delete the caches (``mapmatch/**/__pycache__/*.nb*``) or a
kernel compiled for the old layout may be loaded.
"""

from __future__ import annotations

from typing import NamedTuple

from mapmatch.config import MatchConfig
from mapmatch.online.state import Step


class PlaceParams(NamedTuple):
    """One fix's :class:`~mapmatch.online.state.Step` fields, the turn observed, and the
    configuration they are scored with (see the config fields of the same names)."""

    x: float
    y: float
    sigma: float
    heading: float
    kappa: float
    travelled: float
    odo: float
    odo_known: bool
    gps: bool
    stopped: bool
    bx: float  # the predicted fix bias and its covariance
    by: float
    pxx: float
    pxy: float
    pyy: float
    odo_sigma: float
    dr: float
    node_hold: float  # ``node_hold_sigmas`` · σ
    turn_obs: float  # the heading change observed over the last ``covered`` metres (nan: none)
    covered: float
    reach: float  # the region radius: how far behind its place a hypothesis may be found
    # configuration
    bias_emission: float
    bias_white_fraction: float
    straight_max_deg: float
    pos_sigma_floor: float
    beta: float
    beta_per_m: float
    turn_window: float
    turn_sigma: float


def _config_part(cfg: MatchConfig) -> tuple[float, ...]:
    """The configuration fields of :class:`PlaceParams`, in order."""
    m, o = cfg.model, cfg.online
    return tuple(
        float(v)
        for v in (
            o.bias.bias_emission,
            o.bias.bias_white_fraction,
            m.straight_max_deg,
            o.evidence.pos_sigma_floor,
            m.beta,
            m.beta_per_m,
            o.evidence.turn_window,
            o.evidence.turn_sigma,
        )
    )


_last: tuple[MatchConfig | None, tuple[float, ...]] = (None, ())  # the last configuration's part


def place_params(step: Step, cfg: MatchConfig, *, turn_obs: float, covered: float) -> PlaceParams:
    """The kernels' view of ``step`` under ``cfg`` (and the turn observed)."""
    return PlaceParams._make(param_values(step, cfg, turn_obs=turn_obs, covered=covered))


def param_values(
    step: Step, cfg: MatchConfig, *, turn_obs: float, covered: float
) -> tuple[float | bool, ...]:
    """:func:`place_params` as a plain tuple (in field order: the first values of the placement
    kernel's buffer, :func:`mapmatch.online.placement._params`)."""
    global _last
    last = _last
    if last[0] is not cfg:
        last = _last = (cfg, _config_part(cfg))
    o = cfg.online
    b = step.bias
    return (
        step.x,
        step.y,
        float(step.sigma),  # a fix's int field must not compile the kernels again
        float(step.heading),
        step.kappa,
        step.travelled,
        step.odo,
        step.odo_known,
        step.gps,
        step.stopped,
        float(b.bx),
        float(b.by),
        float(b.pxx),
        float(b.pxy),
        float(b.pyy),
        step.odo_sigma,
        step.dr,
        float(o.stop.node_hold_sigmas * step.sigma),
        float(turn_obs),
        float(covered),
        float(step.r_a),
        *last[1],
    )
