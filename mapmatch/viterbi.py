"""The Viterbi search over a lattice of columns, knowing nothing of roads (compiled).

A lattice is a sequence of columns (a track's points), each with its states (candidates) and
their emission log-probabilities; states are numbered across the whole lattice, column ``t``
holding ``ptr[t]:ptr[t + 1]``. A column's predecessor column need not be the one before it
(a caller may skip columns), and a column may start a new piece (no predecessor).

The search is three operations, each compiled into its caller:

- :func:`start_column`: a column that starts a piece scores its emissions;
- the relaxation, for one step from a source column to a target column:
  :func:`open_column` clears the targets' best scores, :func:`sources_best_first` orders the
  sources, :func:`relax` offers one source's score plus one transition log-probability to a
  target (the transition comes from the caller: a dense block, or a cost provider such as the
  batch matcher's routing, :mod:`mapmatch.batch.step`), and :func:`close_column` adds the
  emissions and says whether any target was reached;
- :func:`backtrack`: from a piece's last column and chosen state, the state chosen at each of
  its columns.

Ties go to the source offered first (:func:`relax` keeps a score only when it is strictly
higher), so with :func:`sources_best_first` to the higher-scored source, then the lower state
number. A log-probability of ``-inf`` is no transition; a target no source reaches keeps
``-inf`` and no back-pointer. :func:`viterbi_dense` is the whole search over dense transition
blocks, the reference the unit tests hold the operations to.
"""

from __future__ import annotations

import numpy as np

from graph.jit import njit


@njit(cache=True, nogil=True, inline="always")
def start_column(score, emis, a, b):  # type: ignore[no-untyped-def]
    """States ``a:b`` start a piece: each scores its emission (their back-pointers are not read:
    :func:`backtrack` stops at a piece's first column)."""
    for j in range(a, b):
        score[j] = emis[j]


@njit(cache=True, nogil=True, inline="always")
def open_column(best, bp, b0, b1):  # type: ignore[no-untyped-def]
    """Before a step into states ``b0:b1``: no target reached yet (``best``, indexed from ``b0``,
    ``-inf``; back-pointers -1)."""
    for j in range(b1 - b0):
        best[j] = -np.inf
        bp[b0 + j] = -1


@njit(cache=True, nogil=True, inline="always")
def sources_best_first(score, a0, a1, order):  # type: ignore[no-untyped-def]
    """The source states ``a0:a1`` into ``order[:a1 - a0]``, highest score first, equal scores
    in state order (an insertion sort: a column holds a few states)."""
    for i in range(a1 - a0):
        order[i] = a0 + i
    for i in range(1, a1 - a0):
        x = order[i]
        q = i - 1
        while q >= 0 and score[order[q]] < score[x]:
            order[q + 1] = order[q]
            q -= 1
        order[q + 1] = x


@njit(cache=True, nogil=True, inline="always")
def worst_target(best, kb):  # type: ignore[no-untyped-def]
    """The lowest best score of the ``kb`` targets: a source scoring no more than it, with every
    transition log-probability <= 0, improves no target."""
    worst = np.inf
    for j in range(kb):
        worst = min(worst, best[j])
    return worst


@njit(cache=True, nogil=True, inline="always")
def relax(best, bp, b0, j, i, s):  # type: ignore[no-untyped-def]
    """Offer target state ``j`` (of a column starting at ``b0``) the score ``s`` through source
    state ``i``: kept, with its back-pointer, when higher than the target's best so far.
    Returns whether it was kept."""
    if s > best[j - b0]:
        best[j - b0] = s
        bp[j] = i
        return True
    return False


@njit(cache=True, nogil=True, inline="always")
def close_column(best, score, emis, b0, b1):  # type: ignore[no-untyped-def]
    """After a step into states ``b0:b1``: each target's score is its best plus its emission
    (``-inf`` where no source reached it). Returns whether any target was reached."""
    reached = False
    for j in range(b1 - b0):
        if best[j] > -np.inf:
            reached = True
            score[b0 + j] = best[j] + emis[b0 + j]
        else:
            score[b0 + j] = -np.inf
    return reached


@njit(cache=True, nogil=True, inline="always")
def backtrack(bp, prev_col, starts, t, j, choice):  # type: ignore[no-untyped-def]
    """The states of a piece ending at column ``t`` in state ``j``, into ``choice`` (per column),
    following the back-pointers ``bp`` and each column's predecessor column ``prev_col`` until
    a column that starts the piece (``starts``). Returns that first column."""
    while True:
        choice[t] = j
        if starts[t]:
            return t
        j = bp[j]
        t = prev_col[t]


@njit(cache=True, nogil=True)
def viterbi_dense(ptr, emis, logp):  # type: ignore[no-untyped-def]
    """The Viterbi search of a lattice with dense transitions, from the operations above.

    ``ptr``: column ``t`` holds states ``ptr[t]:ptr[t + 1]``; ``emis``: per state; ``logp``:
    per state of columns 1 and on, the log-probability from each state of the column before,
    ``logp[j, i - ptr[t - 1]]`` from ``i`` to ``j`` (``-inf``: none; rows of column 0 unused).
    A column no state of the column before reaches starts a new piece. Returns per column the
    chosen state, and per column whether it starts a piece.
    """
    m = len(ptr) - 1
    n = len(emis)
    score = np.full(n, -np.inf)
    bp = np.full(n, -1, dtype=np.int64)
    kmax = 1
    for t in range(m):
        kmax = max(kmax, ptr[t + 1] - ptr[t])
    best = np.empty(kmax)
    order = np.empty(kmax, dtype=np.int64)
    prev_col = np.full(m, -1, dtype=np.int64)
    starts = np.zeros(m, dtype=np.bool_)
    choice = np.full(m, -1, dtype=np.int64)
    if m == 0:
        return choice, starts
    start_column(score, emis, ptr[0], ptr[1])
    starts[0] = True
    for t in range(1, m):
        a0, a1, b0, b1 = ptr[t - 1], ptr[t], ptr[t], ptr[t + 1]
        sources_best_first(score, a0, a1, order)
        open_column(best, bp, b0, b1)
        for oi in range(a1 - a0):
            i = order[oi]
            if score[i] == -np.inf:
                break
            for j in range(b0, b1):
                relax(best, bp, b0, j, i, score[i] + logp[j, i - a0])
        prev_col[t] = t - 1
        if not close_column(best, score, emis, b0, b1):
            start_column(score, emis, b0, b1)
            starts[t] = True
    t = m - 1
    while t >= 0:
        j = ptr[t] + np.argmax(score[ptr[t] : ptr[t + 1]])
        t = backtrack(bp, prev_col, starts, t, j, choice) - 1
    return choice, starts
