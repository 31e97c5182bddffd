"""Fitting the online matcher's confidence model and its usable threshold, in and out of fold.

The per-fix table of ``bench_online_real.py --calibration`` (one replay of the drives) holds,
per fix, what the matcher knows when it answers and whether the answer is right; everything
here works on that table, so a fit, a threshold or a term left out costs no replay.

* **Features** (:func:`features`): the terms of :data:`TERMS`, as
  :func:`mapmatch.measurement.confidence` computes them, with the configured caps.
* **Fit**: a logistic model by maximum likelihood with a light L2 prior on the coefficients
  other than the intercept, its weight chosen from :data:`RIDGES` by the out-of-fold
  log-loss (:func:`choose_ridge`). Pooled over rates, a fix weighs ``1 / rate`` (each second
  of driving counts once at every rate).
* **Threshold** (``measurement.min_probability``): the least of :data:`THRESHOLDS` whose wrong
  share among usable fixes is at most :data:`WRONG_USABLE_TARGET` at every rate, judged on
  *out-of-fold* probabilities (:func:`oof_threshold`): a threshold chosen on the fixes a model
  was fitted on lets through more wrong answers on tracks it has not seen.
* **Out of fold**: the model and the threshold are chosen on four folds (the threshold on the
  four folds' own out-of-fold probabilities) and applied to the fifth.

    fit = fit_model(df, cfg, pooled=True)     # ModelFit: probabilities, usable flags, text
"""

from __future__ import annotations

from dataclasses import dataclass, field

import calibration
import numpy as np
import pandas as pd

from mapmatch.config import DEFAULT_CONFIG, ConfidenceConfig, MatchConfig

TERMS = ("intercept", "log_odds", "heading", "parallel", "parallel_gap")
"""The terms of the matcher's confidence model: ``confidence.coef_<term>``."""
IDENTITY = tuple(f"confidence.coef_{t}={1 if t == 'log_odds' else 0}" for t in TERMS)
"""The confidence model switched off: the matcher reports the road's probability itself."""
RIDGES = (1e-3, 1.0, 10.0, 100.0, 1000.0)
"""The weights of the L2 prior :func:`choose_ridge` tries."""
WRONG_USABLE_TARGET = 0.001
"""The wrong share among usable fixes ``measurement.min_probability`` is chosen for (issue
#48's target)."""
THRESHOLDS = np.round(np.arange(0.9, 0.9995, 0.0005), 4)
"""The thresholds :func:`choose_threshold` tries."""
WRONG_SHARES = (0.0005, 0.001, 0.0015, 0.002, 0.003)
"""The wrong shares among usable fixes of the trade-off curve (:func:`trade_off`)."""


def features(g: pd.DataFrame, model: ConfidenceConfig = DEFAULT_CONFIG.confidence) -> np.ndarray:
    """The model's features per fix, in the order of :data:`TERMS`, as
    :func:`mapmatch.measurement.confidence` takes them with ``model``'s caps: 1, the road
    probability's log-odds, the heading disagreement per 10° (at most ``heading_cap``, 0
    without a heading), whether a road runs alongside and by how many σ it is nearer to the
    fix (``gap_cap`` less the gap in σ, the gap within ±``gap_cap``; 0 without one)."""
    m = model
    p = np.clip(g["p"].to_numpy(dtype=float), m.probability_floor, 1.0 - m.probability_floor)
    head = np.minimum(np.nan_to_num(g["head_diff"].to_numpy(dtype=float)), m.heading_cap) * 0.1
    cross = g["cross_sig"].to_numpy(dtype=float)
    other = g["other_sig"].to_numpy(dtype=float)
    beside = np.isfinite(other)
    near = np.clip(np.where(beside, other, 0.0) - cross, -m.gap_cap, m.gap_cap)
    gap = np.where(beside, m.gap_cap - near, 0.0)
    return np.column_stack([np.ones(len(p)), np.log(p / (1.0 - p)), head, beside, gap])


def configured(cfg: MatchConfig) -> np.ndarray:
    """The confidence model's coefficients in ``cfg``, in the order of :data:`TERMS`."""
    m = cfg.confidence
    return np.array([getattr(m, f"coef_{t}") for t in TERMS], dtype=float)


def weights(g: pd.DataFrame, *, pooled: bool) -> np.ndarray:
    """Each fix's weight in a fit: ``1 / rate`` pooled over rates (a second of driving counts
    once at every rate), else 1."""
    return 1.0 / g["hz"].to_numpy(dtype=float) if pooled else np.ones(len(g))


def gate(g: pd.DataFrame, q: np.ndarray, min_probability: float) -> np.ndarray:
    """The matcher's usable test with probability ``q`` and threshold ``min_probability``."""
    return g["gate"].to_numpy(dtype=bool) & (q >= min_probability)


def choose_threshold(g: pd.DataFrame, q: np.ndarray, *, target: float = WRONG_USABLE_TARGET) -> float:
    """The least threshold of :data:`THRESHOLDS` whose wrong share among the usable fixes of
    ``g`` (probability ``q``) is at most ``target`` at each rate of ``g`` (the largest if none is)."""
    right = g["right"].to_numpy(dtype=bool)
    rates = [g["hz"].to_numpy() == h for h in np.unique(g["hz"].to_numpy())]
    for t in THRESHOLDS.tolist():
        u = gate(g, q, t)
        if all(calibration.usable_shares(u[s], right[s])[0] <= target for s in rates):
            return float(t)
    return float(THRESHOLDS[-1])


def choose_ridge(x: np.ndarray, right: np.ndarray, fold: np.ndarray, w: np.ndarray) -> float:
    """The weight of :data:`RIDGES` whose out-of-fold log-loss is least (the smaller on a tie)."""
    loss = []
    for ridge in RIDGES:
        q, _ = calibration.logistic_out_of_fold(x, right, fold, ridge=ridge, weight=w)
        loss.append(round(calibration.log_loss(q, right, weight=w), 6))
    return float(RIDGES[int(np.argmin(loss))])


def oof_threshold(g: pd.DataFrame, x: np.ndarray, w: np.ndarray, *, ridge: float) -> float:
    """The threshold chosen on out-of-fold probabilities over the folds of ``g``."""
    right = g["right"].to_numpy(dtype=bool)
    q, _ = calibration.logistic_out_of_fold(x, right, g["fold"].to_numpy(), ridge=ridge, weight=w)
    return choose_threshold(g, q)


@dataclass
class ModelFit:
    """The model fitted to a table: in-sample and out-of-fold probabilities and usable flags
    per fix, the prior's weight, and the coefficients and thresholds of each fit (as rows:
    name, coefficients, threshold)."""

    ridge: float
    q_in: np.ndarray
    u_in: np.ndarray
    q_oof: np.ndarray
    u_oof: np.ndarray
    coef: np.ndarray
    threshold: float
    rows: list[tuple[str, np.ndarray, float]] = field(default_factory=list)


def fit_model(g: pd.DataFrame, cfg: MatchConfig, *, pooled: bool, ridge: float | None = None) -> ModelFit:
    """Fit the model and its threshold on all of ``g`` (the recommended coefficients and
    ``measurement.min_probability``: the threshold judged out of fold) and, per fold, on the
    others, applied to it (see the module docstring); ``ridge`` None: chosen by
    :func:`choose_ridge`."""
    x = features(g, cfg.confidence)
    right = g["right"].to_numpy(dtype=bool)
    fold = g["fold"].to_numpy()
    w = weights(g, pooled=pooled)
    lam = choose_ridge(x, right, fold, w) if ridge is None else ridge
    b = calibration.logistic_fit(x, right, ridge=lam, weight=w)
    q_in = calibration.logistic_apply(b, x)
    q_oof, coefs = calibration.logistic_out_of_fold(x, right, fold, ridge=lam, weight=w)
    t_all = choose_threshold(g, q_oof)
    u_oof = np.zeros(len(g), dtype=bool)
    rows = [("all tracks", b, t_all)]
    for f, bf in coefs.items():
        held = fold == f
        t = oof_threshold(g[~held], x[~held], w[~held], ridge=lam)
        u_oof[held] = gate(g[held], q_oof[held], t)
        rows.append((f"without fold {f}", bf, t))
    return ModelFit(lam, q_in, gate(g, q_in, choose_threshold(g, q_in)), q_oof, u_oof, b, t_all, rows)


def coefficient_table(fit: ModelFit) -> str:
    """The coefficients and thresholds of each fit, as a markdown table."""
    lines = [f"| fit | {' | '.join(TERMS)} | threshold |", "|---|" + "---|" * (len(TERMS) + 1)]
    for name, b, t in fit.rows:
        lines.append(f"| {name} | " + " | ".join(f"{v:.3f}" for v in b) + f" | {t:.4f} |")
    return "\n".join(lines)


def trade_off(q: np.ndarray, g: pd.DataFrame) -> list[float]:
    """The share of right fixes usable at each wrong share of :data:`WRONG_SHARES` (one
    threshold on ``q`` per point, the best for those fixes: a curve, not a choice)."""
    right = g["right"].to_numpy(dtype=bool)
    ok = g["gate"].to_numpy(dtype=bool)
    return [calibration.right_usable_at(q, right, ok, wrong_share=s) for s in WRONG_SHARES]


def without_each_term(
    g: pd.DataFrame, cfg: MatchConfig, *, pooled: bool, ridge: float
) -> list[dict[str, object]]:
    """Out of fold, the model with all terms and with each term but the intercept left out:
    per rate, the wrong share among usable fixes, the right share usable (thresholds chosen
    on out-of-fold probabilities of the training folds), the ECE and the log-loss."""
    x_all = features(g, cfg.confidence)
    right = g["right"].to_numpy(dtype=bool)
    fold = g["fold"].to_numpy()
    w = weights(g, pooled=pooled)
    out: list[dict[str, object]] = []
    for k in [None, *range(1, len(TERMS))]:
        x = x_all if k is None else np.delete(x_all, k, axis=1)
        q, _ = calibration.logistic_out_of_fold(x, right, fold, ridge=ridge, weight=w)
        u = np.zeros(len(g), dtype=bool)
        for f in np.unique(fold).tolist():
            held = fold == f
            u[held] = gate(g[held], q[held], oof_threshold(g[~held], x[~held], w[~held], ridge=ridge))
        for hz in np.unique(g["hz"].to_numpy()).tolist():
            s = g["hz"].to_numpy() == hz
            wrong, kept = calibration.usable_shares(u[s], right[s])
            out.append(
                {
                    "model": "all terms" if k is None else f"without {TERMS[k]}",
                    "hz": hz,
                    "wrong_usable": wrong,
                    "right_usable": kept,
                    "ece": calibration.ece(q[s], right[s]),
                    "log_loss": calibration.log_loss(q[s], right[s]),
                }
            )
    return out
