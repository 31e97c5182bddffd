"""The cross-validation folds (bench/folds.py) and the choice on them (bench/crossval.py).

The folds split tracks, not fixes: deterministic, disjoint, covering every track, sizes within
one of each other, and the same whatever order the ids come in. The choice of a fold must never
look at the held fold's tracks.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from bench_modules import bench_module

folds = bench_module("folds")
crossval = bench_module("crossval")

IDS = [f"{i:08d}" for i in range(100) if i % 7 in (0, 3)]  # the shared set's 29 ids


def test_the_folds_are_disjoint_cover_every_track_and_differ_in_size_by_at_most_one() -> None:
    parts = folds.folds(IDS)
    assert len(parts) == folds.FOLDS == 5
    flat = [t for p in parts for t in p]
    assert sorted(flat) == sorted(IDS)
    assert len(flat) == len(set(flat))
    assert sorted(len(p) for p in parts) == [5, 6, 6, 6, 6]
    assert all(p == sorted(p) for p in parts)


def test_the_folds_are_the_same_on_every_call_and_for_any_order_of_the_ids() -> None:
    first = folds.folds(IDS)
    assert folds.folds(list(reversed(IDS))) == first
    assert folds.folds(IDS + IDS[:3]) == first
    assert folds.assign_folds(IDS) == folds.assign_folds(sorted(IDS, key=lambda s: s[::-1]))
    # a shuffle, not the sorted order dealt round: neighbouring ids do not all share a pattern
    assert [folds.assign_folds(IDS)[t] for t in IDS[:5]] != [0, 1, 2, 3, 4]
    assert folds.folds(IDS, seed=folds.SEED + 1) != first


def test_too_many_folds_for_the_tracks_is_an_error_naming_both_counts() -> None:
    with pytest.raises(ValueError, match="6 folds of 5 tracks"):
        folds.folds(IDS[:5], k=6)


def test_the_shared_tracks_fall_in_five_folds(kubicka_dir: Path) -> None:
    ids = folds.track_ids(kubicka_dir)
    assert ids == sorted(ids) and len(ids) >= 15
    assert sorted(t for p in folds.folds(ids) for t in p) == ids


def test_each_fold_is_chosen_without_its_held_tracks_and_scored_on_them() -> None:
    ids = [f"t{i}" for i in range(10)]
    parts = folds.folds(ids, k=5)
    # setting "a" is best on every track but those of fold 0, where "b" is far better
    held0 = set(parts[0])
    scores = {
        ("x=a",): {t: (5.0 if t in held0 else 1.0) for t in ids},
        ("x=b",): {t: (0.0 if t in held0 else 2.0) for t in ids},
    }
    res = crossval.cross_validate(scores, parts, loss=lambda r: sum(r) / len(r))
    # fold 0 chooses on the other eight tracks, where "a" is better, and pays for it on its own
    assert res.folds[0].chosen == ("x=a",)
    assert res.folds[0].held_loss == 5.0
    # the other folds' training sets hold fold 0, where "b" gains enough: (6*2 + 0) / 8 < (6 + 10) / 8
    assert [c.chosen for c in res.folds[1:]] == [("x=b",)] * 4
    assert res.oof_records == [5.0, 5.0] + [2.0] * 8
    # in sample "b" wins: mean 1.6 against 1.8, the figure the out-of-fold 2.6 is compared with
    assert res.in_sample == ("x=b",)
    assert res.losses == {("x=a",): pytest.approx(1.8), ("x=b",): pytest.approx(1.6)}
    assert res.oof_loss == pytest.approx(2.6)
    with pytest.raises(ValueError, match="no record of track"):
        crossval.cross_validate({("x=a",): {"t0": 1.0}}, parts, loss=sum)


def test_the_grid_is_every_combination_in_order_and_a_bad_spec_is_named() -> None:
    grid = crossval.parse_grid(["model.beta=3,5", "online.region.switch_penalty=8"])
    assert crossval.settings_grid(grid) == [
        ("model.beta=3", "online.region.switch_penalty=8"),
        ("model.beta=5", "online.region.switch_penalty=8"),
    ]
    with pytest.raises(ValueError, match=r"model\.beta=x"):
        crossval.parse_grid(["model.beta=x"])
    with pytest.raises(ValueError, match=r"expected SECTION\.FIELD"):
        crossval.parse_grid(["model.beta"])
