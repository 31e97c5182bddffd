"""The hot path's fast builders give the very objects the dataclass constructors give."""

from __future__ import annotations

import dataclasses
import pickle

import pytest

from mapmatch.types import (
    Candidate,
    Correction,
    MapAidedMeasurement,
    SnapResult,
    State,
    Turn,
    new_candidate,
    new_measurement,
    new_snap_result,
)


def _values(cls: type) -> dict[str, object]:
    """A distinct value for every field of ``cls``."""
    special: dict[str, object] = {"state": State.AMBIGUOUS, "turn": Turn.LEFT, "usable": True}
    out: dict[str, object] = {}
    for i, f in enumerate(dataclasses.fields(cls)):
        out[f.name] = special.get(f.name, float(i) + 0.5)
    return out


def _check(built: object, cls: type, kw: dict[str, object]) -> None:
    ref = cls(**kw)
    assert type(built) is cls
    assert built == ref and hash(built) == hash(ref) and repr(built) == repr(ref)
    assert dataclasses.asdict(built) == dataclasses.asdict(ref)  # type: ignore[call-overload]
    assert pickle.loads(pickle.dumps(built)) == ref
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(built, dataclasses.fields(cls)[0].name, 1)
    assert {f.name for f in dataclasses.fields(cls)} == set(cls.__slots__)  # type: ignore[attr-defined]


def test_candidate() -> None:
    kw = _values(Candidate)
    _check(new_candidate(*kw.values()), Candidate, kw)  # type: ignore[arg-type]


def test_measurement() -> None:
    kw = _values(MapAidedMeasurement)
    kw["reason"] = "settling"
    _check(new_measurement(*kw.values()), MapAidedMeasurement, kw)  # type: ignore[arg-type]


def test_snap_result() -> None:
    kw = _values(SnapResult)
    kw["candidates"] = (new_candidate(1, 2, 3, 4, 0.5, 1.0, 2.0),)
    kw["correction"] = Correction(1.0, 2.0, (3,), (4,))
    kw["map_aided"] = new_measurement(*_values(MapAidedMeasurement).values())  # type: ignore[arg-type]
    _check(new_snap_result(**kw), SnapResult, kw)  # type: ignore[arg-type]
    assert dataclasses.replace(new_snap_result(**kw), edge=7).edge == 7  # type: ignore[arg-type]


def test_positional_orders() -> None:
    """The per-fix path passes these by position, in this order (a call of positional arguments
    plus twice its keywords over 30 goes through a dict): a field or parameter moved or put in
    between must change those calls too (``prepare``, ``report``)."""
    import inspect

    from mapmatch.measurement import map_aided_measurement
    from mapmatch.online.state import Step

    step = ("time", "x", "y", "sigma", "heading", "kappa", "travelled", "odo", "odo_known", "dt", "gps")
    assert tuple(f.name for f in dataclasses.fields(Step))[:14] == (*step, "weight", "stopped", "r_a")
    aided = inspect.signature(map_aided_measurement).parameters
    assert tuple(aided)[:18] == (
        *("graph", "state", "edge", "offset", "lat", "lon", "bearing", "probability", "gps"),
        *("fix_sigma", "bias_cov", "white_share", "anchor_sd", "odo_sigma", "dr_distance", "gps_sigma"),
        "since_init",
        "width",
    )
    assert aided["width"].kind is inspect.Parameter.KEYWORD_ONLY
    snap = tuple(inspect.signature(new_snap_result).parameters)
    assert snap[:12] == tuple(f.name for f in dataclasses.fields(SnapResult))[:12]
