"""The generic Viterbi search (:mod:`mapmatch.viterbi`) on toy lattices: a hand-computed best
path, ties, an unreachable column, ``-inf`` emissions and transitions, and every path of small
random lattices enumerated."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from mapmatch.viterbi import backtrack, relax, viterbi_dense

NEG = -np.inf


def _lattice(emis_cols: list[list[float]], blocks: list[list[list[float]]]):  # type: ignore[no-untyped-def]
    """``ptr``, ``emis`` and the dense ``logp`` of columns given as lists (``blocks[t - 1]``:
    rows the states of column ``t``, columns those of ``t - 1``)."""
    ptr = np.cumsum([0] + [len(c) for c in emis_cols]).astype(np.int64)
    emis = np.array([e for c in emis_cols for e in c], dtype=np.float64)
    kmax = max(len(c) for c in emis_cols)
    logp = np.full((len(emis), kmax), NEG)
    for t, block in enumerate(blocks, start=1):
        for r, row in enumerate(block):
            logp[ptr[t] + r, : len(row)] = row
    return ptr, emis, logp


def _solve(emis_cols, blocks):  # type: ignore[no-untyped-def]
    choice, starts = viterbi_dense(*_lattice(emis_cols, blocks))
    return choice.tolist(), starts.tolist()


def test_the_best_path_is_the_hand_computed_one_not_the_greedy_one() -> None:
    # column 1: state 2 = max(-1 - 1, -2 - 0.5) - 1 = -3 from 0; state 3 = max(-1 - 2, -2 - 0.1)
    # - 0.5 = -2.6 from 1. Column 2: state 4 = max(-3 - 0.2, -2.6 - 5) - 3 = -6.2 from 2;
    # state 5 = -2.6 - 1 - 1 = -4.6 from 3 (state 2 has no transition to it). Best: 1, 3, 5,
    # though state 0 has the better emission in column 0.
    emis = [[-1.0, -2.0], [-1.0, -0.5], [-3.0, -1.0]]
    blocks = [[[-1.0, -0.5], [-2.0, -0.1]], [[-0.2, -5.0], [NEG, -1.0]]]
    assert _solve(emis, blocks) == ([1, 3, 5], [True, False, False])


def test_equal_scores_go_to_the_higher_scored_source_then_the_lower_state() -> None:
    # equal sources, equal transitions: the lower state
    assert _solve([[-1.0, -1.0], [0.0]], [[[-1.0, -1.0]]])[0] == [0, 2]
    # state 0 (-2, then -1) and state 1 (-1, then -2) both give -3: the higher-scored source wins
    assert _solve([[-2.0, -1.0], [0.0]], [[[-1.0, -2.0]]])[0] == [1, 2]


def test_a_column_no_state_reaches_starts_a_new_piece() -> None:
    emis = [[-1.0, -0.5], [-2.0, -0.1], [-0.3]]
    blocks = [[[NEG, NEG], [NEG, NEG]], [[-1.0, -4.0]]]
    choice, starts = _solve(emis, blocks)
    # column 0 alone: its best emission; column 1 starts again and its state 3 wins
    # (-0.1 - 4 = -4.1 against -2 - 1 = -3: state 2)
    assert starts == [True, True, False]
    assert choice == [1, 2, 4]


def test_minus_inf_emissions_and_transitions_are_never_chosen() -> None:
    emis = [[NEG, -5.0], [-0.1, NEG]]
    blocks = [[[NEG, -3.0], [0.0, 0.0]]]
    assert _solve(emis, blocks) == ([1, 2], [True, False])
    best = np.array([NEG])
    bp = np.array([-1], dtype=np.int64)
    assert not relax(best, bp, 0, 0, 7, NEG)  # -inf reaches nothing
    assert bp[0] == -1
    assert relax(best, bp, 0, 0, 7, -1e300) and bp[0] == 7
    assert not relax(best, bp, 0, 0, 8, -1e300)  # a tie keeps the first


def test_backtrack_follows_skipped_columns_to_the_piece_start() -> None:
    bp = np.array([-1, -1, 0, -1, 2, 4], dtype=np.int64)  # 5 <- 4 <- 2
    prev_col = np.array([-1, 0, 0, -1, 2], dtype=np.int64)  # column 3 is skipped by column 4
    starts = np.array([True, False, False, False, False])
    choice = np.full(5, -1, dtype=np.int64)
    assert backtrack(bp, prev_col, starts, 4, 5, choice) == 0
    assert choice.tolist() == [2, -1, 4, -1, 5]


@pytest.mark.parametrize("seed", range(20))
def test_the_best_path_scores_what_enumerating_every_path_finds(seed: int) -> None:
    rng = np.random.default_rng(seed)
    sizes = rng.integers(1, 4, size=int(rng.integers(2, 6)))
    emis = [list(-rng.exponential(size=k)) for k in sizes]
    blocks = [
        [list(-rng.exponential(size=sizes[t - 1])) for _ in range(sizes[t])] for t in range(1, len(sizes))
    ]
    ptr, e, logp = _lattice(emis, blocks)
    choice, starts = viterbi_dense(ptr, e, logp)
    assert starts.tolist() == [True] + [False] * (len(sizes) - 1)

    def total(path: tuple[int, ...]) -> float:
        s = e[path[0]]
        for t in range(1, len(path)):
            s += logp[path[t], path[t - 1] - ptr[t - 1]] + e[path[t]]
        return float(s)

    paths = itertools.product(*(range(ptr[t], ptr[t + 1]) for t in range(len(sizes))))
    assert total(tuple(choice.tolist())) == pytest.approx(max(total(p) for p in paths), abs=1e-12)
    # the same code run as plain Python gives the same answer
    py_choice, _ = viterbi_dense.py_func(ptr, e, logp)
    assert py_choice.tolist() == choice.tolist()
