"""A session's state as bytes: JSON by named keys with a version, validated field by field.

Version 3 (what :func:`to_bytes` writes) names every field and carries the two long lists
compactly: the odometer trail as whole milliseconds and centimetres, each item the difference
from the one before (``trail_time_ms``, ``trail_odo_cm``), and the heading samples as their
float64 values, little-endian, in base64 (``headings_f64``, exact). Version 2 (the trail as
``[time, odo]`` pairs rounded to ms and cm, the headings as ``[odo, heading]`` pairs) decodes
to the same state; :func:`to_bytes` still writes it for a trail too large for whole units.
Version 1 (positional lists, the format before the online package) is migrated explicitly on
reading. :func:`from_bytes` checks every value (types,
lengths, finite numbers, non-negative variances and σ, edge indices) and raises
:class:`~mapmatch.errors.ValidationError` naming the offending key, e.g. ``state.hyps[0].k``.
Every list is bounded by the matcher configuration's own caps (:class:`StateCaps`), checked
before its items are read: decoding a blob costs at most what the matcher's own sessions hold.
"""

from __future__ import annotations

import base64
import binascii
import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from mapmatch.config import DEFAULT_CONFIG, MatchConfig
from mapmatch.errors import ValidationError
from mapmatch.online.state import (
    NO_CHAIN,
    AnchorState,
    BackEdge,
    BiasState,
    CrossingTrail,
    FixBias,
    Hypothesis,
    LiveFix,
    RegionState,
    ScaleChain,
    SessionState,
    TrailPoint,
)

VERSION = 3
# the largest whole number of ms or cm a version-3 trail holds (floats are exact up to it)
MAX_TRAIL_UNITS = 2**53
# the largest σ, variance or distance a state may hold: squares and products of imported
# spreads stay finite (times, coordinates and the odometer need only be finite)
MAX_MAGNITUDE = 1e100
_NAN = math.nan
_HYP = ("edges", "k", "off", "s", "logp", "enter", "dist", "px", "py", "bearing", "anc", "anc_sd")
_LIVE = ("time", "edge", "x", "y", "heading", "sigma", "kappa", "gps")


@dataclass(frozen=True)
class StateCaps:
    """The most items each list of a session state may hold (the matcher never keeps more).

    ``hyps``: the hypotheses kept plus a search's candidates; ``path_edges``: the edges of a
    hypothesis's path (and its entry times) and of the edges since the last turn anchor;
    ``live``, ``headings``, ``trail``: the fixes, heading samples and odometer points kept.
    """

    hyps: int
    path_edges: int
    live: int
    headings: int
    trail: int

    @classmethod
    def of(cls, config: MatchConfig) -> StateCaps:
        """The caps of a matcher configuration."""
        o = config.online
        return cls(
            hyps=o.region.max_hypotheses + config.model.max_candidates,
            path_edges=o.corrections.max_path_edges,
            live=o.corrections.max_live,
            headings=max(o.evidence.turn_max_samples, 2),
            trail=o.corrections.trail_max,
        )


def check_length(v: Any, name: str, cap: int) -> None:
    """:class:`ValidationError` naming ``name`` when the list ``v`` holds more than ``cap`` items."""
    if isinstance(v, list) and len(v) > cap:
        raise ValidationError(name, f"holds {len(v)} items, over the limit of {cap}")


def to_bytes(st: SessionState, *, version: int = VERSION) -> bytes:
    """Compact JSON (a few kilobytes); the trail is rounded to ms and cm. ``version`` 3 (the
    default; 2 when the trail does not fit :data:`MAX_TRAIL_UNITS`) or 2."""
    if version not in (2, VERSION):
        raise ValueError(f"to_bytes writes versions 2 and {VERSION}, not {version!r}")
    trail = st.crossings.trail
    coded = _trail_units(trail) if version == VERSION else None
    if coded is None:
        d = _fields(
            st,
            2,
            {"headings": st.headings},
            {"trail": [[round(p.time, 3), round(p.odo, 2)] for p in trail]},
        )
    else:
        d = _fields(
            st,
            VERSION,
            {"headings_f64": _f64(st.headings)},
            {"trail_time_ms": coded[0], "trail_odo_cm": coded[1]},
        )
    return json.dumps(d, separators=(",", ":"), allow_nan=True).encode()


def _fields(
    st: SessionState, version: int, headings: dict[str, Any], trail: dict[str, Any]
) -> dict[str, Any]:
    """The blob's keys in their order, with the version's own keys of the headings and trail."""
    anc, fb, rg = st.anchor, st.bias, st.region
    return {
        "version": version,
        "time": st.time,
        "x": st.x,
        "y": st.y,
        "odo": st.odo,
        "gps_odo": st.gps_odo,
        "bad_time": st.bad_time,
        "bad_odo": st.bad_odo,
        "init_pending": rg.init_pending,
        "init_odo": rg.init_odo,
        "hyps": [{k: getattr(h, k) for k in _HYP} for h in st.hyps],
        "live": [[getattr(f, k) for k in _LIVE] for f in rg.live],
        "live_fields": list(_LIVE),
        **headings,
        "res_pos2": fb.res_pos2,
        "res_head2": fb.res_head2,
        "drift_sigma": fb.drift_sigma,
        "speed": st.speed,
        "search_time": st.search_time,
        "shown": st.shown,
        "bias": fb.vector._asdict(),
        "odo_k": anc.odo_k,
        "odo_kvar": anc.odo_kvar,
        "anc_odo": anc.anc_odo,
        "chain": list(anc.chain),
        "anc_sd": anc.anc_sd,
        **trail,
        "back": [[b.edge, b.time] for b in st.crossings.back],
    }


def _trail_units(trail: list[TrailPoint]) -> tuple[list[int], list[int]] | None:
    """The trail as whole ms and cm, each after the first as the difference from the one
    before; None when a value is not finite or over :data:`MAX_TRAIL_UNITS` units."""
    t = np.rint(np.array([p.time for p in trail], dtype=np.float64) * 1000.0)
    o = np.rint(np.array([p.odo for p in trail], dtype=np.float64) * 100.0)
    if trail and not (np.abs(t).max() <= MAX_TRAIL_UNITS and np.abs(o).max() <= MAX_TRAIL_UNITS):
        return None
    ti, oi = t.astype(np.int64), o.astype(np.int64)
    ti[1:] -= ti[:-1].copy()
    oi[1:] -= oi[:-1].copy()
    return ti.tolist(), oi.tolist()


def _f64(pairs: list[list[float]]) -> str:
    """Pairs of floats as their float64 values, little-endian, in base64."""
    flat = np.fromiter((v for p in pairs for v in p), np.dtype("<f8"), 2 * len(pairs))
    return base64.b64encode(flat.tobytes()).decode("ascii")


def from_bytes(data: bytes, *, n_edges: int | None = None, caps: StateCaps | None = None) -> SessionState:
    """Decode :func:`to_bytes` (version 3 or 2) or version 1; edges must be below ``n_edges`` when
    given, and every list within ``caps`` (default: those of
    :data:`~mapmatch.config.DEFAULT_CONFIG`). Raises :class:`ValidationError` naming the key on
    anything else, e.g. ``state.headings`` for a list over its cap."""
    caps = caps if caps is not None else _DEFAULT_CAPS
    _check_size(data, caps)
    try:
        d = json.loads(data)
    except (ValueError, TypeError, RecursionError) as exc:
        raise ValidationError("state", f"not a valid session state ({exc})") from None
    if not isinstance(d, dict):
        raise ValidationError("state", "not a valid session state (not an object)")
    version = d.get("version", d.get("v"))
    if version == 1:
        _check_lengths(d, _V1_LISTS, caps)
        d = migrate_v1(d)
    elif version == VERSION:
        _check_lengths(d, _V3_LISTS, caps)
        d = v3_as_v2(d, caps)
    elif version != 2:
        raise ValidationError("state.version", f"unknown session state version {version!r}")
    _check_lengths(d, _V2_LISTS, caps)
    return _decode(_Reader(d, "state"), n_edges, caps)


_DEFAULT_CAPS = StateCaps.of(DEFAULT_CONFIG)
# the longest JSON text one value (with its key) of a state takes: a float's repr is at most
# 24 characters; the longest key is 12 ("init_pending") with quotes and a colon
VALUE_BYTES = 48
# the keys of the state's lists, both versions, as they appear in its JSON text
_LIST_KEYS = (
    *((k, k) for k in ("hyps", "live", "headings", "trail", "back")),
    *(("h", "hyps"), ("hd", "headings"), ("tr", "trail"), ("bk", "back")),
    *((k, k) for k in ("trail_time_ms", "trail_odo_cm")),
)


def max_values(caps: StateCaps) -> int:
    """The most values (numbers, strings, keys) a state within ``caps`` holds: its JSON text
    has fewer commas than this."""
    per_hyp = len(_HYP) + 2 * caps.path_edges + 1
    lists = caps.hyps * per_hyp + caps.live * (len(_LIVE) + 1) + 3 * (caps.headings + caps.trail)
    return lists + 3 * caps.path_edges + 64


def _check_size(data: bytes, caps: StateCaps) -> None:
    """Before parsing (which holds the GIL for as long as the text is long): a blob with more
    values, or more bytes, than a state within ``caps`` can hold is refused, naming the list
    that holds most of its values."""
    most = max_values(caps)
    if not isinstance(data, bytes | bytearray):
        return
    if len(data) > most * VALUE_BYTES:
        raise ValidationError(
            "state", f"the blob is {len(data)} bytes, over the limit of {most * VALUE_BYTES} that the "
            "matcher's caps allow",
        )  # fmt: skip
    n = data.count(b",")
    if n < most:
        return
    where = sorted((i, name) for key, name in _LIST_KEYS if (i := data.find(f'"{key}"'.encode())) >= 0)
    ends = [i for i, _ in where[1:]] + [len(data)]
    spans = [(data.count(b",", i, end), name) for (i, name), end in zip(where, ends, strict=True)]
    raise ValidationError(
        f"state.{max(spans)[1]}" if spans else "state",
        f"the blob holds {n + 1} values, over the limit of {most} that the matcher's caps allow",
    )


# the lists of each version's top level: (key, the name errors use, the cap's name)
_V2_LISTS = (
    ("hyps", "hyps", "hyps"),
    ("live", "live", "live"),
    ("headings", "headings", "headings"),
    ("trail", "trail", "trail"),
    ("back", "back", "path_edges"),
)
_V3_LISTS = (
    ("hyps", "hyps", "hyps"),
    ("live", "live", "live"),
    ("trail_time_ms", "trail_time_ms", "trail"),
    ("trail_odo_cm", "trail_odo_cm", "trail"),
    ("back", "back", "path_edges"),
)
_V1_LISTS = (("h", "hyps", "hyps"), ("live", "live", "live"), ("hd", "headings", "headings"),
             ("tr", "trail", "trail"), ("bk", "back", "path_edges"))  # fmt: skip


def _check_lengths(d: dict[str, Any], lists: tuple[tuple[str, str, str], ...], caps: StateCaps) -> None:
    for key, name, cap in lists:
        check_length(d.get(key), f"state.{name}", getattr(caps, cap))


def v3_as_v2(d: dict[str, Any], caps: StateCaps) -> dict[str, Any]:
    """Version 3's compact lists as version 2's pairs, checked, naming the version-3 key."""
    out = {k: v for k, v in d.items() if k not in ("trail_time_ms", "trail_odo_cm", "headings_f64")}
    times = _units(d, "trail_time_ms", 1000.0)
    odos = _units(d, "trail_odo_cm", 100.0)
    if len(odos) != len(times):
        raise ValidationError("state.trail_odo_cm", f"must hold as many items as trail_time_ms, {len(times)}")
    out["trail"] = [[t, o] for t, o in zip(times, odos, strict=True)]
    out["headings"] = _f64_pairs(d, "headings_f64", caps.headings)
    return out


def _units(d: dict[str, Any], key: str, per: float) -> list[float]:
    """A version-3 trail list: whole units, each after the first the difference from the one
    before, as floats of ``1 / per`` of a unit's scale."""
    if key not in d:
        raise ValidationError(f"state.{key}", "missing")
    v = d[key]
    if not isinstance(v, list):
        raise ValidationError(f"state.{key}", "must be a list")
    out, total = [], 0
    for i, step in enumerate(v):
        if type(step) is not int:
            raise ValidationError(f"state.{key}[{i}]", "must be a whole number")
        total += step
        if abs(total) > MAX_TRAIL_UNITS:
            raise ValidationError(f"state.{key}[{i}]", f"sums to more than {MAX_TRAIL_UNITS} in magnitude")
        out.append(total / per)
    return out


def _f64_pairs(d: dict[str, Any], key: str, cap: int) -> list[list[float]]:
    """Pairs of floats from their float64 values in base64 (at most ``cap`` pairs)."""
    if key not in d:
        raise ValidationError(f"state.{key}", "missing")
    v = d[key]
    if not isinstance(v, str):
        raise ValidationError(f"state.{key}", "must be a base64 string")
    if len(v) > 4 * math.ceil(16 * cap / 3):  # checked before it is decoded
        raise ValidationError(f"state.{key}", f"holds over {cap} pairs, over the limit of {cap}")
    try:
        raw = base64.b64decode(v, validate=True)
    except (binascii.Error, ValueError):
        raise ValidationError(f"state.{key}", "must be a base64 string") from None
    if len(raw) % 16:
        raise ValidationError(f"state.{key}", "must hold whole pairs of float64 values")
    if len(raw) > 16 * cap:
        raise ValidationError(f"state.{key}", f"holds {len(raw) // 16} pairs, over the limit of {cap}")
    flat: list[float] = np.frombuffer(raw, dtype="<f8").tolist()
    return [flat[i : i + 2] for i in range(0, len(flat), 2)]


def migrate_v1(d: dict[str, Any]) -> dict[str, Any]:
    """Version 1 (positional lists) as version 2; older layouts of v1 get its defaults."""

    def at(key: str, i: int, default: Any = _NAN) -> Any:
        seq = d.get(key)
        if not isinstance(seq, list) or i >= len(seq):
            if default is _MISSING:
                raise ValidationError(f"state.{key}", "missing or too short")
            return default
        return seq[i]

    try:
        odo = d["odo"]
        full = isinstance(odo, list) and len(odo) > 6
        hyps = []
        for i, a in enumerate(d["h"]):
            if not isinstance(a, list) or len(a) < 10:
                raise ValidationError(f"state.hyps[{i}]", "not a hypothesis")
            h = dict(zip(_HYP[:10], a[:10], strict=True))
            h["anc"], h["anc_sd"] = (a[10], a[11]) if len(a) > 11 else (_NAN, _NAN)
            hyps.append(h)
        b = d.get("b", [0.0, 0.0, _NAN, 0.0, _NAN])
        return {
            "version": 1,
            "time": d["t"],
            "x": at("xy", 0, _MISSING),
            "y": at("xy", 1, _MISSING),
            "odo": at("odo", 0, _MISSING),
            "gps_odo": at("odo", 1, _MISSING),
            "init_odo": at("odo", 2, _MISSING),
            "odo_k": at("odo", 3) if full else 0.0,
            "odo_kvar": at("odo", 4) if full else _NAN,
            "anc_odo": at("odo", 5) if full else _NAN,
            "anc_sd": at("odo", 6) if full else _NAN,
            "bad_time": at("bad", 0, _MISSING),
            "bad_odo": at("bad", 1, _MISSING),
            "init_pending": d["init"],
            "hyps": hyps,
            # rows of older layouts (not 8 values) are dropped, as version 1 did
            "live": [r for r in d["live"] if isinstance(r, list) and len(r) == 8],
            "live_fields": list(_LIVE),
            "headings": d["hd"],
            "res_pos2": at("res", 0, _MISSING),
            "res_head2": at("res", 1, _MISSING),
            "drift_sigma": at("res", 2, _MISSING),
            "search_time": at("res", 3, _MISSING),
            "shown": d.get("sh", -1),
            "bias": dict(zip(FixBias._fields, b, strict=False)) if isinstance(b, list) and len(b) == 5 else b,
            "trail": d.get("tr", []),
            "back": d.get("bk", []),
        }
    except KeyError as exc:
        raise ValidationError(f"state.{exc.args[0]}", "missing") from None
    except TypeError as exc:
        raise ValidationError("state", f"not a valid session state ({exc})") from None


_MISSING: Any = object()


class _Reader:
    """Typed access to one JSON object, naming ``path.key`` in every error."""

    def __init__(self, d: Any, path: str) -> None:
        if not isinstance(d, dict):
            raise ValidationError(path, "must be an object")
        self.d, self.path = d, path

    def name(self, key: str) -> str:
        return f"{self.path}.{key}"

    def get(self, key: str) -> Any:
        if key not in self.d:
            raise ValidationError(self.name(key), "missing")
        return self.d[key]

    def num(self, key: str, *, nan: bool = False, low: float | None = None, spread: bool = False) -> float:
        return _num(self.get(key), self.name(key), nan=nan, low=low, spread=spread)

    def int_(self, key: str, *, low: int, high: int | None = None) -> int:
        return _int(self.get(key), self.name(key), low=low, high=high)

    def list_(self, key: str) -> list[Any]:
        v = self.get(key)
        if not isinstance(v, list):
            raise ValidationError(self.name(key), "must be a list")
        return v


def _num(v: Any, name: str, *, nan: bool = False, low: float | None = None, spread: bool = False) -> float:
    """A number; NaN only when ``nan``; at least ``low``; a spread (σ, variance, distance: every
    field with a ``low``) at most :data:`MAX_MAGNITUDE` in magnitude."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ValidationError(name, f"must be a number, got {type(v).__name__}")
    f = float(v)
    if math.isnan(f):
        if not nan:
            raise ValidationError(name, "must be a finite number")
        return f
    if not math.isfinite(f):
        raise ValidationError(name, "must be a finite number")
    if (spread or low is not None) and abs(f) > MAX_MAGNITUDE:
        raise ValidationError(name, f"must be at most {MAX_MAGNITUDE:g} in magnitude")
    if low is not None and f < low:
        raise ValidationError(name, f"must be at least {low:g}")
    return f


def _int(v: Any, name: str, *, low: int, high: int | None = None) -> int:
    if isinstance(v, bool) or not isinstance(v, int | float) or v != v or v != int(v):
        raise ValidationError(name, "must be a whole number")
    i = int(v)
    if i < low or (high is not None and i >= high):
        raise ValidationError(name, f"must be in [{low}, {high if high is not None else 'inf'})")
    return i


def _pairs(seq: list[Any], name: str) -> list[tuple[Any, Any]]:
    out = []
    for i, p in enumerate(seq):
        if not isinstance(p, list) or len(p) != 2:
            raise ValidationError(f"{name}[{i}]", "must be a pair")
        out.append((p[0], p[1]))
    return out


def _decode(r: _Reader, n_edges: int | None, caps: StateCaps) -> SessionState:
    # every value is read in the order of the keys, so that the first bad one is named
    bias = _Reader(r.get("bias"), r.name("bias"))
    time, x, y = r.num("time", nan=True), r.num("x", nan=True), r.num("y", nan=True)
    odo, gps_odo = r.num("odo"), r.num("gps_odo")
    bad_time, bad_odo = r.num("bad_time", nan=True), r.num("bad_odo", nan=True)
    init_pending = _bool(r.get("init_pending"), r.name("init_pending"))
    init_odo = r.num("init_odo")
    hyps = [
        _hyp(_Reader(a, f"{r.name('hyps')}[{i}]"), n_edges, caps.path_edges)
        for i, a in enumerate(r.list_("hyps"))
    ]
    region = RegionState(live=_live(r, n_edges), init_pending=init_pending, init_odo=init_odo)
    headings = [
        [_num(o, f"{r.name('headings')}[{i}]"), _num(h, f"{r.name('headings')}[{i}]")]
        for i, (o, h) in enumerate(_pairs(r.list_("headings"), r.name("headings")))
    ]
    res_pos2, res_head2 = r.num("res_pos2", low=0.0), r.num("res_head2", low=0.0)
    drift_sigma = r.num("drift_sigma", low=0.0)
    speed = r.num("speed", nan=True, low=0.0) if "speed" in r.d else _NAN  # absent in older blobs
    search_time = r.num("search_time", nan=True)
    shown = r.int_("shown", low=-1, high=n_edges)
    vector = FixBias(
        bias.num("bx"),
        bias.num("by"),
        bias.num("pxx", nan=True, low=0.0),
        bias.num("pxy", spread=True),
        bias.num("pyy", nan=True, low=0.0),
    )
    anchor = AnchorState(
        odo_k=r.num("odo_k"),
        odo_kvar=r.num("odo_kvar", nan=True, low=0.0),
        anc_odo=r.num("anc_odo", nan=True),
        anc_sd=r.num("anc_sd", nan=True, low=0.0),
        chain=_chain(r, n_edges),
    )
    return SessionState(
        time=time, x=x, y=y, odo=odo, gps_odo=gps_odo, speed=speed,
        bad_time=bad_time, bad_odo=bad_odo, search_time=search_time, shown=shown,
        hyps=hyps, headings=headings, anchor=anchor,
        bias=BiasState(vector=vector, res_pos2=res_pos2, res_head2=res_head2, drift_sigma=drift_sigma),
        crossings=_crossings(r, n_edges),
        region=region,
    )  # fmt: skip


def _crossings(r: _Reader, n_edges: int | None) -> CrossingTrail:
    return CrossingTrail(
        trail=[
            TrailPoint(_num(t, f"{r.name('trail')}[{i}]"), _num(o, f"{r.name('trail')}[{i}]"))
            for i, (t, o) in enumerate(_pairs(r.list_("trail"), r.name("trail")))
        ],
        back=[
            BackEdge(
                _int(e, f"{r.name('back')}[{i}]", low=0, high=n_edges), _num(t, f"{r.name('back')}[{i}]")
            )
            for i, (e, t) in enumerate(_pairs(r.list_("back"), r.name("back")))
        ],
    )


def _bool(v: Any, name: str) -> bool:
    if not isinstance(v, bool):
        raise ValidationError(name, "must be true or false")
    return v


def _hyp(r: _Reader, n_edges: int | None, most_edges: int) -> Hypothesis:
    check_length(r.get("edges"), r.name("edges"), most_edges)
    check_length(r.get("enter"), r.name("enter"), most_edges)
    edges = _edge_list(r.list_("edges"), r.name("edges"), n_edges)
    if not edges:
        raise ValidationError(r.name("edges"), "must not be empty")
    k = r.int_("k", low=0, high=len(edges))
    enter = _time_list(r.list_("enter"), r.name("enter"))
    if len(enter) != k + 1:
        raise ValidationError(r.name("enter"), f"must hold k + 1 = {k + 1} times")
    return Hypothesis(
        edges=edges,
        k=k,
        off=r.num("off"),
        s=r.num("s"),
        logp=r.num("logp"),
        enter=enter,
        dist=r.num("dist", nan=True, low=0.0),
        px=r.num("px", nan=True),
        py=r.num("py", nan=True),
        bearing=r.num("bearing", nan=True),
        anc=r.num("anc", nan=True),
        anc_sd=r.num("anc_sd", nan=True, low=0.0),
    )


def _edge_list(v: list[Any], name: str, n_edges: int | None) -> list[int]:
    """Edge indices; all plain ints in range checked in one pass (a path may hold
    ``max_path_edges``), else item by item, naming the first bad one."""
    if all(type(e) is int for e in v) and (not v or (min(v) >= 0 and (n_edges is None or max(v) < n_edges))):
        return list(v)
    return [_int(e, f"{name}[{i}]", low=0, high=n_edges) for i, e in enumerate(v)]


def _time_list(v: list[Any], name: str) -> list[float]:
    """Finite numbers; all floats with a finite sum (so each is finite) checked in one pass,
    else item by item, naming the first bad one."""
    if all(type(t) is float for t in v) and math.isfinite(sum(v)):
        return list(v)
    return [_num(t, f"{name}[{i}]") for i, t in enumerate(v)]


def _live(r: _Reader, n_edges: int | None) -> list[LiveFix]:
    fields = r.list_("live_fields")
    if tuple(fields) != _LIVE:
        raise ValidationError(r.name("live_fields"), f"must be {list(_LIVE)}")
    out = []
    for i, row in enumerate(r.list_("live")):
        name = f"{r.name('live')}[{i}]"
        if not isinstance(row, list) or len(row) != len(_LIVE):
            raise ValidationError(name, f"must hold {len(_LIVE)} values")
        row_r = _Reader(dict(zip(_LIVE, row, strict=True)), name)
        gps = row_r.get("gps")
        if not isinstance(gps, bool):  # version 1 stored it as 0.0 / 1.0
            gps = _num(gps, row_r.name("gps")) != 0.0
        out.append(
            LiveFix(
                time=row_r.num("time"),
                edge=_int(row_r.get("edge"), row_r.name("edge"), low=0, high=n_edges),
                x=row_r.num("x"),
                y=row_r.num("y"),
                heading=row_r.num("heading", nan=True),
                sigma=row_r.num("sigma", low=0.0),
                kappa=row_r.num("kappa", low=0.0),
                gps=gps,
            )
        )
    return out


def _chain(r: _Reader, n_edges: int | None) -> ScaleChain:
    """The running scale estimate from the GPS (absent in older blobs, whose straight
    baseline ``base`` it replaces: none, it starts again)."""
    if "chain" not in r.d:
        return NO_CHAIN
    v = r.list_("chain")
    if len(v) != len(ScaleChain._fields):
        raise ValidationError(r.name("chain"), f"must hold {len(ScaleChain._fields)} numbers")
    name = r.name("chain")
    edge = _int(v[0], f"{name}[0]", low=-1, high=n_edges)
    off, time = _num(v[1], f"{name}[1]", nan=True), _num(v[2], f"{name}[2]", nan=True)
    dx = _num(v[3], f"{name}[3]", low=0.0)
    p, b = _num(v[4], f"{name}[4]", spread=True), _num(v[5], f"{name}[5]", spread=True)
    ppp = _num(v[6], f"{name}[6]", low=0.0)
    ppk, ppb, pkb = (_num(v[i], f"{name}[{i}]", spread=True) for i in (7, 8, 9))
    pbb = _num(v[10], f"{name}[10]", low=0.0)
    return ScaleChain(edge, off, time, dx, p, b, ppp, ppk, ppb, pkb, pbb)
