"""The fix's slowly varying error: its bias vector learnt across roads, the road residuals
(real position and heading σ) and the dead-reckoning drift σ."""

from __future__ import annotations

import math

from graph.angles import angle_diff
from mapmatch.config import MatchConfig
from mapmatch.online.state import BiasState, FixBias, Hypothesis, Step


def drift_sigma(b: BiasState, gps: bool, dr: float, dt: float, cfg: MatchConfig) -> float:
    """σ of the dead-reckoning drift: grows with the distance ``dr`` since the last GPS-aided
    fix and decays over ``drift_decay_time`` once GPS is back (the fusion filter needs time to
    converge)."""
    if not gps:
        return max(b.drift_sigma, cfg.model.gps_sigma + cfg.online.bias.dr_sigma_growth * dr)
    if b.drift_sigma <= 0.0 or math.isnan(dt):
        return 0.0
    return b.drift_sigma * math.exp(-dt / cfg.online.bias.drift_decay_time)


def take(b: BiasState, step: Step, cfg: MatchConfig) -> None:
    """The fix is accepted: its predicted bias and its drift σ are the state's."""
    b.drift_sigma = drift_sigma(b, True, 0.0, step.dt, cfg) if step.gps else step.sigma
    b.vector = step.bias


def predict_bias(b: FixBias, sigma: float, dt: float, cfg: MatchConfig) -> FixBias:
    """The fix bias a step on: it decays towards zero, its covariance towards σ²."""
    bx, by, pxx, pxy, pyy = b
    if cfg.online.bias.bias_time <= 0.0 or math.isnan(pxx) or math.isnan(dt):
        return FixBias(0.0, 0.0, sigma * sigma, 0.0, sigma * sigma)
    a = math.exp(-dt / cfg.online.bias.bias_time)
    q = sigma * sigma * (1.0 - a * a)
    return FixBias(a * bx, a * by, a * a * pxx + q, a * a * pxy, a * a * pyy + q)


def learn_bias(b: BiasState, best: Hypothesis, step: Step, cfg: MatchConfig) -> None:
    """Kalman update of the fix bias with its offset across the road (a 1-D view of it)."""
    if step.weight <= 0.0 or math.isnan(best.bearing) or not step.gps:
        return
    bx, by, pxx, pxy, pyy = b.vector
    rad = math.radians(best.bearing)
    nx, ny = math.cos(rad), -math.sin(rad)  # normal to the road (bearing clockwise from north)
    z = (step.x - best.px) * nx + (step.y - best.py) * ny
    pnx, pny = pxx * nx + pxy * ny, pxy * nx + pyy * ny
    r = (cfg.online.bias.bias_white_fraction * step.sigma) ** 2 / step.weight
    sv = nx * pnx + ny * pny + r
    nu = z - (bx * nx + by * ny)
    lim = 3.0 * math.sqrt(sv)
    nu = min(max(nu, -lim), lim)  # robust: a wrong road must not teach a large bias
    kx, ky = pnx / sv, pny / sv
    b.vector = FixBias(bx + kx * nu, by + ky * nu, pxx - kx * pnx, pxy - kx * pny, pyy - ky * pny)


def learn_residuals(b: BiasState, best: Hypothesis, step: Step, cfg: MatchConfig) -> None:
    """Running estimate of the real position and heading error, from on-road fixes."""
    o = cfg.online
    a = 1.0 if math.isnan(step.dt) else min(1.0, step.dt / o.bias.residual_time)
    # clipped (robust) and bounded, so that a wrong road cannot teach a large σ
    if step.gps:
        d = min(best.dist, 2.5 * math.sqrt(b.res_pos2))
        b.res_pos2 = min(b.res_pos2 + a * (d * d - b.res_pos2), o.bias.learned_pos_sigma_max**2)
    if step.kappa > 0.0:
        dh = min(abs(angle_diff(step.heading, best.bearing)), 2.5 * math.sqrt(b.res_head2))
        b.res_head2 = min(b.res_head2 + a * (dh * dh - b.res_head2), o.bias.learned_heading_sigma_max_deg**2)
