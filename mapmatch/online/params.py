"""The per-fix quantities and configuration the compiled placement kernels read, as one named
tuple built once per fix."""

from __future__ import annotations

from typing import NamedTuple

from mapmatch.config import MatchConfig
from mapmatch.online.state import Step


class PlaceParams(NamedTuple):
    """One fix's :class:`~mapmatch.online.state.Step` fields and the configuration they are
    scored with (see the config fields of the same names)."""

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
    speed_dt: float  # the step's dt, at least ``speed_time``: the transition's speed judged over it
    node_hold: float  # ``node_hold_sigmas`` · σ
    bias_emission: float
    bias_white_fraction: float
    anchor_gate: float
    straight_max_deg: float
    pos_sigma_floor: float
    beta: float
    max_speed: float
    speed_penalty: float
    turn_obs: float  # the heading change observed over the last ``covered`` metres (nan: none)
    covered: float
    turn_window: float
    turn_sigma: float


def place_params(step: Step, cfg: MatchConfig, *, turn_obs: float, covered: float) -> PlaceParams:
    """The kernels' view of ``step`` under ``cfg`` (and the turn observed)."""
    m, o = cfg.model, cfg.online
    b = step.bias
    return PlaceParams(
        step.x,
        step.y,
        step.sigma,
        step.heading,
        step.kappa,
        step.travelled,
        step.odo,
        step.odo_known,
        step.gps,
        step.stopped,
        b.bx,
        b.by,
        b.pxx,
        b.pxy,
        b.pyy,
        step.odo_sigma,
        step.dr,
        float(max(step.dt, o.speed_time)),
        float(o.node_hold_sigmas * step.sigma),
        float(o.bias_emission),
        float(o.bias_white_fraction),
        float(o.anchor_gate),
        float(m.straight_max_deg),
        float(o.pos_sigma_floor),
        float(m.beta),
        float(m.max_speed),
        float(m.speed_penalty),
        float(turn_obs),
        float(covered),
        float(o.turn_window),
        float(o.turn_sigma),
    )
