"""The shared Kubicka tracks split into folds by track, for cross-validation of the defaults.

A track is the unit: all of a track's fixes, at every rate and sub-sampling, fall in one fold,
so a setting chosen on the other folds has never seen any part of the held tracks (their roads,
their receiver, their driver). The split is deterministic: the track ids (the folder names)
are sorted, shuffled by a NumPy generator seeded with ``SEED``, and dealt round the folds in
that order, so the folds' sizes differ by at most one (29 tracks in 5 folds: 6, 6, 6, 6, 5).
It depends only on the set of ids, not on the order they are listed in.

    python bench/folds.py            # print the folds of the tracks in the shared data set
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
KUBICKA = Path(os.environ.get("MAPMATCH_SHARED") or ROOT.parent / "shared") / "data" / "kubicka"
FOLDS = 5
"""Folds of the cross-validation: choose on four, score on the fifth."""
SEED = 48
"""Seed of the shuffle that deals the tracks to the folds."""


def track_ids(root: Path = KUBICKA) -> list[str]:
    """The track ids in ``root``: the sorted names of its folders that hold a ``track.csv``."""
    return sorted(p.name for p in root.iterdir() if (p / "track.csv").is_file())


def assign_folds(ids: Iterable[str], *, k: int = FOLDS, seed: int = SEED) -> dict[str, int]:
    """Each track id's fold, ``0 .. k-1``.

    Parameters
    ----------
    ids : the track ids; repeated ids are one track.
    k : number of folds, at least 2 and at most the number of tracks.
    seed : seed of the shuffle.

    Returns
    -------
    dict
        ``{track id: fold}`` in sorted id order.
    """
    names = sorted(set(ids))
    if not 2 <= k <= len(names):
        raise ValueError(f"{k} folds of {len(names)} tracks: need 2 <= folds <= tracks")
    order = np.random.default_rng(seed).permutation(len(names))
    fold = {names[int(j)]: pos % k for pos, j in enumerate(order)}
    return {n: fold[n] for n in names}


def folds(ids: Iterable[str], *, k: int = FOLDS, seed: int = SEED) -> list[list[str]]:
    """The ``k`` folds as sorted lists of track ids (see :func:`assign_folds`)."""
    fold = assign_folds(ids, k=k, seed=seed)
    return [[n for n, f in fold.items() if f == i] for i in range(k)]


def main() -> int:
    if not KUBICKA.is_dir():
        print(f"error: needs the shared Kubicka tracks in {KUBICKA}", file=sys.stderr)
        return 2
    ids = track_ids()
    print(f"{len(ids)} tracks in {FOLDS} folds (seed {SEED})")
    for i, f in enumerate(folds(ids)):
        print(f"fold {i}: {len(f)} tracks: {' '.join(f)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
