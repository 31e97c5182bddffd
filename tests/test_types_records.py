"""The answer records: built by position on the per-fix path, they hold what their fields name."""

from __future__ import annotations

import dataclasses
import inspect
import math
import pickle

from graph.ascii import parse_ascii_map
from mapmatch.online import OnlineMatcher
from mapmatch.types import Candidate, Correction, MapAidedMeasurement, SnapResult, State, Turn
from tests.online_helpers import DriveSpec, drive


def _values(cls: type) -> dict[str, object]:
    """A distinct value for every field of ``cls``."""
    special: dict[str, object] = {"state": State.AMBIGUOUS, "turn": Turn.LEFT, "usable": True}
    return {f.name: special.get(f.name, float(i) + 0.5) for i, f in enumerate(dataclasses.fields(cls))}


def test_records_by_position_equal_by_keyword() -> None:
    for cls in (Candidate, MapAidedMeasurement, SnapResult):
        kw = _values(cls)
        if cls is SnapResult:
            kw["candidates"] = (Candidate(1, 2, 3, 4, 0.5, 1.0, 2.0),)
            kw["correction"] = Correction(1.0, 2.0, (3,), (4,))
            kw["map_aided"] = MapAidedMeasurement(*_values(MapAidedMeasurement).values())  # type: ignore[arg-type]
        by_position, by_name = cls(*kw.values()), cls(**kw)
        assert by_position == by_name and repr(by_position) == repr(by_name)
        assert {f.name: getattr(by_position, f.name) for f in dataclasses.fields(cls)} == kw
        assert pickle.loads(pickle.dumps(by_position)) == by_name
        assert not hasattr(by_position, "__dict__")  # slots: no per-object dict


def test_replace_makes_a_new_answer() -> None:
    r = SnapResult(time=1.0, state=State.ON_ROAD, edge=3)
    s = dataclasses.replace(r, state=State.REINITIALISED)
    assert (r.state, s.state, s.edge) == (State.ON_ROAD, State.REINITIALISED, 3)


CROSS = """
        n
        |
a-------b-------c
        |
        s
"""


def test_the_matchers_answers_hold_what_their_fields_name() -> None:
    """The per-fix path passes every field by position: a field moved or put in between would
    put a value under the wrong name here."""
    amap = parse_ascii_map(CROSS, scale=20.0)
    g = amap.graph
    matcher = OnlineMatcher(g)
    state = matcher.new_session()
    fixes = drive(amap, "abc", DriveSpec(speed=10.0, sigma=3.0))
    placed = 0
    for f in fixes:
        r = matcher.update(state, f)
        assert type(r) is SnapResult and isinstance(r.state, State) and isinstance(r.turn, Turn)
        assert (r.time, r.raw_lat, r.raw_lon) == (f.time, f.lat, f.lon)
        assert isinstance(r.map_aided, MapAidedMeasurement) and isinstance(r.candidates, tuple)
        assert all(type(c) is Candidate for c in r.candidates)
        if r.edge < 0:
            continue
        placed += 1
        assert r.u == g.node_id[g.edge_u[r.edge]] and r.v == g.node_id[g.edge_v[r.edge]]
        assert 0.0 <= r.offset <= g.edge_len[r.edge] + 1e-6 and r.dist >= 0.0
        assert r.way_id == g.way_id_at(r.edge, r.offset) and isinstance(r.name, str)
        assert isinstance(r.road_class, str) and r.speed_kph >= 0.0
        assert abs(r.lat - f.lat) < 1e-3 and abs(r.lon - f.lon) < 1e-3
        assert 0.0 <= r.bearing < 360.0
        m = r.map_aided
        if m.usable:
            assert m.reason == "" and math.isfinite(m.var_e) and m.var_e > 0 and m.var_n > 0
            assert m.along_sigma > 0 and m.cross_sigma > 0 and 0.0 <= m.probability <= 1.0
            assert abs(m.lat - r.lat) < 1e-9 and abs(m.heading - r.bearing) < 1e-9
    assert placed > len(fixes) // 2


def test_positional_orders() -> None:
    """The per-fix path passes these by position, in this order (a call of positional arguments
    plus twice its keywords over 30 goes through a dict): a field or parameter moved or put in
    between must change those calls too (``prepare``, ``report``)."""
    from mapmatch.measurement import AlongEvidence, Placement, map_aided_measurement
    from mapmatch.online.state import Step

    step = ("time", "x", "y", "sigma", "heading", "kappa", "travelled", "odo", "odo_known", "dt", "gps")
    assert tuple(f.name for f in dataclasses.fields(Step))[:14] == (*step, "weight", "stopped", "r_a")
    placement = ("state", "edge", "offset", "lat", "lon", "bearing", "probability", "since_init", "beyond")
    assert tuple(f.name for f in dataclasses.fields(Placement)) == placement
    evidence = ("gps", "fix_sigma", "bias_cov", "white_share", "anchor_sd", "odo_sigma", "dr_distance")
    assert tuple(f.name for f in dataclasses.fields(AlongEvidence)) == (*evidence, "gps_sigma")
    aided = inspect.signature(map_aided_measurement).parameters
    assert tuple(aided) == ("graph", "placement", "evidence", "tags", "agreement", "config", "model")
    assert aided["config"].kind is inspect.Parameter.KEYWORD_ONLY
