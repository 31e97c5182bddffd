"""Batch matching against the peers (Valhalla, OSRM, fastmm) on the shared Kubicka tracks.

Runs ``../shared/peers/run_peers.py`` (or ``$MAPMATCH_PEERS/run_peers.py``) with our matcher as the
custom engine (``bench/peers_adapter.py``), so every engine is scored by the peers' ``score.py``.
The harness times each call once; with ``--repeat K`` (the default) every engine is then timed
again by ``bench/peers_timing.py`` in its own Python, the same loop for all: per track and S one
warm-up call, then K timed calls, and the least of them (best of K) replaces the harness's
single time; the median is kept too. On a shared machine the least is the figure least
disturbed by the other processes (a 0.5 ms call loses whole time slices under load).
Prints mean and median RMF and points/s per engine and S, the per-track
geometric mean of our points/s over fastmm's per S, our time per point at S = 30 on the largest
vs the smallest map (timed apart, as above, and side by side in one process, in alternating
rounds of five calls on each: the check's figure, ``--side-rounds``) with each of those two
tracks' candidates a fix and candidate pairs a step (which the time per point follows), and one
PASS/FAIL line per target of issues #14 and #48 (the latter: against Valhalla with
``fixed_speed`` 120, the per-track shares of any gap printed).

    python bench/bench_batch.py                       # all tracks, S = 1, 10, 30
    python bench/bench_batch.py --ids 0,21 --engines custom,fastmm     # a quick check
    python bench/bench_batch.py --engines custom,fastmm --repeat 9      # speed only, 9 timed calls
    python bench/bench_batch.py --summary ~/.cache/mapmatch-peers/results/batch.jsonl
    python bench/bench_batch.py --routing --ids 0,28      # bounded search vs UBODT, in process
    python bench/bench_batch.py --fixed --ids 14,21       # time per call on tiny tracks, in process
    python bench/bench_batch.py --docs     # also write the summary into the docs (bench/report.py)
    python bench/bench_batch.py --cv --grid model.gps_sigma=5,8,12   # out-of-fold RMF, in process

``--cv`` matches every track at each S in process under every setting of ``--grid`` (on the
batch defaults), scores it with the peers' ``score.py``, chooses on four of the folds of
``bench/folds.py`` and scores the fifth (``bench/crossval.py``), and prints the out-of-fold mean
and median RMF beside the in-sample ones (``--docs``: the fragment ``cv_batch``).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import statistics
import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # the in-process modes use this tree's mapmatch, not the installed one
    sys.path.insert(0, str(ROOT))
PEERS = Path(
    os.environ.get("MAPMATCH_PEERS")
    # the nearest folder above the project with shared/peers (a worktree sits one level deeper)
    or next((d / "shared" / "peers" for d in ROOT.parents if (d / "shared" / "peers").is_dir()), "")
    or ROOT.parent / "shared" / "peers"
)
CACHE = Path(os.path.expanduser("~/.cache/mapmatch-peers"))
PEERS_PY = CACHE / "venvs" / "venv" / "bin" / "python"


def run(ids: str, engines: str, S: str, tag: str) -> Path:
    env = dict(os.environ)
    env["MM_PEERS_CUSTOM"] = str(ROOT / "bench" / "peers_adapter.py")
    env["MM_PEERS_CUSTOM_PY"] = sys.executable
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    cmd = [str(PEERS_PY), str(PEERS / "run_peers.py"), "--engines", engines, "--S", S, "--tag", tag]
    if ids != "all":
        cmd += ["--ids", ids]
    subprocess.run(cmd, env=env, check=True)
    return CACHE / "results" / f"{tag}.jsonl"


ENGINE_VENV = {
    "osrm": "venv312",
    "valhalla": "venv312",
    "valhalla_nots": "venv312",
    "valhalla_fs120": "venv312",
}
"""The peers' venv of each engine (as the harness's ``ENGINE_PY``; the rest use ``venv``)."""
WORK = CACHE / "work"
"""The peers' prepared work dirs, one per track (made by ``run_peers.py``)."""


def engine_python(eng: str) -> str:
    """The Python that runs ``eng``: ours this one, a peer its own venv's."""
    if eng == "custom":
        return sys.executable
    return str(CACHE / "venvs" / ENGINE_VENV.get(eng, "venv") / "bin" / "python")


def worker_env() -> dict[str, str]:
    """The environment of a worker run in an engine's Python (ours as the custom engine)."""
    env = dict(os.environ)
    env["MM_PEERS_CUSTOM"] = str(ROOT / "bench" / "peers_adapter.py")
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("PEERS_DIR", str(CACHE / "venvs"))
    return env


def work_tracks(ids: str) -> list[str]:
    """The prepared work dirs' track names: all, or those of comma-separated numbers."""
    names = sorted(p.name for p in WORK.iterdir() if p.is_dir() and p.name.isdigit())
    if ids != "all":
        names = [n for n in names if int(n) in {int(x) for x in ids.split(",")}]
    return names


def time_engines(ids: str, engines: str, S: str, repeat: int, tag: str) -> Path:
    """Time every engine on every track again (``peers_timing.py``): one warm-up call, then
    ``repeat`` timed calls per S. Returns the JSON-lines file of the timings."""
    env = worker_env()
    names = work_tracks(ids)
    out = CACHE / "results" / f"{tag}_timing.jsonl"
    lines = []
    for name in names:
        for eng in engines.split(","):
            py = engine_python(eng)
            tmp = WORK / name / f"timing_{eng}.json"
            cmd = [py, str(ROOT / "bench" / "peers_timing.py"), eng, str(WORK / name), str(tmp)]
            cmd += ["--S", S, "--repeat", str(repeat), "--peers", str(PEERS)]
            r = subprocess.run(cmd, env=env, capture_output=True, text=True)
            if r.returncode != 0:
                print(f"timing {eng} on {name} failed: {r.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
                continue
            res = json.loads(tmp.read_text())
            for run_ in res["runs"]:
                lines.append(json.dumps({"engine": eng, "track": name, **run_}))
            print(f"timed {name} {eng}", file=sys.stderr, flush=True)
    out.write_text("\n".join(lines) + "\n")
    return out


def apply_timing(recs: list[dict], timing: Path) -> int:
    """Replace each record's ``match_s`` with the least of its repeated timings (the median goes
    to ``match_median_s``); returns how many."""
    t = {}
    for line in timing.read_text().splitlines():
        if line.strip():
            r = json.loads(line)
            t[(r["engine"], r["track"], int(r["S"]))] = r
    n = 0
    for r in recs:
        got = t.get((r["engine"], r["track"], int(r["S"])))
        if got and r.get("match_s"):
            r["match_s_harness"], r["match_s"], r["match_median_s"] = (
                r["match_s"],
                got["min_s"],
                got["median_s"],
            )
            n += 1
    return n


Check = tuple[str, bool | None, str]
"""One "Done means" target: label, passed (``None``: not measured), figures."""


def _load_records(paths: list[Path], timing: Path | None) -> list[dict]:
    """The runs in ``paths`` that were not skipped, re-timed from ``timing`` when given."""
    recs = [json.loads(line) for p in paths for line in p.read_text().splitlines() if line.strip()]
    recs = [r for r in recs if not r.get("skipped")]
    if timing is not None:
        reps = {len(json.loads(x)["times_s"]) for x in timing.read_text().splitlines() if x.strip()}
        n = apply_timing(recs, timing)
        print(
            f"\ntiming: {n} of {len(recs)} (track, engine, S) runs timed again by bench/peers_timing.py, "
            f"each engine in its own process per track: one warm-up call, then {'/'.join(map(str, reps))} "
            "timed calls; match s below is the least of them, best of K (the median is match_median_s, "
            "the harness's single warm call match_s_harness)"
        )
    else:
        print("\ntiming: the harness's own (one warm call per track and S, after one first call)")
    return recs


RmfByRun = dict[tuple[str, int], float]
"""An RMF figure per (engine, S)."""


def _print_table(by: dict[tuple[str, int], list[dict]]) -> tuple[RmfByRun, RmfByRun]:
    """Print one row per (engine, S); return the mean and the median RMF of each."""
    print(
        f"\n{'engine':10s} {'S':>3s} {'tracks':>6s} {'fail':>4s} {'mean RMF':>9s} {'median RMF':>10s} "
        f"{'points':>8s} {'match s':>8s} {'pts/s':>9s}"
    )
    mean_rmf: dict[tuple[str, int], float] = {}
    med_rmf: dict[tuple[str, int], float] = {}
    for (eng, s), g in sorted(by.items(), key=lambda kv: (kv[0][0] != "custom", kv[0][0], kv[0][1])):
        rmf = [r["rmf"] if r.get("rmf") is not None else 1.0 for r in g]  # a failed match scores 1
        mean_rmf[(eng, s)], med_rmf[(eng, s)] = statistics.fmean(rmf), statistics.median(rmf)
        timed = [r for r in g if r.get("match_s")]
        pts = sum(r["n_points"] for r in timed)
        secs = sum(r["match_s"] for r in timed)
        fails = sum(1 for r in g if r.get("failed"))
        print(
            f"{eng:10s} {s:3d} {len(g):6d} {fails:4d} {mean_rmf[(eng, s)]:9.4f} {med_rmf[(eng, s)]:10.4f} "
            f"{pts:8d} {secs:8.3f} {pts / secs if secs else 0:9.0f}"
        )
    return mean_rmf, med_rmf


def _rmf_checks(
    Ss: list[int],
    peers: list[str],
    mean_rmf: RmfByRun,
    med_rmf: RmfByRun,
) -> list[Check]:
    """Mean and median RMF of ours against the best peer's at each S."""
    mean_txt, med_txt, mean_ok, med_ok = [], [], True, True
    for s in Ss:
        if ("custom", s) not in mean_rmf or not any((e, s) in mean_rmf for e in peers):
            mean_ok = med_ok = False
            continue
        bm = min(mean_rmf[(e, s)] for e in peers if (e, s) in mean_rmf)
        bd = min(med_rmf[(e, s)] for e in peers if (e, s) in med_rmf)
        om, od = mean_rmf[("custom", s)], med_rmf[("custom", s)]
        mean_ok &= om <= 0.5 * bm
        med_ok &= od <= bd
        mean_txt.append(f"S={s}: {om:.4f} vs best peer {bm:.4f}")
        med_txt.append(f"S={s}: {od:.4f} vs best peer {bd:.4f}")
    return [
        ("mean RMF at most half the best peer's at every S", mean_ok, "; ".join(mean_txt)),
        ("median RMF at or below the best peer's at every S", med_ok, "; ".join(med_txt)),
    ]


REFERENCE = "valhalla_fs120"
"""The peer the batch target names: Valhalla with ``fixed_speed`` 120 km/h, its strongest setting."""


def _reference_check(Ss: list[int], mean_rmf: RmfByRun) -> Check:
    """Our mean RMF against half of :data:`REFERENCE`'s at every S (not measured without it)."""
    if not any((REFERENCE, s) in mean_rmf for s in Ss):
        return (f"mean RMF at most half of {REFERENCE}'s at every S", None, f"no {REFERENCE} run")
    ok, txt = True, []
    for s in Ss:
        if ("custom", s) not in mean_rmf or (REFERENCE, s) not in mean_rmf:
            ok = False
            continue
        om, vm = mean_rmf[("custom", s)], mean_rmf[(REFERENCE, s)]
        ok &= om <= 0.5 * vm
        txt.append(f"S={s}: {om:.4f} vs {vm:.4f} (ratio {om / vm:.2f})")
    return (f"mean RMF at most half of {REFERENCE}'s at every S", ok, "; ".join(txt))


def gap_tracks(by: dict[tuple[str, int], list[dict]], Ss: list[int], *, top: int = 8) -> list[str]:
    """Per S, the tracks that carry our mean RMF above half of :data:`REFERENCE`'s: each track's
    excess, our RMF less half of the reference's on it, over the number of tracks (the excesses sum
    to our mean less half of the reference's mean), the largest ``top`` first; as printed lines."""
    lines: list[str] = []
    for s in Ss:
        ours = {r["track"]: r.get("rmf") for r in by.get(("custom", s), [])}
        ref = {r["track"]: r.get("rmf") for r in by.get((REFERENCE, s), [])}
        common = sorted(set(ours) & set(ref))
        if not common:
            continue
        rmf = {t: (1.0 if ours[t] is None else ours[t], 1.0 if ref[t] is None else ref[t]) for t in common}
        excess = {t: (o - 0.5 * v) / len(common) for t, (o, v) in rmf.items()}
        total = sum(excess.values())
        lines.append(
            f"S={s:2d}: our mean less half of {REFERENCE}'s {total:+.4f} over {len(common)} tracks; "
            f"largest shares (track: ours / {REFERENCE} RMF, share of the mean):"
        )
        worst = sorted(common, key=lambda t: -excess[t])[:top]
        lines.append(
            "       " + "; ".join(f"{t}: {rmf[t][0]:.4f} / {rmf[t][1]:.4f}, {excess[t]:+.4f}" for t in worst)
        )
    return lines


def _speed_check(Ss: list[int], by: dict[tuple[str, int], list[dict]]) -> Check:
    """Per track, our points/s over fastmm's (same points), geometric mean over tracks."""
    speed_txt, speed_ok = [], bool(Ss)
    for s in Ss:
        ours = {r["track"]: r["match_s"] for r in by.get(("custom", s), []) if r.get("match_s")}
        fm = {r["track"]: r["match_s"] for r in by.get(("fastmm", s), []) if r.get("match_s")}
        common = sorted(set(ours) & set(fm))
        if not common:
            speed_ok = False
            speed_txt.append(f"S={s}: no tracks timed by both")
            continue
        ratios = [fm[t] / ours[t] for t in common]
        gm = math.exp(statistics.fmean(math.log(x) for x in ratios))
        speed_ok &= gm >= 1.5
        print(
            f"S={s:2d}: per-track geometric mean of our points/s over fastmm's {gm:.2f} "
            f"({len(common)} tracks, min {min(ratios):.2f} on {common[ratios.index(min(ratios))]}, "
            f"max {max(ratios):.2f})"
        )
        speed_txt.append(f"S={s}: {gm:.2f}")
    return (
        "per-track geometric-mean speed at least 1.5x fastmm's at every S",
        speed_ok,
        "; ".join(speed_txt),
    )


def _growth_side(small: dict, big: dict, side_rounds: int) -> tuple[bool, str]:
    """The growth check timed side by side in one process; print the figures."""
    (ls, ms), (lb, mb) = growth_side_by_side(small["track"], big["track"], S=30, rounds=side_rounds)
    side_ok = lb / ls < 2.0
    side = (
        f"side by side in one process ({side_rounds} rounds of 5 calls each, alternating): "
        f"{ls:.2f} and {lb:.2f} us, ratio {lb / ls:.2f} "
        f"(medians {ms:.2f} and {mb:.2f} us, ratio {mb / ms:.2f})"
    )
    print(f"S=30: our time per point, {side}")
    # not the check: the same with SETTLE untimed calls first in each block
    (ls, ms), (lb, mb) = growth_side_by_side(
        small["track"], big["track"], S=30, rounds=side_rounds, settle=SETTLE
    )
    print(
        f"S=30: our time per point, side by side, each block's first {SETTLE} calls untimed "
        f"(not the check; see growth_side_by_side): {ls:.2f} and {lb:.2f} us, ratio {lb / ls:.2f} "
        f"(medians {ms:.2f} and {mb:.2f} us, ratio {mb / ms:.2f})"
    )
    return side_ok, side


def _growth_check(by: dict[tuple[str, int], list[dict]], side_rounds: int) -> Check:
    """Time per point at 30 s: largest map over smallest map."""
    growth: bool | None = None
    growth_txt = "no S=30 run"
    ours30 = [r for r in by.get(("custom", 30), []) if r.get("match_s")]
    if ours30:
        small = min(ours30, key=lambda r: r["arcs"])
        big = max(ours30, key=lambda r: r["arcs"])
        us, ub = (r["match_s"] / r["n_points"] * 1e6 for r in (small, big))
        growth = ub / us < 2.0
        growth_txt = (
            f"smallest map {small['track']} ({small['arcs']} arcs, {small['n_points']} points) {us:.2f} us, "
            f"largest {big['track']} ({big['arcs']} arcs, {big['n_points']} points) {ub:.2f} us, "
            f"ratio {ub / us:.2f}"
        )
        if small.get("match_median_s") and big.get("match_median_s"):
            ms, mb = (r["match_median_s"] / r["n_points"] * 1e6 for r in (small, big))
            growth_txt += f" (medians {ms:.2f} and {mb:.2f} us, ratio {mb / ms:.2f})"
        print(f"S=30: our time per point: {growth_txt}")
        if side_rounds > 0:
            growth, side = _growth_side(small, big, side_rounds)
            growth_txt = f"{side}; timed apart as above: ratio {ub / us:.2f}"
    return (
        "time per point at 30 s grows less than 2x from the smallest to the largest map",
        growth,
        growth_txt,
    )


def summarise(paths: list[Path], timing: Path | None = None, *, side_rounds: int = 0) -> bool:
    """Print the table, the speed figures and one pass/fail line per "Done means" target of
    issues #14 and #48; returns whether all pass."""
    recs = _load_records(paths, timing)
    by: dict[tuple[str, int], list[dict]] = defaultdict(list)
    for r in recs:
        by[(r["engine"], int(r["S"]))].append(r)
    Ss = sorted({s for _, s in by})
    mean_rmf, med_rmf = _print_table(by)
    peers = sorted({e for e, _ in by} - {"custom"})
    checks = _rmf_checks(Ss, peers, mean_rmf, med_rmf)
    checks.append(_reference_check(Ss, mean_rmf))
    if any(eng == REFERENCE for eng, _ in by):
        print("\n" + "\n".join(gap_tracks(by, Ss)))
    checks.append(_speed_check(Ss, by))
    checks.append(_growth_check(by, side_rounds))
    print("\nissues #14 and #48, done means:")
    for label, ok, txt in checks:
        print(f"  {'PASS' if ok else 'FAIL'}  {label}: {txt}")
    return all(ok for _, ok, _ in checks)


SETTLE = 20
"""Untimed calls at the start of each block in the growth check's second, informational figure."""


def growth_side_by_side(
    small: str, big: str, *, S: int, rounds: int, block: int = 5, settle: int = 0
) -> list[tuple[float, float]]:
    """Our time per point (µs) at ``S`` on two prepared work dirs, timed side by side in this
    process: after ``rounds`` untimed rounds, ``rounds`` timed rounds of ``block`` calls on each
    in turn, so both meet the same machine (whose speed moves by up to 2x within minutes, which
    makes two tracks timed minutes apart, as above, a poor ratio), and each block runs on its own
    map as a batch does (single calls alternating would start every call in the other map's
    cache). The harness's sub-sampling, and our adapter's load and timed call. Returns (least,
    median) per track.

    ``settle`` untimed calls open each block. After a switch the larger map's calls take
    several blocks' worth of calls to settle (REAL 00000028 at 30 s, medians by call: 2.4, 2.0,
    1.8, 1.7 ... 1.5 us by the tenth), whether the calls before were on the smaller map or on
    the same track at S = 1; after a 32 MB write that empties the caches, two calls. So the
    check's figure (``settle`` 0) includes what the processor relearns after a switch of
    workload, as the harness's single timed call does."""
    import time

    import peers_adapter  # type: ignore[import-not-found]

    calls = _growth_calls(small, big, S)
    if settle == 0:
        for name, (m, _tt, la, lo) in zip((small, big), calls, strict=True):
            cands, pairs = candidate_load(m, la, lo)
            print(f"S={S}: {name}: {cands:.2f} candidates a fix, {pairs:.1f} candidate pairs a step")
    times: list[list[float]] = [[], []]
    for r in range(2 * rounds):
        for k, (m, tt, la, lo) in enumerate(calls):
            for c in range(settle + block):
                t0 = time.perf_counter()
                peers_adapter.call(m, tt, la, lo)
                dt = time.perf_counter() - t0
                if r >= rounds and c >= settle:
                    times[k].append(dt / len(tt) * 1e6)
    return [(min(x), statistics.median(x)) for x in times]


@functools.cache
def _growth_calls(small: str, big: str, S: int) -> list[tuple[Any, list[float], list[float], list[float]]]:
    """Our adapter's matcher and the harness's sub-sampled track (times, lat, lon) for each work dir."""
    sys.path.insert(0, str(ROOT / "bench"))
    sys.path.insert(0, str(PEERS))
    import engines_kubicka as ek  # type: ignore[import-not-found]
    import peers_adapter  # type: ignore[import-not-found]

    calls = []
    for name in (small, big):
        matcher = peers_adapter.load(WORK / name)
        t, lat, lon = ek.read_track(WORK / name)
        idx = ek.subsample(len(t), S)
        calls.append((matcher, [t[i] for i in idx], [lat[i] for i in idx], [lon[i] for i in idx]))
    return calls


def candidate_load(matcher: Any, lat: list[float], lon: list[float]) -> tuple[float, float]:
    """Mean candidates a fix and candidate pairs a Viterbi step (each fix's roads within the
    search radius, nearest ``max_candidates`` and their reverse twins, as the matcher queries
    them): the time per point follows these (the roads near the track), not the map's size."""
    import numpy as np

    from graph.projection import to_xy
    from mapmatch.gridindex import GridIndex

    cfg = matcher.config
    xy = to_xy(matcher.graph.crs, np.asarray(lon, dtype=np.float64), np.asarray(lat, dtype=np.float64))
    grid = GridIndex(matcher.index, cell=cfg.model.search_radius)
    found = grid.query(xy, cfg.model.search_radius, k=cfg.model.max_candidates)
    n = np.bincount(found.point, minlength=len(xy)).astype(np.float64)
    return float(n.mean()), float(np.mean(n[1:] * n[:-1])) if len(n) > 1 else 0.0


def _tracks(ids: str) -> tuple[Any, Path, list[str]]:
    """The adapter module, the Kubicka folder and the chosen track folders' names."""
    sys.path.insert(0, str(ROOT / "bench"))
    import peers_adapter  # type: ignore[import-not-found]

    data = PEERS.parent / "data" / "kubicka"
    names = sorted(p.name for p in data.iterdir() if p.is_dir())
    if ids != "all":
        names = [n for n in names if int(n) in {int(x) for x in ids.split(",")}]
    return peers_adapter, data, names


def compare_routing(ids: str, S: str, deltas: str) -> None:
    """Bounded Dijkstra vs UBODT tables: build time, size, points/s (best of 5), same routes."""
    import time

    import numpy as np

    from mapmatch.batch import BatchMatcher
    from mapmatch.io import Columns, read_tracks
    from mapmatch.route_table import Ubodt, ubodt_estimate

    peers_adapter, data, names = _tracks(ids)
    for name in names:
        graph = peers_adapter.load_graph(data / name)
        (track,) = read_tracks(data / name / "track.csv", columns=Columns(time="t"))
        variants: list[tuple[str, BatchMatcher]] = [("search", BatchMatcher(graph))]
        for d in (float(x) for x in deltas.split(",")):
            t0 = time.perf_counter()
            estimate = ubodt_estimate(graph, d)
            t1 = time.perf_counter()
            table = Ubodt.build(graph, d)  # with the batch default turn cost
            build = time.perf_counter() - t1
            print(
                f"{name} edges={graph.n_edges} UBODT {d:.0f} m: "
                f"build {build:.2f} s, {table.nbytes / 1e6:.0f} MB "
                f"(estimated {estimate / 1e6:.0f} MB in {(t1 - t0) * 1e3:.0f} ms)"
            )
            variants.append((f"ubodt{d:.0f}", BatchMatcher(graph, ubodt=table)))
        for s in (int(x) for x in S.split(",")):
            idx = np.arange(0, len(track), s)
            sub = type(track)(track.track_id, track.time[idx], track.lat[idx], track.lon[idx])
            ref = variants[0][1].match(sub).routes
            row = []
            for label, m in variants:
                best = min(_timed(m, sub) for _ in range(5))
                same = m.match(sub).routes == ref
                row.append(f"{label} {len(idx) / best:9.0f} pts/s{'' if same else ' (DIFFERENT ROUTE)'}")
            print(f"  S={s:2d}: " + " | ".join(row))


def fixed_cost(ids: str, calls: int) -> None:
    """Time per match() call on tiny tracks (first fixes of each track, 30 s apart), the map loaded:
    the least and the median over ``calls`` calls, with and without the lon/lat fill."""
    import gc
    import time

    import numpy as np

    from mapmatch.io import Columns, read_tracks
    from mapmatch.types import Track

    peers_adapter, data, names = _tracks(ids)
    for name in names:
        matcher = peers_adapter.load(data / name)
        (track,) = read_tracks(data / name / "track.csv", columns=Columns(time="t"))
        row = []
        for npts in (1, 2, 3, 5):
            idx = np.arange(npts) * 30
            t, lat, lon = track.time[idx].tolist(), track.lat[idx].tolist(), track.lon[idx].tolist()
            for lonlat in (False, True):
                for _ in range(20):
                    matcher.match(Track("t", np.asarray(t), np.asarray(lat), np.asarray(lon)), lonlat=lonlat)
                gc.disable()
                ts = []
                for _ in range(calls):
                    t0 = time.perf_counter()
                    matcher.match(Track("t", np.asarray(t), np.asarray(lat), np.asarray(lon)), lonlat=lonlat)
                    ts.append(time.perf_counter() - t0)
                gc.enable()
                us = np.array(ts) * 1e6
                row.append(f"{npts} pts{' +lonlat' if lonlat else ''}: {us.min():.1f} / {np.median(us):.1f}")
        print(f"{name} ({matcher.graph.n_edges} edges) us per call, least / median: " + "; ".join(row))


CV_GRID = ("model.gps_sigma=5,8,12", "model.beta=3,5,8")
"""The default grid of ``--cv``: the fixes' σ where a track gives none, and the transition scale β."""


def cv_track(
    name: str, settings: list[tuple[str, ...]], Ss: list[int]
) -> dict[tuple[str, ...], dict[int, float]]:
    """RMF of one track at each S under each setting (on the batch defaults), in process: the
    adapter's map and route table (``peers_adapter.load``), the harness's sub-sampling and its
    ``score.py`` against the truth, trimmed to the track's first and last fix as the harness does."""
    import numpy as np

    from mapmatch.batch import BATCH_CONFIG
    from mapmatch.types import Track

    peers_adapter, data, _ = _tracks("all")
    if str(PEERS) not in sys.path:
        sys.path.insert(0, str(PEERS))
    import engines_kubicka as ek  # type: ignore[import-not-found]
    import score as scoring  # type: ignore[import-not-found]

    matcher = peers_adapter.load(data / name)
    t, lat, lon = ek.read_track(data / name)
    truth = json.loads((data / name / "truth.geojson").read_text())
    first_last = ((lon[0], lat[0]), (lon[-1], lat[-1]))
    out: dict[tuple[str, ...], dict[int, float]] = {}
    for setting in settings:
        config = BATCH_CONFIG.with_settings(list(setting))
        out[setting] = {}
        for s in Ss:
            idx = ek.subsample(len(t), s)
            track = Track("track", *(np.asarray([v[i] for i in idx], float) for v in (t, lat, lon)))
            lines, _ = peers_adapter.convert(matcher, matcher.match(track, config, lonlat=False))
            out[setting][s] = float(scoring.score(truth, lines, first_last)["rmf"])
    return out


def batch_loss(records: list[dict[int, float]]) -> float:
    """What ``--cv`` minimises over tracks: the mean RMF over the tracks, averaged over the S."""
    return statistics.fmean(statistics.fmean(r[s] for r in records) for s in records[0])


def cv_batch(ids: str, S: str, grid_specs: list[str], json_out: Path | None = None) -> str:
    """``--cv``: RMF of every grid setting on every track, cross-validated over the folds of
    ``bench/folds.py``; prints and returns the report."""
    import crossval  # type: ignore[import-not-found]
    import folds  # type: ignore[import-not-found]

    from mapmatch.batch import BATCH_CONFIG

    _, _, names = _tracks(ids)
    Ss = [int(x) for x in S.split(",")]
    settings = crossval.settings_grid(crossval.parse_grid(grid_specs))
    settings.sort(key=lambda s: BATCH_CONFIG.with_settings(list(s)) != BATCH_CONFIG)  # the default first
    current = settings[0]
    if BATCH_CONFIG.with_settings(list(current)) != BATCH_CONFIG:
        raise ValueError("the grid must hold the current value of each field")
    load0 = os.getloadavg()
    scores: dict[tuple[str, ...], dict[str, dict[int, float]]] = {x: {} for x in settings}
    for n, name in enumerate(names):
        for setting, per_s in cv_track(name, settings, Ss).items():
            scores[setting][name] = per_s
        print(f"# cv {n + 1}/{len(names)} {name}, load {os.getloadavg()[0]:.2f}", file=sys.stderr, flush=True)
    if json_out is not None:  # every setting's RMF of every track at each S
        json_out.write_text(json.dumps({";".join(k): v for k, v in scores.items()}))
    fold_ids = folds.folds(names)
    result = crossval.cross_validate(scores, fold_ids, loss=batch_loss)
    named = (
        ("current defaults, all tracks", [scores[current][n] for n in names]),
        (f"chosen on all {len(names)} tracks ({crossval.label(result.in_sample)})", result.in_sample_records),
        ("out of fold (chosen on 4 folds, scored on the 5th)", result.oof_records),
    )
    lines = [
        f"| | mean RMF, S = {' / '.join(map(str, Ss))} s | median RMF |",
        "|---|---|---|",
    ]
    for label, recs in named:
        mean = " / ".join(f"{statistics.fmean(r[s] for r in recs):.4f}" for s in Ss)
        med = " / ".join(f"{statistics.median(r[s] for r in recs):.4f}" for s in Ss)
        lines.append(f"| {label} | {mean} | {med} |")
    text = (
        f"REAL GPS: {len(names)} Kubicka tracks, batch matcher in process (the peers' sub-sampling and "
        f"`score.py`); {len(fold_ids)} folds by track (`bench/folds.py`, seed {folds.SEED}); grid "
        f"{'; '.join(f'`{g}`' for g in grid_specs)} ({len(settings)} settings) on the batch defaults; "
        "chosen by the least mean RMF over the training tracks, averaged over the S. Load average "
        f"{load0[0]:.2f} at the start, {os.getloadavg()[0]:.2f} at the end ({os.cpu_count()} cores).\n\n"
        + "\n".join(lines)
        + "\n\nThe choice of each fold, and each setting's loss (mean RMF averaged over the S) over all "
        + "tracks:\n\n"
        + crossval.choice_table(result)
    )
    print(text)
    return text


def _timed(m: object, track: object) -> float:
    import time

    t0 = time.perf_counter()
    m.match(track)  # type: ignore[attr-defined]
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ids", default="all", help="all, or comma-separated track numbers")
    ap.add_argument("--engines", default="custom,osrm,valhalla,valhalla_fs120,fastmm")
    ap.add_argument("--S", default="1,10,30")
    ap.add_argument("--tag", default="batch")
    ap.add_argument("--summary", nargs="+", type=Path, help="only summarise these result files")
    ap.add_argument("--timing", type=Path, help="with --summary: a timing file of an earlier run")
    ap.add_argument(
        "--repeat",
        type=int,
        default=7,
        help="timed calls per track, S and engine after the run (0: the harness's)",
    )
    ap.add_argument("--time-engines", help="the engines timed again (default: all of --engines)")
    ap.add_argument(
        "--side-rounds",
        type=int,
        default=25,
        help="growth check: rounds of 5 calls per map, smallest and largest map side by side (0: apart)",
    )
    ap.add_argument("--routing", action="store_true", help="compare bounded search and UBODT in process")
    ap.add_argument("--deltas", default="1000,2000,3000", help="UBODT bounds in metres for --routing")
    ap.add_argument(
        "--fixed", action="store_true", help="time per call on tiny tracks (fixed cost), in process"
    )
    ap.add_argument("--calls", type=int, default=2000, help="calls per tiny track for --fixed")
    ap.add_argument(
        "--cv", action="store_true", help="cross-validate --grid over the folds of bench/folds.py, in process"
    )
    ap.add_argument("--grid", nargs="*", default=list(CV_GRID), metavar="SECTION.FIELD=V1,V2,...")
    ap.add_argument("--json", type=Path, help="with --cv: also write every setting's RMF of every track here")
    ap.add_argument("--docs", action="store_true", help="also write the summary to docs/benchmarks/batch.md")
    a = ap.parse_args()
    if a.routing:
        compare_routing(a.ids, a.S, a.deltas)
        return 0
    if a.cv:
        sys.path.insert(0, str(ROOT / "bench"))
        from report import run_header, write_fragment

        try:
            text = cv_batch(a.ids, a.S, a.grid, a.json)
        except ValueError as exc:  # ConfigError is a ValueError too
            print(f"error: --grid: {exc}", file=sys.stderr)
            return 2
        if a.docs:
            print(f"wrote {write_fragment('cv_batch', run_header() + text)}")
        return 0
    if a.fixed:
        print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())} ({os.cpu_count()} cores)")
        fixed_cost(a.ids, a.calls)
        return 0
    if not PEERS.is_dir():
        print(f"needs the peers folder {PEERS}", file=sys.stderr)
        return 2
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())} ({os.cpu_count()} cores)")
    paths = a.summary or [run(a.ids, a.engines, a.S, a.tag)]
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    timing = a.timing
    if timing is None and not a.summary and a.repeat > 0:
        timing = time_engines(a.ids, a.time_engines or a.engines, a.S, a.repeat, a.tag)
        print(f"load average after the repeated timing: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    side = a.side_rounds if "custom" in a.engines.split(",") and not a.summary else 0
    if not a.docs:
        summarise(paths, timing, side_rounds=side)
        return 0
    from report import capture, fenced, run_header, write_fragment

    with capture() as out:
        summarise(paths, timing, side_rounds=side)
    print(f"wrote {write_fragment('batch', run_header() + fenced(out.getvalue()))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
