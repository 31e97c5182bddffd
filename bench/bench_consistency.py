"""Checks that need no truth, on the shared Kubicka tracks: the count of violations per check.

**Denser input covers sparser input (batch).** Each track is matched in process at full rate
and sub-sampled every S seconds (S = 10 and 30 by default; the harness's sub-sampling: every
S-th fix and the last), on the adapter's map and route table (``bench/peers_adapter.py``). The
sparse route, cut before the projection of the first fix and after that of the last (as the
peers' scorer trims the truth), must lie within ``--buffer`` metres of the full-rate route: a
stretch of it farther than that and longer than ``--min-length`` metres is a stretch the
full-rate match lost, a violation. Prints per S the number of tracks that violate, and per
violating track the stretches' lengths and the routes' pieces. The check needs no truth; where
a track has one (``truth.geojson``), it tells a stretch of the true route the full-rate match
lost from a detour of the sparse match off the true route: each
stretch's length within ``--buffer`` of the true route and its greatest distance from it are
printed beside it. The headline figure, the one that must be zero, counts the tracks with a
stretch on the true route longer than ``--min-length`` (a track without a truth counts with
every stretch); the truth-free count stands beside it.

**10 Hz is never worse than 1 Hz (online, ``--online``).** Each track's drive with the seed
papers' five outages (``bench/bench_online_real.py``: the same seed at both rates) runs through
the online matcher at 1 Hz and at 10 Hz; a track whose correct road per fix at 10 Hz is more than
``--worse`` points below its figure at 1 Hz (live, as reported) is a violation. This check scores
against the drive's own true path.

    python bench/bench_consistency.py                  # all tracks, S = 10 and 30
    python bench/bench_consistency.py --ids 0,21 --S 10
    python bench/bench_consistency.py --online --ids 7,14   # also 10 Hz against 1 Hz online
    python bench/bench_consistency.py --S "" --online  # only the online check
    python bench/bench_consistency.py --online --docs  # also write docs/benchmarks/consistency*.md
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # this tree's mapmatch, not the installed one
    sys.path.insert(0, str(ROOT))
SHARED = Path(os.environ.get("MAPMATCH_SHARED") or ROOT.parent / "shared")
KUBICKA = SHARED / "data" / "kubicka"
PEERS = SHARED / "peers"


@dataclass(frozen=True, kw_only=True)
class CoverOptions:
    """How the sparse route is compared with the full-rate one."""

    buffer_m: float = 5.0
    """A point of the sparse route this close to the full-rate route is covered."""
    min_length_m: float = 30.0
    """An uncovered stretch longer than this is a violation."""


@dataclass(kw_only=True)
class TrackCover:
    """One track's result: per S the uncovered stretches' lengths, and the routes' pieces."""

    track: str
    fixes: int
    full_pieces: int
    missing_m: dict[int, list[float]] = field(default_factory=dict)
    off_truth_m: dict[int, list[float]] = field(default_factory=dict)
    """Per S, each stretch's greatest distance from the true route (NaN without a truth)."""
    on_truth_m: dict[int, list[float]] = field(default_factory=dict)
    """Per S, each stretch's length within the buffer of the true route (all of it without a
    truth: a stretch that cannot be told from a lost one counts as lost)."""
    near_fix: dict[int, list[int]] = field(default_factory=dict)
    """Per S, the index of the fix nearest to each stretch's start."""
    pieces: dict[int, int] = field(default_factory=dict)


def subsample(n: int, s: int) -> list[int]:
    """The harness's sub-sampling (``engines_kubicka.subsample``): every ``s``-th index and the last."""
    if str(PEERS) not in sys.path:
        sys.path.insert(0, str(PEERS))
    import engines_kubicka as ek  # type: ignore[import-not-found]

    return list(ek.subsample(n, s))


def check_track(track_dir: Path, Ss: list[int], options: CoverOptions) -> TrackCover:
    """Match one track at full rate and at every S in ``Ss`` and compare the routes."""
    if str(ROOT / "bench") not in sys.path:  # the adapter and the report helpers
        sys.path.insert(0, str(ROOT / "bench"))
    import peers_adapter  # type: ignore[import-not-found]

    from graph.projection import to_xy
    from mapmatch.io import Columns, read_tracks
    from mapmatch.route_score import farthest_from, read_route_geojson, trim_route_ends, uncovered_stretches
    from mapmatch.types import Track

    matcher = peers_adapter.load(track_dir)
    (t,) = read_tracks(track_dir / "track.csv", columns=Columns(time="t"))
    xy = to_xy(matcher.graph.crs, t.lon, t.lat)
    truth = None
    if (track_dir / "truth.geojson").is_file():
        _, parts, _ = read_route_geojson(track_dir / "truth.geojson")
        truth = [to_xy(matcher.graph.crs, p[:, 0], p[:, 1]) for p in parts]

    def route(idx: list[int]) -> Any:
        sub = Track(track_dir.name, t.time[idx], t.lat[idx], t.lon[idx])
        return matcher.match(sub, lonlat=False)

    full = route(list(range(len(t))))
    out = TrackCover(track=track_dir.name, fixes=len(t), full_pieces=len(full.route_xy))
    for s in Ss:
        sparse = route(subsample(len(t), s))
        trimmed = trim_route_ends(sparse.route_xy, first_xy=xy[0], last_xy=xy[-1])
        gaps = uncovered_stretches(
            full.route_xy, trimmed, buffer_m=options.buffer_m, min_length_m=options.min_length_m
        )
        out.missing_m[s] = [g.length_m for g in gaps]
        out.near_fix[s] = [int(np.hypot(*(xy - g.xy[0]).T).argmin()) for g in gaps]
        out.off_truth_m[s] = [farthest_from(truth, g.xy) if truth else float("nan") for g in gaps]
        out.on_truth_m[s] = [on_route_m(truth, g, options) if truth else g.length_m for g in gaps]
        out.pieces[s] = len(sparse.route_xy)
    return out


def on_route_m(route: list[Any], stretch: Any, options: CoverOptions) -> float:
    """The length of ``stretch`` (a :class:`~mapmatch.route_score.Stretch`) within
    ``options.buffer_m`` of ``route`` (pieces of polylines in metres)."""
    from mapmatch.route_score import uncovered_stretches

    off = uncovered_stretches(route, [stretch.xy], buffer_m=options.buffer_m, min_length_m=0.0)
    return max(stretch.length_m - sum(g.length_m for g in off), 0.0)


def lost_on_truth(r: TrackCover, s: int, options: CoverOptions) -> int:
    """How many of a track's stretches at ``s`` are lost stretches of the true route: longer
    than ``options.min_length_m`` within the buffer of it."""
    return sum(on > options.min_length_m for on in r.on_truth_m[s])


def summary(results: list[TrackCover], Ss: list[int], options: CoverOptions) -> str:
    """The violation counts per check and the violating tracks, as printed text."""
    lines = [
        f"{len(results)} tracks; a stretch: a stretch of the route at S longer than "
        f"{options.min_length_m:g} m farther than {options.buffer_m:g} m from the full-rate route "
        "(no truth needed); lost on truth: a track with such a stretch of which more than "
        f"{options.min_length_m:g} m lie within {options.buffer_m:g} m of the true route (the "
        "headline, the goal is zero); the rest are detours of the sparse route off the true one",
        "",
        f"{'check':30s} {'lost on truth':>13s} {'violations':>10s} {'stretches':>9s} {'missing m':>9s} "
        f"{'on truth m':>10s}",
    ]
    for s in Ss:
        bad = [r for r in results if r.missing_m[s]]
        lost = sum(lost_on_truth(r, s, options) > 0 for r in bad)
        n = sum(len(r.missing_m[s]) for r in bad)
        m = sum(sum(r.missing_m[s]) for r in bad)
        on = sum(sum(r.on_truth_m[s]) for r in bad)
        lines.append(
            f"{f'full rate covers S = {s} s':30s} {lost:13d} {len(bad):10d} {n:9d} {m:9.0f} {on:10.0f}"
        )
    lines.append("")
    for s in Ss:
        for r in results:
            if r.missing_m[s]:
                gaps = ", ".join(
                    f"{g:.0f} m from fix {k} of {r.fixes} ({on:.0f} m of it within {options.buffer_m:g} m "
                    f"of the truth, at most {d:.0f} m from it)"
                    for g, k, d, on in sorted(
                        zip(r.missing_m[s], r.near_fix[s], r.off_truth_m[s], r.on_truth_m[s], strict=True),
                        reverse=True,
                    )
                )
                lines.append(
                    f"S = {s:2d} s  track {r.track}: missing at full rate {gaps}; "
                    f"pieces: full rate {r.full_pieces}, S = {s} s {r.pieces[s]}"
                )
    if all(not r.missing_m[s] for r in results for s in Ss):
        lines.append("no track violates")
    return "\n".join(lines)


@dataclass(frozen=True, kw_only=True)
class RateCompare:
    """One track's correct road per fix (percent of the scored fixes) online at 1 and 10 Hz."""

    track: str
    live_1hz: float
    live_10hz: float
    corrected_1hz: float
    corrected_10hz: float


def compare_rates(track_dir: Path) -> RateCompare:
    """Run one track's drive with the outages at 1 Hz and at 10 Hz through the online matcher."""
    if str(ROOT / "bench") not in sys.path:
        sys.path.insert(0, str(ROOT / "bench"))
    import bench_online_real as bor  # type: ignore[import-not-found]

    graph = bor.load_graph(track_dir, None)
    matcher = bor.OnlineMatcher(graph, config=bor.DEFAULT_CONFIG)
    pct: dict[tuple[str, int], float] = {}
    for rate in (1, 10):
        row = bor.run_one(graph, matcher, track_dir, rate=float(rate), outages=True, seed=int(track_dir.name))
        for tag in ("live", "fin"):
            pct[(tag, rate)] = 100.0 * row[f"ok_{tag}"] / max(row["scored"], 1)
    return RateCompare(
        track=track_dir.name,
        live_1hz=pct[("live", 1)],
        live_10hz=pct[("live", 10)],
        corrected_1hz=pct[("fin", 1)],
        corrected_10hz=pct[("fin", 10)],
    )


def rate_summary(results: list[RateCompare], *, worse: float) -> str:
    """The violations of "10 Hz is never worse than 1 Hz", as printed text."""
    bad = [r for r in results if r.live_10hz < r.live_1hz - worse]
    bad_fin = [r for r in results if r.corrected_10hz < r.corrected_1hz - worse]
    lines = [
        f"{len(results)} tracks, drives with the five outages; a violation: correct road per fix "
        f"at 10 Hz more than {worse:g} points below 1 Hz (the check: live; corrected for reference)",
        "",
        f"{'check':40s} {'violations':>10s}",
        f"{'10 Hz not worse than 1 Hz, live':40s} {len(bad):10d}",
        f"{'10 Hz not worse than 1 Hz, corrected':40s} {len(bad_fin):10d}",
        "",
        f"{'track':8s} {'live 1 Hz':>9s} {'live 10 Hz':>10s} {'corr. 1 Hz':>10s} {'corr. 10 Hz':>11s}",
    ]
    for r in results:
        mark = "  violation, live" if r in bad else ""
        mark += "  violation, corrected" if r in bad_fin else ""
        lines.append(
            f"{r.track:8s} {r.live_1hz:8.2f}% {r.live_10hz:9.2f}% {r.corrected_1hz:9.2f}% "
            f"{r.corrected_10hz:10.2f}%{mark}"
        )
    return "\n".join(lines)


def track_dirs(ids: str) -> list[Path]:
    """The Kubicka track folders: all, or those of comma-separated numbers."""
    dirs = sorted(p for p in KUBICKA.iterdir() if p.is_dir() and p.name.isdigit())
    if ids != "all":
        wanted = {int(x) for x in ids.split(",")}
        dirs = [p for p in dirs if int(p.name) in wanted]
    return dirs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ids", default="all", help="all, or comma-separated track numbers")
    ap.add_argument(
        "--S",
        default="10,30",
        help="the sparse sub-samplings, seconds, comma-separated (empty: no batch check)",
    )
    ap.add_argument("--buffer", type=float, default=CoverOptions.buffer_m, help="metres")
    ap.add_argument("--min-length", type=float, default=CoverOptions.min_length_m, help="metres")
    ap.add_argument("--online", action="store_true", help="also compare 10 Hz with 1 Hz online")
    ap.add_argument("--worse", type=float, default=0.5, help="points of correct road (--online)")
    ap.add_argument(
        "--docs",
        action="store_true",
        help="also write docs/benchmarks/consistency.md (and consistency_online.md)",
    )
    a = ap.parse_args()
    if not KUBICKA.is_dir() or not PEERS.is_dir():
        print(f"needs {KUBICKA} and {PEERS} (set MAPMATCH_SHARED)", file=sys.stderr)
        return 2
    Ss = [int(x) for x in a.S.split(",") if x.strip()]
    options = CoverOptions(buffer_m=a.buffer, min_length_m=a.min_length)
    results = []
    for d in track_dirs(a.ids) if Ss else []:
        r = check_track(d, Ss, options)
        results.append(r)
        print(
            f"checked {d.name}: missing m {r.missing_m}, pieces {r.full_pieces} {r.pieces}", file=sys.stderr
        )
    rates = []
    for d in track_dirs(a.ids) if a.online else []:
        rates.append(compare_rates(d))
        print(f"online {d.name}: {rates[-1]}", file=sys.stderr, flush=True)
    texts = {}
    if Ss:
        texts["consistency"] = summary(results, Ss, options)
    if a.online:
        texts["consistency_online"] = rate_summary(rates, worse=a.worse)
    load = f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())} ({os.cpu_count()} cores)"
    for name, text in texts.items():
        print(f"{text}\n{load}\n")
        if a.docs:
            from report import fenced, run_header, write_fragment  # type: ignore[import-not-found]

            print(f"wrote {write_fragment(name, run_header() + fenced(text + chr(10) + load))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
