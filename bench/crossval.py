"""Cross-validation of settings over tracks: choose on four folds, score the held fold.

The benchmarks score every candidate setting on every track once (``scores[setting][track]``,
one record per track in the benchmark's own form). This module only chooses: for each fold,
the setting whose ``loss`` over the other folds' tracks is least (ties go to the earlier
setting in the grid, the current default first), and that setting's records of the held
tracks. The held records of all folds together are the out-of-fold records: each track scored
by a setting that was chosen without it. The benchmark then summarises them as it summarises
any run, so the out-of-fold figure and the in-sample one are the same figure.

    grid = settings_grid({"model.gps_sigma": [5, 8, 12], "model.beta": [3, 5, 8]}, base=config)
    result = cross_validate(scores, folds(ids), loss=my_loss)
    summary(result.oof_records)         # out of fold
    summary(result.in_sample_records)   # chosen on all tracks and scored on them
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

Setting = tuple[str, ...]
"""``SECTION.FIELD=VALUE`` strings, as ``MatchConfig.with_settings`` takes them."""
Loss = Callable[[list[Any]], float]
"""A figure to minimise over a list of per-track records."""


def settings_grid(grid: Mapping[str, Sequence[float]]) -> list[Setting]:
    """Every combination of the grid's values, as settings, in the grid's order.

    Parameters
    ----------
    grid : ``{"section.field": [values]}``.

    Returns
    -------
    list
        One :data:`Setting` per combination; the first value of each field varies slowest.
    """
    names = list(grid)
    return [
        tuple(f"{n}={_fmt(v)}" for n, v in zip(names, combo, strict=True))
        for combo in itertools.product(*(grid[n] for n in names))
    ]


def parse_grid(specs: Sequence[str]) -> dict[str, list[float]]:
    """``["model.gps_sigma=5,8,12", ...]`` as ``{"model.gps_sigma": [5.0, 8.0, 12.0], ...}``;
    a spec without ``=`` or with a value that is no number is a ``ValueError`` naming it."""
    grid: dict[str, list[float]] = {}
    for spec in specs:
        name, sep, values = spec.partition("=")
        if not sep or not name.strip() or not values.strip():
            raise ValueError(f"{spec!r}: expected SECTION.FIELD=V1,V2,...")
        try:
            grid[name.strip()] = [float(v) for v in values.split(",")]
        except ValueError:
            raise ValueError(f"{spec!r}: the values must be numbers") from None
    return grid


def _fmt(v: float) -> str:
    return str(int(v)) if float(v).is_integer() else repr(float(v))


def label(setting: Setting) -> str:
    """A setting as one short text (the values only, field names dropped to their last part)."""
    return ", ".join(f"{s.split('=')[0].rsplit('.', 1)[-1]}={s.split('=')[1]}" for s in setting)


@dataclass(frozen=True)
class FoldChoice:
    """One fold: the setting chosen on the other folds, its loss there and on the held tracks."""

    fold: int
    held: tuple[str, ...]
    chosen: Setting
    train_loss: float
    held_loss: float


@dataclass(frozen=True)
class CvResult:
    """What :func:`cross_validate` found.

    folds : the choice of each fold.
    oof_records : the held tracks' records under their fold's choice, all folds together.
    in_sample : the setting of least loss over all tracks.
    in_sample_records : every track's record under ``in_sample``.
    losses : each setting's loss over all tracks.
    oof_loss : the loss of ``oof_records``.
    """

    folds: tuple[FoldChoice, ...]
    oof_records: list[Any]
    in_sample: Setting
    in_sample_records: list[Any]
    losses: dict[Setting, float]
    oof_loss: float


def _best(
    scores: Mapping[Setting, Mapping[str, Any]], tracks: Sequence[str], loss: Loss
) -> tuple[Setting, float]:
    best: tuple[Setting, float] | None = None
    for setting, per_track in scores.items():
        value = loss([per_track[t] for t in tracks])
        if best is None or value < best[1]:
            best = (setting, value)
    if best is None:
        raise ValueError("no settings to choose from")
    return best


def cross_validate(
    scores: Mapping[Setting, Mapping[str, Any]], folds: Sequence[Sequence[str]], *, loss: Loss
) -> CvResult:
    """Choose a setting on all folds but one and score it on that one, for each fold.

    Parameters
    ----------
    scores : ``{setting: {track id: record}}``; every setting must have a record of every
        track of ``folds``. Iteration order breaks ties (put the current default first).
    folds : the track ids of each fold (:func:`folds.folds`).
    loss : the figure to minimise, from a list of records (lower is better).

    Returns
    -------
    CvResult
    """
    tracks = [t for f in folds for t in f]
    for setting, per_track in scores.items():
        missing = sorted(set(tracks) - set(per_track))
        if missing:
            raise ValueError(f"{label(setting) or 'defaults'}: no record of track(s) {', '.join(missing)}")
    choices, oof = [], []
    for i, held in enumerate(folds):
        train = [t for j, f in enumerate(folds) if j != i for t in f]
        chosen, train_loss = _best(scores, train, loss)
        held_records = [scores[chosen][t] for t in held]
        oof.extend(held_records)
        choices.append(FoldChoice(i, tuple(held), chosen, train_loss, loss(held_records)))
    in_sample, _ = _best(scores, tracks, loss)
    return CvResult(
        folds=tuple(choices),
        oof_records=oof,
        in_sample=in_sample,
        in_sample_records=[scores[in_sample][t] for t in tracks],
        losses={s: loss([per_track[t] for t in tracks]) for s, per_track in scores.items()},
        oof_loss=loss(oof),
    )


def choice_table(result: CvResult, *, fmt: str = "{:.4f}") -> str:
    """The per-fold choices and every setting's loss over all tracks, as markdown."""
    lines = ["| fold | held tracks | chosen on the other folds | loss there | loss on the held fold |"]
    lines.append("|---|---|---|---|---|")
    for c in result.folds:
        lines.append(
            f"| {c.fold} | {len(c.held)} | {label(c.chosen) or 'defaults'} | "
            f"{fmt.format(c.train_loss)} | {fmt.format(c.held_loss)} |"
        )
    lines.append("\n| setting | loss over all tracks |\n|---|---|")
    for s, v in result.losses.items():
        mark = " (least)" if s == result.in_sample else ""
        lines.append(f"| {label(s) or 'defaults'}{mark} | {fmt.format(v)} |")
    lines.append(f"| out of fold (each fold's choice on its held tracks) | {fmt.format(result.oof_loss)} |")
    return "\n".join(lines)
