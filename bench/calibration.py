"""Calibration of a reported probability: reliability table, ECE, the usable gate, isotonic fit.

A probability is calibrated when answers reported at ``p`` are right a share ``p`` of the
time. The reliability table bins the fixes by reported ``p`` and gives, per bin, the fixes,
their mean ``p`` and the share of them that is right; the expected calibration error (ECE) is
the fix-weighted mean over the bins of ``|mean p - right share|``. The usable gate is scored
by the share of wrong answers among the fixes it lets through and the share of right answers
it lets through.

Isotonic regression (pool-adjacent-violators) maps a reported ``p`` to the right share of
fixes reported near it, under the one constraint that the map does not decrease. Fitted
out of fold (:func:`out_of_fold`), it is scored on fixes it has never seen.

    rows = reliability(p, right)             # list of Bin
    e = ece(p, right)
    e20 = ece_equal_mass(p, right)
    iso = isotonic_fit(p, right); q = isotonic_apply(iso, p)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

BINS = (0.0, 0.5, 0.7, 0.9, 0.99, 0.999, 1.0)
"""Edges of the reliability table's bins; each bin is ``[lo, hi)``, the last ``[lo, 1]``."""


@dataclass(frozen=True)
class Bin:
    """One row of a reliability table: fixes reported in ``[lo, hi)``."""

    lo: float
    hi: float
    fixes: int
    mean_p: float
    right_share: float


@dataclass(frozen=True)
class Isotonic:
    """A non-decreasing step map: ``value[k]`` for reported ``p`` from ``start[k]`` on."""

    start: NDArray[np.float64]
    value: NDArray[np.float64]


def _bin_index(p: NDArray[np.float64], edges: tuple[float, ...]) -> NDArray[np.intp]:
    inner = np.asarray(edges[1:-1], dtype=float)
    return np.searchsorted(inner, p, side="right")


def reliability(p: ArrayLike, right: ArrayLike, *, edges: tuple[float, ...] = BINS) -> list[Bin]:
    """The reliability table of probabilities ``p`` against outcomes ``right``.

    Parameters
    ----------
    p : reported probabilities in [0, 1].
    right : per fix, whether the answer was right (bool or 0/1).
    edges : the bins' edges, increasing, from 0 to 1.

    Returns
    -------
    list
        One :class:`Bin` per bin, empty bins included (their mean and share NaN).
    """
    pa = np.asarray(p, dtype=float)
    ra = np.asarray(right, dtype=float)
    k = _bin_index(pa, edges)
    out = []
    for b in range(len(edges) - 1):
        sel = k == b
        n = int(sel.sum())
        mp = float(pa[sel].mean()) if n else float("nan")
        rs = float(ra[sel].mean()) if n else float("nan")
        out.append(Bin(edges[b], edges[b + 1], n, mp, rs))
    return out


def ece(p: ArrayLike, right: ArrayLike, *, edges: tuple[float, ...] = BINS) -> float:
    """Expected calibration error: ``sum_b n_b / N * |mean p_b - right share_b|`` (0 when empty)."""
    rows = reliability(p, right, edges=edges)
    n = sum(r.fixes for r in rows)
    if n == 0:
        return 0.0
    return float(sum(r.fixes * abs(r.mean_p - r.right_share) for r in rows if r.fixes) / n)


def usable_shares(usable: ArrayLike, right: ArrayLike) -> tuple[float, float]:
    """(wrong share among the usable fixes, share of the right fixes that are usable); NaN
    where there is no usable or no right fix."""
    u = np.asarray(usable, dtype=bool)
    r = np.asarray(right, dtype=bool)
    wrong = float((u & ~r).sum() / u.sum()) if u.any() else float("nan")
    kept = float((u & r).sum() / r.sum()) if r.any() else float("nan")
    return wrong, kept


def isotonic_fit(p: ArrayLike, right: ArrayLike) -> Isotonic:
    """The non-decreasing step map of ``p`` that is closest to ``right`` in least squares
    (pool-adjacent-violators over the distinct values of ``p``).

    Parameters
    ----------
    p : reported probabilities (at least one).
    right : per fix, 0/1 or bool.

    Returns
    -------
    Isotonic
        Each block's smallest ``p`` and its value (the right share of its fixes).
    """
    pa = np.asarray(p, dtype=float)
    ux, inv = np.unique(pa, return_inverse=True)
    w = np.bincount(inv, minlength=len(ux)).astype(float)
    s = np.bincount(inv, weights=np.asarray(right, dtype=float), minlength=len(ux))
    starts: list[int] = []
    sums: list[float] = []
    weights: list[float] = []
    for i in range(len(ux)):  # a stack of blocks, merged while the means decrease
        starts.append(i)
        sums.append(float(s[i]))
        weights.append(float(w[i]))
        while len(sums) > 1 and sums[-2] * weights[-1] >= sums[-1] * weights[-2]:
            top_s, top_w = sums.pop(), weights.pop()
            sums[-1] += top_s
            weights[-1] += top_w
            starts.pop()
    value = np.asarray(sums) / np.asarray(weights)
    return Isotonic(start=ux[np.asarray(starts, dtype=np.intp)], value=value)


def isotonic_apply(iso: Isotonic, p: ArrayLike) -> NDArray[np.float64]:
    """The fitted map at ``p``: the value of the last block starting at or below ``p`` (the
    first block's value below its start)."""
    k = np.searchsorted(iso.start, np.asarray(p, dtype=float), side="right") - 1
    return iso.value[np.clip(k, 0, len(iso.value) - 1)]


def out_of_fold(p: ArrayLike, right: ArrayLike, fold: ArrayLike) -> NDArray[np.float64]:
    """Each fix's probability mapped by an isotonic fit on the fixes of the other folds."""
    pa = np.asarray(p, dtype=float)
    ra = np.asarray(right, dtype=float)
    fa = np.asarray(fold)
    out = np.full(len(pa), np.nan)
    for f in np.unique(fa):
        held = fa == f
        out[held] = isotonic_apply(isotonic_fit(pa[~held], ra[~held]), pa[held])
    return out


def logistic_fit(
    x: ArrayLike,
    right: ArrayLike,
    *,
    ridge: float = 1e-3,
    steps: int = 60,
    weight: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """The coefficients of a logistic model of ``right`` on the columns of ``x`` (the first
    a column of ones for the intercept), by Newton's method on the (weighted) log-likelihood
    with a ridge prior: ``ridge`` times the squared coefficients other than the intercept's
    (a light L2 prior; it also keeps the fit finite on separable data).

    Parameters
    ----------
    x : (N, K) features.
    right : per fix, 0/1 or bool.
    ridge : weight of the prior.
    steps : at most this many Newton steps.
    weight : per fix, its weight in the likelihood (default: 1 each).

    Returns
    -------
    ndarray
        K coefficients.
    """
    xa = np.asarray(x, dtype=float)
    y = np.asarray(right, dtype=float)
    w = np.ones(len(y)) if weight is None else np.asarray(weight, dtype=float)
    prior = ridge * np.eye(xa.shape[1])
    prior[0, 0] = 1e-9
    b = np.zeros(xa.shape[1])
    for _ in range(steps):
        mu = logistic_apply(b, xa)
        h = w * mu * (1.0 - mu) + 1e-12
        hess = xa.T @ (xa * h[:, None]) + prior
        step = np.linalg.solve(hess, xa.T @ (w * (y - mu)) - prior @ b)
        b += step
        if np.abs(step).max() < 1e-9:
            break
    return b


def logistic_apply(b: ArrayLike, x: ArrayLike) -> NDArray[np.float64]:
    """The logistic model's probability ``1 / (1 + exp(-x b))`` per row of ``x``."""
    z = np.asarray(x, dtype=float) @ np.asarray(b, dtype=float)
    return np.asarray(1.0 / (1.0 + np.exp(-np.clip(z, -700.0, 700.0))))


def logistic_out_of_fold(
    x: ArrayLike,
    right: ArrayLike,
    fold: ArrayLike,
    *,
    ridge: float = 1e-3,
    weight: ArrayLike | None = None,
) -> tuple[NDArray[np.float64], dict[int, NDArray[np.float64]]]:
    """Each fix's probability from a logistic fit on the fixes of the other folds, and each
    fold's coefficients (the fit's ``ridge`` and ``weight`` as in :func:`logistic_fit`)."""
    xa = np.asarray(x, dtype=float)
    ra = np.asarray(right, dtype=float)
    fa = np.asarray(fold)
    wa = np.ones(len(ra)) if weight is None else np.asarray(weight, dtype=float)
    out = np.full(len(ra), np.nan)
    coefs: dict[int, NDArray[np.float64]] = {}
    for f in np.unique(fa).tolist():
        held = fa == f
        coefs[int(f)] = logistic_fit(xa[~held], ra[~held], ridge=ridge, weight=wa[~held])
        out[held] = logistic_apply(coefs[int(f)], xa[held])
    return out, coefs


def log_loss(p: ArrayLike, right: ArrayLike, *, weight: ArrayLike | None = None) -> float:
    """The (weighted) mean negative log-likelihood of outcomes ``right`` under ``p``."""
    q = np.clip(np.asarray(p, dtype=float), 1e-12, 1.0 - 1e-12)
    y = np.asarray(right, dtype=float)
    w = np.ones(len(y)) if weight is None else np.asarray(weight, dtype=float)
    return float(-np.sum(w * (y * np.log(q) + (1.0 - y) * np.log1p(-q))) / w.sum())


def ece_equal_mass(p: ArrayLike, right: ArrayLike, *, bins: int = 20) -> float:
    """The ECE over ``bins`` bins of equal numbers of fixes (sorted by ``p``): no bin is
    nearly empty, so it is not dominated by a few fixes in a sparse bin (0 when empty)."""
    pa = np.asarray(p, dtype=float)
    ra = np.asarray(right, dtype=float)
    if len(pa) == 0:
        return 0.0
    parts = np.array_split(np.argsort(pa, kind="stable"), min(bins, len(pa)))
    return float(sum(len(k) * abs(pa[k].mean() - ra[k].mean()) for k in parts) / len(pa))


def right_usable_at(q: ArrayLike, right: ArrayLike, gate: ArrayLike, *, wrong_share: float) -> float:
    """The largest share of right fixes a single threshold on ``q`` marks usable (among the
    fixes whose ``gate`` is true) with at most ``wrong_share`` of wrong fixes among the
    usable ones: one point of the trade-off curve (0 when no threshold meets it)."""
    qa = np.asarray(q, dtype=float)
    ra = np.asarray(right, dtype=bool)
    ga = np.asarray(gate, dtype=bool)
    order = np.argsort(-np.where(ga, qa, -np.inf), kind="stable")
    rr, gg = ra[order], ga[order]
    kept = np.cumsum(rr & gg)
    wrong = np.cumsum(~rr & gg)
    n = np.arange(1, len(rr) + 1)
    # a threshold falls between distinct values only
    qs = np.where(ga, qa, -np.inf)[order]
    edge = np.r_[qs[1:] != qs[:-1], True]
    ok = gg & edge & (wrong <= wrong_share * n)
    if not ok.any() or not ra.any():
        return 0.0
    return float(kept[ok].max() / ra.sum())
