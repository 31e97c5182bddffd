"""Robustness runs of one engine on one prepared Kubicka work dir (run by ``bench_batch_robust.py``
with the engine's own Python, as the peers' harness runs its engines; ours runs ``run_track``
in process). Writes one JSON line per run, scored by the peers' ``score.py``.

    <python> peers_robust.py ENGINE WORKDIR OUT.jsonl --sets phases,gaps --peers DIR
    <python> peers_robust.py ENGINE --check --peers DIR      # is the engine installed?

The engine is the harness's ``engines_kubicka.ENGINES[ENGINE]`` (``load``, ``call``, ``convert``).
Four sets of runs (``phase_runs``, ``gap_runs``, ``noise_offsets``, ``jump_offsets``):
  phases  for each S, fix 0, every S-th fix from offset 0, step, 2 step, ... < S, and the last
          fix (``engines_kubicka.subsample`` is offset 0; the first fix: ``phase_runs``);
  gaps    every gap_S-th fix from offset 0 (plus the last), with one gap cut out per run: from
          sub-fix g0 (first, first + every, ...) the following sub-fixes are dropped until the
          next kept one is at least G metres (straight line, UTM) from g0.
  noise   every S-th fix from offset 0 (plus the last) of the real track with extra position
          noise added at 1 Hz before sub-sampling: per axis a first-order autoregressive error of
          σ N metres and correlation time ``--noise-tau`` (GPS errors drift, they do not jump),
          seeded by the track and N, so every engine gets the same fixes. Real routes and real
          fixes, synthetic extra error: a worse receiver than the tracks had.
  jumps   as noise, but the extra error is multipath jumps: a burst starts at a fix with
          probability J % and lasts 1-5 s, every fix in it displaced by one offset of 50-200 m
          in a random direction.
Each run is scored against truth.geojson with the run's own first and last fix.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import traceback
from collections.abc import Iterator
from pathlib import Path
from typing import Any

JOIN_M = 1.0
"""Lines whose ends are closer than this (metres) form one connected piece (Valhalla returns one
line per leg, OSRM one per matching, fastmm one per sub-trajectory, ours one per piece)."""


def peer_modules(peers: str) -> tuple[Any, Any]:
    """The peers' ``engines_kubicka`` and ``score`` modules, from their folder."""
    if peers not in sys.path:
        sys.path.insert(0, peers)
    import engines_kubicka  # type: ignore[import-not-found]
    import score  # type: ignore[import-not-found]

    return engines_kubicka, score


def with_last(idx: list[int], n: int) -> list[int]:
    return idx if idx[-1] == n - 1 else [*idx, n - 1]


def phase_runs(n: int, Ss: list[int], step: int) -> Iterator[tuple[dict[str, Any], list[int]]]:
    """Every S-th fix from each offset 0, step, ... < S, after the first fix and before the last.

    Every run starts at fix 0: ``score.py`` trims the true route only along its first arc, to
    the run's first fix, so a run starting at fix ``offset`` would be charged with the road
    driven before it (every engine alike, growing with the offset)."""
    for s in Ss:
        for off in range(0, s, max(step, 1)):
            if off < n:
                yield (
                    {"set": "phases", "S": s, "offset": off},
                    with_last(([0] if off else []) + list(range(off, n, s)), n),
                )


def gap_runs(
    xy: list[tuple[float, float]], S: int, Gs: list[float], first: int, every: int
) -> Iterator[tuple[dict[str, Any], list[int]]]:
    """Every S-th fix from offset 0 (plus the last) with one gap of at least G metres cut out after
    sub-fix g0; a g0 whose gap would reach the last fix ends the runs of that G."""
    n = len(xy)
    idx = with_last(list(range(0, n, S)), n)
    for G in Gs:
        for g0 in range(first, len(idx) - first, every):
            x0, y0 = xy[idx[g0]]
            g1 = g0 + 1
            while g1 < len(idx) - 1 and math.hypot(xy[idx[g1]][0] - x0, xy[idx[g1]][1] - y0) < G:
                g1 += 1
            if g1 >= len(idx) - 1:
                break
            x1, y1 = xy[idx[g1]]
            key = {"set": "gaps", "S": S, "offset": 0, "G": G, "g0": g0, "dropped": g1 - g0 - 1}
            key["gap_m"] = round(math.hypot(x1 - x0, y1 - y0), 1)
            yield key, idx[: g0 + 1] + idx[g1:]


def noise_offsets(
    n: int, t: list[float], sigma: float, tau: float, seed: int
) -> tuple[list[float], list[float]]:
    """East and north errors (metres) of ``n`` fixes at times ``t``: per axis a stationary
    first-order autoregressive series of standard deviation ``sigma`` and correlation time
    ``tau`` seconds."""
    import random

    rng = random.Random(seed)
    ex, ey = [rng.gauss(0.0, sigma)], [rng.gauss(0.0, sigma)]
    for i in range(1, n):
        rho = math.exp(-max(t[i] - t[i - 1], 0.0) / tau)
        k = sigma * math.sqrt(1.0 - rho * rho)
        ex.append(rho * ex[-1] + k * rng.gauss(0.0, 1.0))
        ey.append(rho * ey[-1] + k * rng.gauss(0.0, 1.0))
    return ex, ey


def jump_offsets(n: int, rate: float, seed: int) -> tuple[list[float], list[float]]:
    """East and north errors (metres) of ``n`` 1 Hz fixes: bursts of 1-5 fixes, starting at a
    fix with probability ``rate``, each displaced by one offset of 50-200 m in a random
    direction; zero elsewhere."""
    import random

    rng = random.Random(seed)
    ex, ey = [0.0] * n, [0.0] * n
    i = 0
    while i < n:
        if rng.random() < rate:
            r, a = rng.uniform(50.0, 200.0), rng.uniform(0.0, 2.0 * math.pi)
            for k in range(i, min(n, i + rng.randint(1, 5))):
                ex[k], ey[k] = r * math.cos(a), r * math.sin(a)
                i = k
        i += 1
    return ex, ey


def pieces(lines: list[list[list[float]]]) -> int:
    """Connected pieces of the returned lines (consecutive lines joined end to start)."""
    n = 0
    for i, ln in enumerate(lines):
        if i == 0:
            n = 1
            continue
        (lo0, la0), (lo1, la1) = lines[i - 1][-1][:2], ln[0][:2]
        dx = (lo1 - lo0) * 111320.0 * math.cos(math.radians(la0))
        if math.hypot(dx, (la1 - la0) * 110540.0) > JOIN_M:
            n += 1
    return n


def run_track(
    engine: Any, work: Path, a: argparse.Namespace, peers: str, name: str
) -> Iterator[dict[str, Any]]:
    """Load ``engine``'s map of ``work`` and yield one scored row per run of the chosen sets."""
    ek, score = peer_modules(peers)
    from pyproj import Transformer

    truth = json.loads((work / "truth.geojson").read_text())
    t, lat, lon = ek.read_track(work)
    epsg = json.loads((work / "meta.json").read_text())["utm_epsg"]
    X, Y = Transformer.from_crs("EPSG:4326", f"EPSG:{epsg}", always_xy=True).transform(lon, lat)
    runs: list[tuple[dict[str, Any], list[int]]] = []
    noisy: dict[tuple[str, float], tuple[list[float], list[float]]] = {}
    sets = a.sets.split(",")
    if "phases" in sets:
        runs += phase_runs(len(t), [int(x) for x in a.S.split(",")], a.step)
    if "gaps" in sets:
        Gs = [float(x) for x in a.gaps.split(",")]
        runs += gap_runs(list(zip(X, Y, strict=True)), a.gap_S, Gs, a.gap_first, a.gap_every)
    back = Transformer.from_crs(f"EPSG:{epsg}", "EPSG:4326", always_xy=True)
    for kind in ("noise", "jumps"):
        if kind not in sets:
            continue
        levels, steps = (a.noise, a.noise_S) if kind == "noise" else (a.jumps, a.jumps_S)
        for N in (float(x) for x in levels.split(",")):
            seed = int(work.name) * 1000 + round(N)
            if kind == "noise":
                ex, ey = noise_offsets(len(t), t, N, a.noise_tau, seed)
            else:
                ex, ey = jump_offsets(len(t), N / 100.0, seed)
            nx = [x + e for x, e in zip(X, ex, strict=True)]
            ny = [y + e for y, e in zip(Y, ey, strict=True)]
            nlo, nla = back.transform(nx, ny)
            noisy[(kind, N)] = (list(nla), list(nlo))
            for s in (int(x) for x in steps.split(",")):
                key = {"set": kind, "S": s, "offset": 0, "N": N}
                runs.append((key, with_last(list(range(0, len(t), s)), len(t))))
    obj = engine.load(work)
    for key, idx in runs:
        la_all, lo_all = noisy[(key["set"], key["N"])] if "N" in key else (lat, lon)
        tt, la, lo = [t[i] for i in idx], [la_all[i] for i in idx], [lo_all[i] for i in idx]
        row: dict[str, Any] = {"engine": name, "track": work.name, **key, "n_points": len(idx)}
        if key["set"] == "gaps":
            row["gap_s"] = round(tt[key["g0"] + 1] - tt[key["g0"]], 1)
        lines: list[list[list[float]]] = []
        try:
            t0 = time.perf_counter()
            raw = engine.call(obj, tt, la, lo)
            row["match_s"] = round(time.perf_counter() - t0, 6)
            lines, _ = engine.convert(obj, raw)
        except Exception as e:
            row["error"] = f"{type(e).__name__}: {str(e)[:300]}"
        sc = score.score(truth, lines, ((lo[0], la[0]), (lo[-1], la[-1])))
        row.update(lines=len(lines), pieces=pieces(lines), failed=bool(sc["failed"] or row.get("error")))
        for k in ("rmf", "d_minus_m", "d_plus_m", "coverage", "precision", "truth_m"):
            v = sc.get(k)
            row[k] = round(v, 6) if isinstance(v, float) else v
        yield row


def add_run_args(ap: argparse.ArgumentParser) -> None:
    """The options that define the runs (shared with ``bench_batch_robust.py``)."""
    ap.add_argument("--sets", default="phases,gaps", help="any of phases, gaps, noise, jumps")
    ap.add_argument("--S", default="10,30", help="phases: the sub-sampling steps")
    ap.add_argument("--step", type=int, default=3, help="phases: offsets 0, step, 2 step, ... < S")
    ap.add_argument("--gap-S", type=int, default=30, help="gaps: the sub-sampling step")
    ap.add_argument("--gaps", default="3000,8000", help="gaps: the least straight-line gaps G in metres")
    ap.add_argument("--gap-first", type=int, default=5, help="gaps: the first g0 (sub-fix index)")
    ap.add_argument("--gap-every", type=int, default=25, help="gaps: g0 step in sub-fixes")
    ap.add_argument("--noise", default="10,20", help="noise: the extra position σ in metres")
    ap.add_argument("--noise-S", default="1,10,30", help="noise: the sub-sampling steps")
    ap.add_argument("--noise-tau", type=float, default=20.0, help="noise: correlation time in seconds")
    ap.add_argument("--jumps", default="1,3", help="jumps: the %% of fixes where a burst starts")
    ap.add_argument("--jumps-S", default="1,10", help="jumps: the sub-sampling steps")


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("engine")
    ap.add_argument("work", nargs="?")
    ap.add_argument("out", nargs="?")
    ap.add_argument("--peers", required=True, help="the peers' folder (engines_kubicka.py, score.py)")
    ap.add_argument("--check", action="store_true", help="print the engine's version and exit")
    add_run_args(ap)
    a = ap.parse_args()
    ek, _ = peer_modules(a.peers)
    engine = ek.ENGINES[a.engine]()
    if a.check:
        print(engine.version())
        return 0
    if not a.work or not a.out:
        ap.error("WORKDIR and OUT are needed")
    with open(a.out, "w") as f:
        try:
            for row in run_track(engine, Path(a.work), a, a.peers, a.engine):
                f.write(json.dumps(row) + "\n")
                f.flush()  # rows done survive a later crash
        except Exception:
            traceback.print_exc()
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
