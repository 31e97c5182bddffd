"""Session state bytes: named keys with a version, every field validated, version 1 migrated."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest
from online_helpers import DriveSpec, drive
from service_util import city

from mapmatch.errors import ValidationError
from mapmatch.online import OnlineMatcher, SessionState
from mapmatch.online.codec import VERSION, from_bytes, to_bytes
from mapmatch.online.state import NO_CHAIN

AMAP = city()


def _session() -> tuple[OnlineMatcher, SessionState, list[Any]]:
    m = OnlineMatcher(AMAP.graph)
    st = m.new_session()
    fixes = drive(AMAP, "abefc", DriveSpec(speed=10.0, dt=1.0, noise=1.5, seed=7, sigma=3.0))
    for i, f in enumerate(fixes):  # into an ambiguous region: hypotheses, live fixes, a trail
        m.update(st, f)
        if len(st.hyps) > 1 and len(st.live) > 1 and len(st.trail) > 2:
            return m, st, fixes[i + 1 :]
    raise AssertionError("the drive never became ambiguous")


def test_named_keys_round_trip_and_go_on_identically() -> None:
    m, st, fixes = _session()
    d = json.loads(st.to_bytes())
    assert d["version"] == VERSION == 3
    assert set(d["hyps"][0]) >= {"edges", "k", "off", "s", "logp", "enter", "anc", "anc_sd"}
    assert set(d) >= {"headings_f64", "trail_time_ms", "trail_odo_cm"} and "trail" not in d
    assert len(st.hyps) > 1 and st.live and st.trail
    st2 = SessionState.from_bytes(st.to_bytes())
    assert st2.to_bytes() == st.to_bytes()
    a = [m.update(st, f) for f in fixes]
    b = [m.update(st2, f) for f in fixes]
    assert a and a == b


def _rejected_field(d: dict[str, Any]) -> str:
    """The field a blob made of ``d`` is refused for."""
    with pytest.raises(ValidationError) as ei:
        SessionState.from_bytes(json.dumps(d).encode())
    return ei.value.field


def _v2(st: SessionState) -> dict[str, Any]:
    """The state as version 2's JSON object (the lists these tests edit as pairs)."""
    d: dict[str, Any] = json.loads(to_bytes(st, version=2))
    return d


def test_version_2_decodes_to_the_state_version_3_holds() -> None:
    m, st, fixes = _session()
    v2 = to_bytes(st, version=2)
    assert json.loads(v2)["version"] == 2
    old = SessionState.from_bytes(v2)
    assert old.to_bytes() == st.to_bytes() and to_bytes(old, version=2) == v2
    assert [m.update(old, f) for f in fixes] == [m.update(st, f) for f in fixes]


def test_version_3_writes_the_trail_in_whole_units_and_the_headings_exactly() -> None:
    _, st, _ = _session()
    d = json.loads(st.to_bytes())
    times = [sum(d["trail_time_ms"][: i + 1]) / 1000.0 for i in range(len(d["trail_time_ms"]))]
    assert times == [round(p.time, 3) for p in st.trail] and len(times) > 2
    back = SessionState.from_bytes(st.to_bytes())
    assert back.headings == st.headings and [p.odo for p in back.trail] == [round(p.odo, 2) for p in st.trail]
    # a trail too large for whole units is written as version 2
    st.crossings.trail[0].time = 1e14
    assert json.loads(st.to_bytes())["version"] == 2
    assert SessionState.from_bytes(st.to_bytes()).trail[0].time == 1e14


@pytest.mark.parametrize(
    ("change", "key"),
    [
        (lambda d: d.pop("trail_time_ms"), "state.trail_time_ms"),
        (lambda d: d.update(trail_time_ms="12"), "state.trail_time_ms"),
        (lambda d: d["trail_time_ms"].__setitem__(1, 2.5), "state.trail_time_ms[1]"),
        (lambda d: d["trail_odo_cm"].__setitem__(0, True), "state.trail_odo_cm[0]"),
        (lambda d: d["trail_odo_cm"].__setitem__(1, 2**60), "state.trail_odo_cm[1]"),
        (lambda d: d["trail_odo_cm"].pop(), "state.trail_odo_cm"),
        (lambda d: d.update(headings_f64=[1.0, 2.0]), "state.headings_f64"),
        (lambda d: d.update(headings_f64="not base64!"), "state.headings_f64"),
        (lambda d: d.update(headings_f64="AAAA"), "state.headings_f64"),  # 3 bytes: no whole pair
        (lambda d: d.update(headings_f64="A" * 4_000), "state.headings_f64"),  # over the cap
        (lambda d: d.update(headings_f64="AAAAAAAAAAAAAAAAAAD4fw=="), "state.headings[0]"),  # NaN
    ],
)
def test_every_version_3_field_is_validated_and_named(change: Any, key: str) -> None:
    _, st, _ = _session()
    d = json.loads(st.to_bytes())
    change(d)
    assert _rejected_field(d) == key


def test_version_1_is_migrated() -> None:
    _, st, _ = _session()
    d = _v2(st)
    v1 = {
        "v": 1,
        "t": d["time"],
        "xy": [d["x"], d["y"]],
        "odo": [d["odo"], d["gps_odo"], d["init_odo"], d["odo_k"], d["odo_kvar"], d["anc_odo"], d["anc_sd"]],
        "bad": [d["bad_time"], d["bad_odo"]],
        "init": d["init_pending"],
        "h": [
            [
                h[k]
                for k in (
                    "edges",
                    "k",
                    "off",
                    "s",
                    "logp",
                    "enter",
                    "dist",
                    "px",
                    "py",
                    "bearing",
                    "anc",
                    "anc_sd",
                )
            ]
            for h in d["hyps"]
        ],
        "live": [[r[0], float(r[1]), *r[2:7], 1.0 if r[7] else 0.0] for r in d["live"]],
        "hd": d["headings"],
        "res": [d["res_pos2"], d["res_head2"], d["drift_sigma"], d["search_time"]],
        "sh": d["shown"],
        "b": list(d["bias"].values()),
        "tr": d["trail"],
        "bk": d["back"],
    }
    old = SessionState.from_bytes(json.dumps(v1).encode())
    assert old.chain == NO_CHAIN  # version 1 had no running scale estimate: none yet
    old.chain = st.chain
    assert math.isnan(old.speed)  # nor an averaged speed: it starts from the next fix
    old.speed = st.speed
    assert old.to_bytes() == st.to_bytes()
    # the oldest layout (10-slot hypotheses, 3 odometer values) gets the defaults
    v1["h"] = [h[:10] for h in v1["h"]]
    v1["odo"] = v1["odo"][:3]
    older = SessionState.from_bytes(json.dumps(v1).encode())
    assert all(math.isnan(h.anc) for h in older.hyps) and older.odo_k == 0.0


@pytest.mark.parametrize(
    ("change", "key"),
    [
        (lambda d: d.update(version=99), "state.version"),
        (lambda d: d.update(time="soon"), "state.time"),
        (lambda d: d.update(odo=math.nan), "state.odo"),
        (lambda d: d.update(odo=math.inf), "state.odo"),
        (lambda d: d.update(res_pos2=-1.0), "state.res_pos2"),
        (lambda d: d.update(drift_sigma=-0.1), "state.drift_sigma"),
        (lambda d: d.update(speed=-0.1), "state.speed"),
        (lambda d: d.update(drift_sigma=1.7e175), "state.drift_sigma"),  # its square overflows
        (lambda d: d.update(chain=[1.0, 2.0]), "state.chain"),
        (lambda d: d.update(chain=[1, 2.0, "x", *[0.0] * 8]), "state.chain[2]"),
        (lambda d: d.update(chain=[1.5, *[0.0] * 10]), "state.chain[0]"),
        (lambda d: d.update(chain=[1, *[0.0] * 5, -1.0, *[0.0] * 4]), "state.chain[6]"),
        (lambda d: d["bias"].update(pyy=1e200), "state.bias.pyy"),
        (lambda d: d.update(init_pending=1), "state.init_pending"),
        (lambda d: d.update(shown=1.5), "state.shown"),
        (lambda d: d["bias"].update(pxx=-4.0), "state.bias.pxx"),
        (lambda d: d["bias"].pop("by"), "state.bias.by"),
        (lambda d: d.update(odo_kvar=-1e-6), "state.odo_kvar"),
        (lambda d: d["hyps"][0].update(k=7), "state.hyps[0].k"),
        (lambda d: d["hyps"][0].update(edges=[]), "state.hyps[0].edges"),
        (lambda d: d["hyps"][0].update(edges=[-3]), "state.hyps[0].edges[0]"),
        (lambda d: d["hyps"][1].update(enter=[0.0, 1.0, 2.0, 3.0, 4.0]), "state.hyps[1].enter"),
        (lambda d: d["hyps"][0].update(logp=None), "state.hyps[0].logp"),
        (lambda d: d["hyps"][0].update(anc_sd=-1.0), "state.hyps[0].anc_sd"),
        (lambda d: d["live"][0].__setitem__(5, -3.0), "state.live[0].sigma"),
        (lambda d: d["live"][0].pop(), "state.live[0]"),
        (lambda d: d["trail"].append([1.0]), "state.trail[2]"),
        (lambda d: d["back"].append(["e", 1.0]), "state.back[0]"),
        (lambda d: d.pop("headings"), "state.headings"),
    ],
)
def test_every_field_is_validated_and_named(change: Any, key: str) -> None:
    _, st, _ = _session()
    d = _v2(st)
    d["back"] = []
    d["trail"] = d["trail"][:2]
    change(d)
    assert _rejected_field(d) == key


def test_edges_beyond_the_map_are_rejected_when_the_map_is_known() -> None:
    _, st, _ = _session()
    blob = st.to_bytes()
    assert from_bytes(blob, n_edges=AMAP.graph.n_edges).to_bytes() == blob
    with pytest.raises(ValidationError) as ei:
        from_bytes(blob, n_edges=2)
    assert ei.value.field.startswith("state.")


@pytest.mark.parametrize("blob", [b"not json", b"[1, 2]", b'{"v": 1}', b'{"version": 2}'])
def test_not_a_state_at_all(blob: bytes) -> None:
    with pytest.raises(ValidationError):
        SessionState.from_bytes(blob)


# ---------------------------------------------------------------------------------- caps
LISTS = {"hyps": "state.hyps", "edges": "state.hyps[0].edges", "live": "state.live",
         "headings": "state.headings", "trail": "state.trail", "back": "state.back"}  # fmt: skip


def test_the_largest_state_the_caps_allow_decodes_with_bounded_lists() -> None:
    from stall_util import worst_case_blob

    from mapmatch.config import DEFAULT_CONFIG
    from mapmatch.online.codec import StateCaps

    _, st, _ = _session()
    caps = StateCaps.of(DEFAULT_CONFIG)
    blob = worst_case_blob(st.to_bytes(), caps, n_edges=AMAP.graph.n_edges)
    got = from_bytes(blob, n_edges=AMAP.graph.n_edges, caps=caps)
    assert len(got.hyps) == caps.hyps and len(got.live) == caps.live
    assert len(got.headings) == caps.headings and len(got.trail) == caps.trail
    assert len(got.back) == caps.path_edges and len(got.hyps[0].edges) == caps.path_edges


@pytest.mark.parametrize("over", sorted(LISTS))
def test_a_list_over_its_cap_is_refused_naming_it(over: str) -> None:
    from stall_util import worst_case_blob

    from mapmatch.config import DEFAULT_CONFIG
    from mapmatch.online.codec import StateCaps

    _, st, _ = _session()
    caps = StateCaps.of(DEFAULT_CONFIG)
    blob = worst_case_blob(st.to_bytes(), caps, n_edges=AMAP.graph.n_edges, over=over)
    with pytest.raises(ValidationError) as ei:
        from_bytes(blob, n_edges=AMAP.graph.n_edges, caps=caps)
    assert ei.value.field == LISTS[over] and "over the limit" in ei.value.reason


def test_version_1_lists_are_capped_before_migration() -> None:
    d = {"v": 1, "t": 0.0, "h": [], "live": [], "hd": [[float(i), 0.0] for i in range(200_000)]}
    with pytest.raises(ValidationError) as ei:
        from_bytes(json.dumps(d).encode())
    assert ei.value.field == "state.headings"


def _add_sample_by_pop(
    samples: list[list[float]], odo: float, heading: float, window: float, most: int
) -> None:
    """The trimming rule, one ``pop(0)`` at a time (what :func:`add_sample` must equal)."""
    if math.isnan(heading) or (samples and odo - samples[-1][0] < 1.0):
        return
    samples.append([odo, heading])
    while len(samples) > 2 and (samples[1][0] <= odo - 2.0 * window or len(samples) > most):
        samples.pop(0)


def test_add_sample_trims_as_one_pop_at_a_time_did() -> None:
    import random

    from mapmatch.turns import add_sample

    rng = random.Random(3)
    for _ in range(200):
        start = [[float(o), 0.0] for o in sorted(rng.uniform(0, 400) for _ in range(rng.randrange(0, 120)))]
        a, b = [list(s) for s in start], [list(s) for s in start]
        for _ in range(20):
            odo = (a[-1][0] if a else 0.0) + rng.choice([0.5, 2.0, 30.0, 200.0])
            add_sample(a, odo, 10.0, window=30.0, max_samples=48)
            _add_sample_by_pop(b, odo, 10.0, 30.0, 48)
            assert a == b


def test_a_blob_larger_than_the_caps_allow_is_refused_before_parsing() -> None:
    from mapmatch.config import DEFAULT_CONFIG
    from mapmatch.online.codec import VALUE_BYTES, StateCaps, max_values

    _, st, _ = _session()
    most = max_values(StateCaps.of(DEFAULT_CONFIG))
    padded = st.to_bytes()[:-1] + b" " * (most * VALUE_BYTES) + b"}"
    with pytest.raises(ValidationError) as ei:
        from_bytes(padded)
    assert ei.value.field == "state" and "over the limit" in ei.value.reason
    d = _v2(st)
    d["trail"] = [[float(i), float(i)] for i in range(most)]
    with pytest.raises(ValidationError) as ei:
        from_bytes(json.dumps(d).encode())
    assert ei.value.field == "state.trail"
