"""The generic filter step: hypotheses with a log-probability and a position along a path,
scored by scorers the road model supplies. Nothing here knows about roads."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from typing import Protocol, TypeVar


class Scored(Protocol):
    logp: float
    s: float  # position along the hypothesis's path


H = TypeVar("H", bound=Scored)


def filter_step(
    hyps: Sequence[H],
    *,
    weight: float,
    place: Callable[[Sequence[H]], Iterable[tuple[float, float]]],
    turn_weight: float | None = None,
) -> None:
    """Move every hypothesis to its place for this observation and add its log-score there:
    ``place(hyps)`` moves each and gives its ``(score, turn)``: the score (emission and
    transition) times the observation's ``weight``, plus the turn score times ``turn_weight``
    (default ``weight``; a score already per distance moved is not weighed by time again). A
    single hypothesis has nothing to be weighed against."""
    many = len(hyps) > 1
    tw = weight if turn_weight is None else turn_weight
    for h, (sc, turn) in zip(hyps, place(hyps), strict=True):
        score = weight * sc
        score += tw * turn
        h.logp += score if many else 0.0


def normalise(hyps: list[H], *, prune_log_ratio: float) -> list[H]:
    """Shift log-probabilities so that the best is 0; drop those ``prune_log_ratio`` below."""
    if not hyps:
        return hyps
    m = hyps[0].logp  # max(h.logp for h in hyps), without a generator (a per-fix path)
    for h in hyps:
        if h.logp > m:
            m = h.logp
    if not math.isfinite(m):
        for h in hyps:
            h.logp = 0.0
        return hyps
    keep = []
    floor = -prune_log_ratio
    for h in hyps:
        h.logp -= m
        if h.logp >= floor:
            keep.append(h)
    return keep


def best(hyps: Sequence[H]) -> H:
    """The most probable hypothesis (the first of equals)."""
    top = hyps[0]
    for h in hyps:
        if h.logp > top.logp:
            top = h
    return top


def keep_best(hyps: list[H], most: int) -> None:
    """Keep the ``most`` most probable hypotheses (in place)."""
    if len(hyps) > most:
        hyps.sort(key=lambda h: -h.logp)
        del hyps[int(most) :]
