"""Equivalence harness for the online matcher's restructuring (issue #13).

Replays drives through whatever ``mapmatch`` is importable and records every ``SnapResult``
(edge, ids, offset, position, state, turn, candidates, correction), a session exported half way
(``SessionState.to_bytes``) and what the matcher does after importing it again, and a few batch
matches. Records are compared field by field, floats to 1e-9.

    # record with the old tree, compare with the new one
    PYTHONPATH=/work/wt/i13-base python tests/online_golden.py record --set full --out /tmp/old.json.gz
    PYTHONPATH=. python tests/online_golden.py compare --set full --golden /tmp/old.json.gz

``--set committed`` is the subset whose before-outputs are committed in
``tests/data/online_golden/`` (checked by ``tests/test_online_golden.py``); ``--set full`` adds
every drive of ``bench/bench_online.py``'s accuracy run (48 drives).
"""

from __future__ import annotations

import argparse
import base64
import gzip
import json
import math
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
TESTS = ROOT / "tests"
for p in (str(TESTS), str(ROOT / "bench")):
    if p not in sys.path:
        sys.path.insert(0, p)

from shared_data import DATA as SHARED  # noqa: E402  (MAPMATCH_SHARED, default ../shared)

GOLDEN_DIR = TESTS / "data" / "online_golden"
TOL = 1e-9

Drive = tuple[str, Callable[[], tuple[Any, list[Any]]]]  # name, () -> (graph, fixes)


# ------------------------------------------------------------------ records
def snap_record(r: Any) -> list[Any]:
    """A result as plain values (names fixed here, not taken from the dataclass)."""
    c = r.correction
    return [
        r.time,
        str(r.state),
        r.edge,
        r.u,
        r.v,
        r.way_id,
        r.offset,
        r.lat,
        r.lon,
        r.bearing,
        r.dist,
        str(r.turn),
        [[k.edge, k.u, k.v, k.way_id, k.probability, k.offset, k.dist] for k in r.candidates],
        None
        if c is None
        else [c.time_from, c.time_to, list(c.edges), list(c.replaced_edges), list(c.edge_times)],
        r.raw_lat,
        r.raw_lon,
    ]


INPUT_FIELDS = ("time", "lat", "lon", "heading", "pos_sigma", "heading_sigma", "speed", "distance")


def fixes_digest(fixes: list[Any]) -> list[float]:
    """Fingerprint of the input, so that a changed simulator is told apart from a changed matcher:
    the number of fixes, of valid GPS fixes and of covariances, and per field the sum of its
    finite values and the number of NaNs. Compared to 1e-9 (:func:`same_input`), it does not
    break on last-bit differences between library versions, as an exact hash of the floats did."""
    out = [float(len(fixes)), float(sum(bool(f.gps_valid) for f in fixes))]
    out.append(float(sum(f.pos_cov is not None for f in fixes)))
    for name in INPUT_FIELDS:
        v = np.array([getattr(f, name) for f in fixes], dtype=float)
        out += [float(np.nansum(v)), float(np.isnan(v).sum())]
    return out


def same_input(old: Any, new: list[float]) -> bool:
    """Whether two :func:`fixes_digest` fingerprints agree (to 1e-9, relative)."""
    return (
        isinstance(old, list)
        and len(old) == len(new)
        and all(math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9) for a, b in zip(old, new, strict=True))
    )


def replay(graph: Any, fixes: list[Any], *, export_at: int | None = None) -> dict[str, Any]:
    """Feed ``fixes`` to a fresh matcher; optionally export the session after ``export_at``
    fixes, and replay the rest from the imported session too."""
    from mapmatch.online import OnlineMatcher, SessionState

    m = OnlineMatcher(graph)
    st = m.new_session()
    out: dict[str, Any] = {"digest": fixes_digest(fixes), "snaps": [], "errors": []}
    blob = b""
    for i, f in enumerate(fixes):
        if export_at is not None and i == export_at:
            blob = st.to_bytes()
        out["snaps"].append(_update(m, st, f, out["errors"], i))
    if export_at is not None:
        out["state"] = base64.b64encode(blob).decode()
        st2 = SessionState.from_bytes(blob)
        errs: list[Any] = []
        out["resumed"] = [_update(m, st2, f, errs, i) for i, f in enumerate(fixes[export_at:], export_at)]
        out["resumed_errors"] = errs
    return out


def resume(graph: Any, fixes: list[Any], state_b64: str, export_at: int) -> list[Any]:
    """Import an exported session and replay the fixes after it."""
    from mapmatch.online import OnlineMatcher, SessionState

    m = OnlineMatcher(graph)
    st = SessionState.from_bytes(base64.b64decode(state_b64))
    return [_update(m, st, f, [], i) for i, f in enumerate(fixes[export_at:], export_at)]


def _update(m: Any, st: Any, f: Any, errors: list[Any], i: int) -> list[Any] | None:
    from mapmatch.errors import ValidationError

    try:
        return snap_record(m.update(st, f))
    except ValidationError as exc:
        errors.append([i, str(exc)])
        return None


def batch_record(graph: Any, track: Any) -> list[Any]:
    from mapmatch.batch import BatchMatcher

    r = BatchMatcher(graph).match(track)
    pts = [[str(p.status), p.edge, p.offset, p.lat, p.lon, p.dist] for p in r.points]
    return [pts, r.routes, r.splits, r.length_m, r.confidence]


# ------------------------------------------------------------------ drives
def service_drives() -> Iterator[Drive]:
    """The fixes the service tests stream (on their 3x3 city map)."""
    from online_helpers import DriveSpec, drive
    from service_util import city

    amap = city()
    plans: list[tuple[str, dict[str, Any]]] = [
        ("abc", {"speed": 10.0, "dt": 1.0, "sigma": 3.0}),
        ("adg", {"speed": 10.0, "dt": 1.0, "sigma": 3.0}),
        ("abe", {"speed": 10.0, "dt": 1.0, "sigma": 3.0}),
        ("abefc", {"speed": 10.0, "dt": 1.0, "noise": 1.5, "seed": 7, "sigma": 3.0}),
        ("def", {"dt": 0.5}),
        ("abcf", {"speed": 10.0, "dt": 1.0, "noise": 1.0, "seed": 5, "sigma": 3.0}),
        ("gdab", {"speed": 10.0, "dt": 1.0, "noise": 1.0, "seed": 5, "sigma": 3.0}),
        ("abefcb", {"speed": 10.0, "dt": 1.0, "noise": 4.0, "seed": 11, "heading_noise": 8.0}),
    ]
    for route, kw in plans:
        yield (f"city-{route}", lambda route=route, kw=kw: (amap.graph, drive(amap, route, DriveSpec(**kw))))


_MAPS: dict[str, Any] = {}


def bench_map(name: str) -> Any:
    from graph.build import BuildOptions, build_map

    if name not in _MAPS:
        if name == "helsinki":
            from bench_online import helsinki_pbf

            _MAPS[name] = build_map(helsinki_pbf(), options=BuildOptions(engine="osmnx"))
        elif name == "monaco":
            _MAPS[name] = build_map(SHARED / "osm" / "monaco.osm.pbf", options=BuildOptions(engine="osmnx"))
        else:
            _MAPS[name] = build_map(
                SHARED / "kubicka" / name / "roads.geojson", options=BuildOptions(engine="osmnx")
            )
    return _MAPS[name]


def bench_drives(
    names: list[str], rates: list[float], sigmas: list[float], outages: list[bool]
) -> Iterator[Drive]:
    """Drives exactly as ``bench_online.accuracy_runs`` makes them (same routes and seeds)."""
    from bench_online import simulate

    from mapmatch.sim.drive import read_route
    from mapmatch.sim.routes import random_route

    for name in names:

        def routes(name: str = name) -> list[tuple[str, Any]]:
            g = bench_map(name)
            rs: list[tuple[str, Any]] = []
            if name.isdigit():
                rs.append(("truth", read_route(g, SHARED / "kubicka" / name / "truth.geojson")))
            rng = np.random.default_rng(7)
            for i in range(1 if name in ("helsinki", "monaco") else 0):
                rs.append((f"random{i}", random_route(g, length_m=12000.0, rng=rng)))
            return rs

        n_routes = 1
        for ri in range(n_routes):
            for rate in rates:
                for sigma in sigmas:
                    for out in outages:

                        def make(name=name, ri=ri, rate=rate, sigma=sigma, out=out):  # type: ignore[no-untyped-def]
                            g = bench_map(name)
                            _, route = routes(name)[ri]
                            seed = int(sigma * 10 + rate)
                            d = simulate(g, route, rate=rate, sigma=sigma, seed=seed, outages=out)
                            return g, d.fix_objects()

                        yield (f"{name}-r{ri}-{rate:g}hz-s{sigma:g}-{'out' if out else 'gps'}", make)


BENCH_ALL = ["helsinki", "monaco", "00000000", "00000007", "00000014", "00000063"]


def drive_set(which: str) -> list[Drive]:
    drives = list(service_drives())
    if which == "committed":
        drives += bench_drives(["00000007"], [1.0], [3.0, 10.0], [False, True])
        drives += bench_drives(["monaco"], [1.0], [10.0], [True])
    elif which == "full":
        drives += bench_drives(BENCH_ALL, [1.0, 10.0], [3.0, 10.0], [False, True])
    return drives


def batch_cases(which: str) -> Iterator[tuple[str, Callable[[], tuple[Any, Any]]]]:
    """Batch matches: the service tests' city track, an ASCII-test map, Kubicka tracks."""
    from online_helpers import DriveSpec, drive
    from service_util import city

    from mapmatch.types import Track

    amap = city()

    def city_track(route: str, noise: float) -> tuple[Any, Any]:
        fx = drive(amap, route, DriveSpec(speed=10.0, dt=2.0, noise=noise, seed=3))
        return amap.graph, Track(route, np.array([f.time for f in fx]), np.array([f.lat for f in fx]),
                                 np.array([f.lon for f in fx]))  # fmt: skip

    yield "city-abefc", lambda: city_track("abefc", 2.0)
    yield "city-gdabc", lambda: city_track("gdabc", 6.0)
    kub = [("00000021", 10), ("00000007", 30)] + (
        [("00000021", 1), ("00000063", 5)] if which == "full" else []
    )
    for track, step in kub:

        def make(track: str = track, step: int = step) -> tuple[Any, Any]:
            from mapmatch.io import Columns, read_tracks

            d = SHARED / "kubicka" / track
            (t,) = read_tracks(d / "track.csv", columns=Columns(time="t"))
            idx = np.arange(0, len(t), step)
            t.time, t.lat, t.lon = t.time[idx], t.lat[idx], t.lon[idx]
            return bench_map(track), t

        yield f"kubicka-{track}-every{step}", make


# ------------------------------------------------------------------ record and compare
def record(which: str, *, log: Callable[[str], None] = print) -> dict[str, Any]:
    out: dict[str, Any] = {"drives": {}, "batch": {}}
    for name, make in drive_set(which):
        g, fixes = make()
        out["drives"][name] = replay(g, fixes, export_at=len(fixes) // 2)
        log(f"recorded {name}: {len(fixes)} fixes")
    for name, make in batch_cases(which):
        g, t = make()
        out["batch"][name] = batch_record(g, t)
        log(f"recorded batch {name}: {len(t.time)} points")
    return out


def diff(a: Any, b: Any, path: str = "") -> str | None:
    """The first difference between two records (floats to ``TOL``), or None."""
    if isinstance(a, float) or isinstance(b, float):
        if not isinstance(a, int | float) or not isinstance(b, int | float):
            return f"{path}: {a!r} != {b!r}"
        if math.isnan(a) and math.isnan(b):
            return None
        return None if abs(a - b) <= TOL else f"{path}: {a!r} != {b!r}"
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        if len(a) != len(b):
            return f"{path}: length {len(a)} != {len(b)}"
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            d = diff(x, y, f"{path}[{i}]")
            if d:
                return d
        return None
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return f"{path}: keys {sorted(set(a) ^ set(b))}"
        for k in a:
            d = diff(a[k], b[k], f"{path}.{k}")
            if d:
                return d
        return None
    return None if a == b else f"{path}: {a!r} != {b!r}"


def without_ways(snaps: list[Any]) -> list[Any]:
    """The records with their way ids blanked: since the map keeps its way pieces (issue #15)
    an answer names the way under the point, where the old code named the edge's first way."""
    out = []
    for r in snaps:
        if isinstance(r, list) and len(r) > 12:
            r = [*r[:5], None, *r[6:12], [[*k[:3], None, *k[4:]] for k in r[12]], *r[13:]]
        out.append(r)
    return out


def compare(which: str, golden: dict[str, Any], *, log: Callable[[str], None] = print) -> list[str]:
    """Replay every drive of ``which`` with the current code against ``golden``: the old
    session export is imported and replayed too. Returns the differences found."""
    problems: list[str] = []
    n_fix = 0
    for name, make in drive_set(which):
        old = golden["drives"].get(name)
        if old is None:
            problems.append(f"{name}: not in the golden record")
            continue
        g, fixes = make()
        if not same_input(old["digest"], fixes_digest(fixes)):
            problems.append(f"{name}: the input fixes differ (simulator changed?)")
            continue
        k = len(fixes) // 2
        new = replay(g, fixes, export_at=k)
        new_state = new.pop("state")
        d = diff(without_ways(old["snaps"]), without_ways(new["snaps"]), f"{name}.snaps") or diff(
            old["errors"], new["errors"], f"{name}.errors"
        )
        d = d or diff(
            without_ways(old["resumed"]), without_ways(new["resumed"]), f"{name}.resumed (own export)"
        )
        d = d or diff(
            without_ways(old["resumed"]),
            without_ways(resume(g, fixes, old["state"], k)),
            f"{name}.resumed (old export)",
        )
        n_fix += len(fixes) + 2 * (len(fixes) - k)
        if d:
            problems.append(d)
        log(f"{name}: {len(fixes)} fixes, {'DIFFERENT ' + d if d else 'identical'}"
            f"{'' if new_state == old['state'] else ' (state bytes re-encoded)'}")  # fmt: skip
    for name, make in batch_cases(which):
        g, t = make()
        d = diff(golden["batch"].get(name), batch_record(g, t), f"batch {name}")
        if d:
            problems.append(d)
        log(f"batch {name}: {len(t.time)} points, {'DIFFERENT ' + d if d else 'identical'}")
    log(f"compared {n_fix} fix results")
    return problems


def save(data: dict[str, Any], path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with gzip.open(path, "wt") as f:
        json.dump(data, f, separators=(",", ":"))


def load(path: Path) -> dict[str, Any]:
    with gzip.open(path, "rt") as f:
        return json.load(f)  # type: ignore[no-any-return]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("action", choices=["record", "compare"])
    ap.add_argument("--set", default="committed", choices=["committed", "full"])
    ap.add_argument("--out", type=Path, default=GOLDEN_DIR / "before.json.gz")
    ap.add_argument("--golden", type=Path, default=GOLDEN_DIR / "before.json.gz")
    args = ap.parse_args()
    import mapmatch

    print(f"# mapmatch from {mapmatch.__file__}")
    if args.action == "record":
        save(record(args.set), args.out)
        return 0
    problems = compare(args.set, load(args.golden))
    print("ALL IDENTICAL" if not problems else f"{len(problems)} DIFFERENCES")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
