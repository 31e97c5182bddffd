"""Distinct integer keys by sorting.

numpy 2's ``np.unique`` and ``np.isin`` hash integer arrays, which on a million keys is tens
of times slower than a sort; the build uses these.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

K = TypeVar("K", bound=np.integer)


def unique(keys: NDArray[K]) -> NDArray[K]:
    """The distinct keys, sorted (``np.unique(keys)``)."""
    s = np.sort(keys)
    if len(s) < 2:
        return s
    new = np.empty(len(s), dtype=bool)
    new[0] = True
    np.not_equal(s[1:], s[:-1], out=new[1:])
    return s[new]


def unique_inverse(keys: NDArray[K]) -> tuple[NDArray[K], NDArray[np.int64], NDArray[np.int64]]:
    """``(distinct sorted keys, index of each key's first occurrence, inverse)``, as
    ``np.unique(keys, return_index=True, return_inverse=True)`` gives them."""
    order = np.argsort(keys, kind="stable")
    s = keys[order]
    new = np.ones(len(s), dtype=bool)
    if len(s) > 1:
        np.not_equal(s[1:], s[:-1], out=new[1:])
    inv = np.empty(len(s), dtype=np.int64)
    inv[order] = np.cumsum(new) - 1
    return s[new], order[new].astype(np.int64), inv


def isin(a: NDArray[np.integer], b: NDArray[np.integer]) -> NDArray[np.bool_]:
    """Whether each key of ``a`` is among ``b`` (``np.isin(a, b)``)."""
    ub = unique(b)
    if not len(ub):
        return np.zeros(len(a), dtype=bool)
    at = np.minimum(np.searchsorted(ub, a), len(ub) - 1)
    return ub[at] == a


def dense_labels(labels: NDArray[np.integer], n: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Labels in ``0..n-1`` renumbered ``0..k-1`` in order: ``(distinct labels, new label of each)``."""
    used = np.bincount(labels, minlength=n) > 0
    uniq = np.flatnonzero(used)
    new = np.cumsum(used) - 1
    return uniq, new[labels]
