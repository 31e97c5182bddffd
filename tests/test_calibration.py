"""The calibration figures of the online bench (bench/calibration.py): reliability table, ECE,
the usable gate's shares, and the isotonic fit in sample and out of fold, on tiny arrays whose
answers are worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
from bench_modules import bench_module

cal = bench_module("calibration")

P = [0.1, 0.3, 0.6, 0.95, 0.95, 1.0]
RIGHT = [0, 1, 1, 1, 0, 1]


def test_reliability_bins_fixes_mean_and_right_share() -> None:
    rows = cal.reliability(P, RIGHT)
    assert [(r.lo, r.hi) for r in rows] == list(zip(cal.BINS[:-1], cal.BINS[1:], strict=True))
    assert [r.fixes for r in rows] == [2, 1, 0, 2, 0, 1]
    full = [r for r in rows if r.fixes]
    assert [r.mean_p for r in full] == pytest.approx([0.2, 0.6, 0.95, 1.0])
    assert [r.right_share for r in full] == pytest.approx([0.5, 1.0, 0.5, 1.0])
    assert all(math.isnan(r.mean_p) and math.isnan(r.right_share) for r in rows if not r.fixes)


def test_bin_edges_are_closed_below_and_the_last_bin_holds_one() -> None:
    rows = cal.reliability([0.5, 0.999, 1.0, 0.49], [1, 1, 1, 1])
    assert [r.fixes for r in rows] == [1, 1, 0, 0, 0, 2]


def test_ece_is_the_fix_weighted_gap() -> None:
    # bins: 2 fixes |0.2 - 0.5|, 1 fix |0.6 - 1|, 2 fixes |0.95 - 0.5|, 1 fix |1 - 1|
    assert cal.ece(P, RIGHT) == pytest.approx((2 * 0.3 + 0.4 + 2 * 0.45) / 6)
    assert cal.ece([], []) == 0.0
    assert cal.ece([0.75, 0.75, 0.75, 0.75], [1, 1, 1, 0]) == pytest.approx(0.0)


def test_usable_shares() -> None:
    wrong, kept = cal.usable_shares([1, 1, 0, 1], [1, 0, 1, 1])
    assert wrong == pytest.approx(1 / 3)  # one of three usable fixes is wrong
    assert kept == pytest.approx(2 / 3)  # two of three right fixes are usable
    wrong, kept = cal.usable_shares([0, 0], [0, 0])
    assert math.isnan(wrong) and math.isnan(kept)


def test_isotonic_pools_adjacent_violators() -> None:
    iso = cal.isotonic_fit([0.1, 0.2, 0.3, 0.4], [1, 0, 0, 1])
    assert iso.start.tolist() == [0.1, 0.4]
    assert iso.value.tolist() == pytest.approx([1 / 3, 1.0])
    got = cal.isotonic_apply(iso, [0.05, 0.25, 0.4, 0.9])
    assert got.tolist() == pytest.approx([1 / 3, 1 / 3, 1.0, 1.0])


def test_isotonic_groups_equal_probabilities_and_is_monotone() -> None:
    iso = cal.isotonic_fit([0.9, 0.5, 0.5], [1, 1, 0])
    assert iso.start.tolist() == [0.5, 0.9]
    assert iso.value.tolist() == pytest.approx([0.5, 1.0])
    rng = np.random.default_rng(1)
    p = rng.random(500)
    y = rng.random(500) < p
    q = cal.isotonic_apply(cal.isotonic_fit(p, y), np.sort(p))
    assert np.all(np.diff(q) >= 0)
    assert q.mean() == pytest.approx(y.mean())  # the fit keeps the overall right share


def test_out_of_fold_never_sees_the_held_fold() -> None:
    # fold 0 is mapped by a fit on fold 1 (both right: 1, 1) and fold 1 by a fit on fold 0
    q = cal.out_of_fold([0.2, 0.8, 0.2, 0.8], [0, 1, 1, 1], [0, 0, 1, 1])
    assert q.tolist() == pytest.approx([1.0, 1.0, 0.0, 1.0])


def test_logistic_fit_recovers_the_coefficients_that_drew_the_outcomes() -> None:
    rng = np.random.default_rng(3)
    n = 20000
    x = np.column_stack([np.ones(n), rng.normal(size=n), rng.integers(0, 2, size=n)])
    truth = np.array([2.0, 1.5, -2.5])
    right = rng.random(n) < cal.logistic_apply(truth, x)
    b = cal.logistic_fit(x, right)
    assert b == pytest.approx(truth, abs=0.15)
    q = cal.logistic_apply(b, x)
    assert cal.ece(q, right) < 0.01


def test_logistic_out_of_fold_fits_each_fold_without_it() -> None:
    rng = np.random.default_rng(4)
    n = 3000
    x = np.column_stack([np.ones(n), rng.normal(size=n)])
    right = rng.random(n) < cal.logistic_apply([1.0, 2.0], x)
    fold = np.arange(n) % 3
    q, coefs = cal.logistic_out_of_fold(x, right, fold)
    assert sorted(coefs) == [0, 1, 2] and not np.isnan(q).any()
    held = fold == 1
    assert q[held] == pytest.approx(cal.logistic_apply(cal.logistic_fit(x[~held], right[~held]), x[held]))


def test_the_prior_shrinks_the_slopes_but_not_the_intercept() -> None:
    rng = np.random.default_rng(5)
    n = 4000
    x = np.column_stack([np.ones(n), rng.normal(size=n)])
    right = rng.random(n) < cal.logistic_apply([3.0, 1.0], x)
    light = cal.logistic_fit(x, right)
    heavy = cal.logistic_fit(x, right, ridge=1e6)
    assert abs(heavy[1]) < 0.01 < abs(light[1])
    # with the slope held near 0 the intercept is the log-odds of the right share
    share = right.mean()
    assert heavy[0] == pytest.approx(math.log(share / (1.0 - share)), abs=0.02)


def test_a_weighted_fit_counts_a_fix_of_weight_two_as_two_fixes() -> None:
    rng = np.random.default_rng(6)
    n = 500
    x = np.column_stack([np.ones(n), rng.normal(size=n)])
    right = rng.random(n) < cal.logistic_apply([0.5, 1.0], x)
    twice = cal.logistic_fit(np.vstack([x, x[:100]]), np.r_[right, right[:100]])
    w = np.r_[np.full(100, 2.0), np.ones(n - 100)]
    assert cal.logistic_fit(x, right, weight=w) == pytest.approx(twice, abs=1e-6)


def test_log_loss_and_equal_mass_ece_by_hand() -> None:
    assert cal.log_loss([0.5, 0.5], [1, 0]) == pytest.approx(math.log(2.0))
    assert cal.log_loss([0.9, 0.2], [1, 0], weight=[3.0, 1.0]) == pytest.approx(
        -(3 * math.log(0.9) + math.log(0.8)) / 4
    )
    # two bins of two fixes: (0.1, 0.3) against 0 and 1 right; (0.9, 0.9) against both right
    assert cal.ece_equal_mass([0.9, 0.1, 0.9, 0.3], [1, 0, 1, 1], bins=2) == pytest.approx(
        (2 * abs(0.2 - 0.5) + 2 * abs(0.9 - 1.0)) / 4
    )
    assert cal.ece_equal_mass([], []) == 0.0


def test_right_usable_at_a_wrong_share_takes_the_best_single_threshold() -> None:
    q = [0.99, 0.98, 0.97, 0.96, 0.95, 0.5]
    right = [1, 1, 0, 1, 0, 1]
    ok = [True] * 6
    # at most 0 wrong: the two at the top (2 of 4 right); at most 1 in 4: down to 0.96 (3 of 4;
    # lower, 2 wrong in 5 and in 6 are too many)
    assert cal.right_usable_at(q, right, ok, wrong_share=0.0) == pytest.approx(2 / 4)
    assert cal.right_usable_at(q, right, ok, wrong_share=0.25) == pytest.approx(3 / 4)
    # a fix the gate refuses is never usable, whatever its probability
    assert cal.right_usable_at(q, right, [False] + [True] * 5, wrong_share=0.0) == pytest.approx(1 / 4)
    # ties are one threshold: both at 0.9 or neither
    assert cal.right_usable_at([0.9, 0.9], [1, 0], [True, True], wrong_share=0.0) == 0.0
