"""Per-track estimates of the batch model's σ and β (Newson and Krumm 2009) against the tuned
defaults, on the shared Kubicka tracks, cross-validated.

Each track, at each S (the peers' sub-sampling and ``score.py``, as ``ablate_batch.py``), is
matched once on the batch defaults; from that first match (its Viterbi path) come

- σ̂ = 1.4826 × the median distance of the matched fixes to their matched position (robust MAD);
- m̂ = median(|route distance − straight distance| / β_step) / ln 2 over consecutive matched
  fixes, β_step being the configured step scale (``model.beta`` + ``batch.route.beta_per_s`` ×
  the step's mean fix interval + ``model.beta_per_m`` × its length): the track's own β in units
  of the configured one (for a constant β this is N&K's median / ln 2 exactly).

Each estimate is shrunk toward the prior by the number of fixes it rests on (``n0`` fixes of
prior weight), clipped to sane bounds, and the track is matched again with it (one EM step).
The records are ``ablate_batch.py``'s, with the estimates: one variant per (estimate, n0),
beside the defaults of the same run; ``--report`` prints the cross-validated table.

    python bench/ablate_estimate.py --out /tmp/est.jsonl            # every track
    python bench/ablate_estimate.py --out /tmp/mean.jsonl --kinds betamean,bothmean
    python bench/ablate_estimate.py --report /tmp/est.jsonl /tmp/mean.jsonl   # the table
    python bench/ablate_estimate.py --report /tmp/est.jsonl /tmp/mean.jsonl --docs   # and the docs
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "bench"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

SS = (1, 10, 30)
SIGMA_BOUNDS = (2.0, 30.0)
SCALE_BOUNDS = (0.2, 5.0)


def estimates(res: Any, xy: np.ndarray, t: np.ndarray, edge_len: np.ndarray, cfg: Any) -> dict[str, float]:
    """σ̂, m̂ and the number of fixes behind each, from a first match ``res`` (``lonlat=False``)
    of the fixes at ``xy`` (map CRS) and times ``t``."""
    status, p_edge, p_off, _, p_dist = res.point_arrays
    matched = status == 1
    sig = 1.4826 * float(np.median(p_dist[matched])) if matched.any() else math.nan
    bounds = [0, *res.splits, len(status)]
    m = cfg.model
    resid: list[float] = []
    for s, edges in enumerate(res.routes):
        if not edges or s + 1 >= len(bounds):
            continue
        cum = np.concatenate(([0.0], np.cumsum(edge_len[np.asarray(edges)])))
        k = 0
        prev: tuple[int, float] | None = None
        for i in range(bounds[s], bounds[s + 1]):
            if status[i] != 1:
                continue
            e, o = int(p_edge[i]), float(p_off[i])
            kk = k
            if prev is not None and edges[k] == e and cum[k] + o < prev[1] - 1e-6:
                kk += 1  # behind the previous fix on its edge: the edge's next visit
            while kk < len(edges) and edges[kk] != e:
                kk += 1
            if kk >= len(edges):
                prev = None
                continue
            pos = cum[kk] + o
            if prev is not None:
                j, ppos = prev
                route = pos - ppos
                trav = float(np.hypot(*(xy[i] - xy[j])))
                dt = float(t[i] - t[j])
                step = m.beta + m.beta_per_m * trav
                if dt > 0:
                    step += cfg.batch.route.beta_per_s * dt / max(i - j, 1)
                if route >= 0:
                    resid.append(abs(route - trav) / step)
            prev = (i, pos)
            k = kk
    scale = float(np.median(resid)) / math.log(2) if resid else math.nan
    mean = float(np.mean(resid)) if resid else math.nan
    return {
        "sigma": sig,
        "n_sigma": int(matched.sum()),
        "scale": scale,
        "scale_mean": mean,
        "n_scale": len(resid),
    }


def shrunk(est: float, n: int, prior: float, n0: float, lo: float, hi: float) -> float:
    """``est`` from ``n`` fixes shrunk toward ``prior`` (weight ``n0`` fixes), clipped to [lo, hi]."""
    if not math.isfinite(est) or n == 0:
        return prior
    return min(max((n0 * prior + n * est) / (n0 + n), lo), hi)


def second_config(cfg: Any, est: dict[str, float], kind: str, n0: float) -> Any:
    """The config of the second match: ``kind`` is ``sigma``, ``beta`` or ``both`` (N&K's median
    / ln 2 for β), or ``betamean`` or ``bothmean`` (β from the residuals' mean, the exponential's
    maximum likelihood)."""
    settings = []
    if kind in ("sigma", "both", "bothmean"):
        sig = shrunk(est["sigma"], est["n_sigma"], cfg.model.gps_sigma, n0, *SIGMA_BOUNDS)
        settings.append(f"model.gps_sigma={sig}")
    if kind in ("beta", "both", "betamean", "bothmean"):
        raw = est["scale_mean"] if kind.endswith("mean") else est["scale"]
        sc = shrunk(raw, est["n_scale"], 1.0, n0, *SCALE_BOUNDS)
        settings += [
            f"model.beta={cfg.model.beta * sc}",
            f"model.beta_per_m={cfg.model.beta_per_m * sc}",
            f"batch.route.beta_per_s={cfg.batch.route.beta_per_s * sc}",
        ]
    return cfg.with_settings(settings)


def score_track(name: str, variants: list[tuple[str, float]]) -> list[dict[str, Any]]:
    """One record per variant (and the defaults): RMF at each S, the coverage check, estimates."""
    import bench_batch

    from graph.projection import to_xy
    from mapmatch.batch import BATCH_CONFIG
    from mapmatch.route_score import trim_route_ends, uncovered_stretches
    from mapmatch.types import Track

    peers_adapter, data, _ = bench_batch._tracks("all")
    if str(bench_batch.PEERS) not in sys.path:
        sys.path.insert(0, str(bench_batch.PEERS))
    import engines_kubicka as ek  # type: ignore[import-not-found]
    import score as scoring  # type: ignore[import-not-found]

    matcher = peers_adapter.load(data / name)
    edge_len = matcher.graph.edge_len
    t, lat, lon = ek.read_track(data / name)
    truth = json.loads((data / name / "truth.geojson").read_text())
    first_last = ((lon[0], lat[0]), (lon[-1], lat[-1]))
    ends = to_xy(matcher.graph.crs, np.array([lon[0], lon[-1]]), np.array([lat[0], lat[-1]]))
    names = ["defaults"] + [f"est_{k}_n{int(n0)}" for k, n0 in variants]
    recs = {v: {"track": name, "variant": v, "rmf": {}, "missing": {}, "est": {}} for v in names}
    routes: dict[str, dict[int, Any]] = {v: {} for v in names}
    secs = {v: 0.0 for v in names}
    for s in SS:
        idx = ek.subsample(len(t), s)
        cols = [np.asarray([v[i] for i in idx], float) for v in (t, lat, lon)]
        track = Track("track", *cols)
        xy = to_xy(matcher.graph.crs, cols[2], cols[1])
        t0 = time.perf_counter()
        first = matcher.match(track, BATCH_CONFIG, lonlat=False)
        secs["defaults"] += time.perf_counter() - t0
        est = estimates(first, xy, cols[0], edge_len, BATCH_CONFIG)
        for v, (kind, n0) in zip(names, [("", 0.0), *variants], strict=True):
            if v == "defaults":
                res = first
            else:
                t0 = time.perf_counter()
                cfg = second_config(BATCH_CONFIG, est, kind, n0)
                res = matcher.match(track, cfg, lonlat=False)
                secs[v] += time.perf_counter() - t0
            recs[v]["est"][str(s)] = est
            routes[v][s] = res.route_xy
            lines, _ = peers_adapter.convert(matcher, res)
            recs[v]["rmf"][str(s)] = float(scoring.score(truth, lines, first_last)["rmf"])
    for v in names:
        for s in SS[1:]:
            trimmed = trim_route_ends(routes[v][s], first_xy=ends[0], last_xy=ends[1])
            gaps = uncovered_stretches(routes[v][1], trimmed, buffer_m=5.0, min_length_m=30.0)
            recs[v]["missing"][str(s)] = [round(g.length_m, 1) for g in gaps]
        recs[v]["pieces"] = len(routes[v][1])
        recs[v]["secs"] = round(secs[v], 3)
    return list(recs.values())


KIND_TEXT = {
    "sigma": "σ̂ (median distance to the path)",
    "beta": "β scale (median / ln 2)",
    "both": "σ̂ and β scale (median / ln 2)",
    "betamean": "β scale (mean)",
    "bothmean": "σ̂ and β scale (mean)",
}


def _by_variant(paths: list[Path]) -> dict[str, dict[str, dict[str, Any]]]:
    """The records of ``paths`` by variant and track (a later file's record of the same pair wins)."""
    by: dict[str, dict[str, dict[str, Any]]] = {}
    for path in paths:
        for x in path.read_text().splitlines():
            if x.strip():
                r = json.loads(x)
                by.setdefault(r["variant"], {})[r["track"]] = r
    return by


def _estimates_line(base: dict[str, dict[str, Any]]) -> str:
    """The estimates over the tracks: median (range) of σ̂, median of the β scales, per S."""
    import statistics

    ests = [r["est"] for r in base.values()]

    def med(key: str, s: int) -> float:
        return statistics.median(e[str(s)].get(key, math.nan) for e in ests)

    sig = " / ".join(
        f"{med('sigma', s):.1f} ({min(e[str(s)]['sigma'] for e in ests):.1f}–"
        f"{max(e[str(s)]['sigma'] for e in ests):.1f}) m"
        for s in SS
    )
    scale = " / ".join(f"{med('scale', s):.3f}" for s in SS)
    mean = " / ".join(f"{med('scale_mean', s):.3f}" for s in SS)
    return f"σ̂ {sig}; β scale (median / ln 2) {scale}, (mean) {mean} of the configured step β"


def report(paths: list[Path]) -> str:
    """Per estimate: its loss at each prior weight, out of fold with the prior weight chosen on
    four folds and scored on the fifth, and per fold the choice between it and the tuned
    defaults (markdown)."""
    import statistics

    import crossval
    import folds
    from ablate_batch import batch_loss

    by = _by_variant(paths)
    base = by.pop("defaults")
    names = sorted(base)
    fold_ids = folds.folds(names)

    def row(what: str, per: list[dict[str, Any]], oof: str, vs_default: str, secs: str) -> str:
        mean = " / ".join(f"{statistics.fmean(r['rmf'][str(s)] for r in per):.4f}" for s in SS)
        med = " / ".join(f"{statistics.median(r['rmf'][str(s)] for r in per):.4f}" for s in SS)
        viol = " / ".join(str(sum(bool(r["missing"][str(s)]) for r in per)) for s in SS[1:])
        return f"| {what} | {batch_loss(per):.5f} | {mean} | {med} | {viol} | {oof} | {vs_default} | {secs} |"

    base_secs = sum(base[n]["secs"] for n in names)
    lines = [
        f"REAL GPS: {len(names)} Kubicka tracks at S = 1 / 10 / 30 s, each matched on the batch "
        "defaults, then again with its own estimates (one EM step), scored by the peers' `score.py` "
        "(loss: mean RMF averaged over the S). Estimates over the tracks, median (range) at S = 1 / "
        f"10 / 30: {_estimates_line(base)}. Out of fold: the prior weight n0 chosen on four folds of "
        "`bench/folds.py` and scored on the fifth; against the defaults: per fold the estimate "
        "(at its n0) or the tuned defaults, whichever has the least loss on the other four. Time: "
        "the second match's, over the first's.",
        "",
        "| estimate, prior weight n0 (fixes) | loss | mean RMF | median RMF | violations 10 s / 30 s "
        "| out of fold | against the defaults, out of fold (folds choosing the estimate) | time |",
        "|---|---|---|---|---|---|---|---|",
        row("none: the tuned defaults", [base[n] for n in names], "", "", "1"),
    ]
    kinds: dict[str, list[str]] = {}
    for v in by:
        kinds.setdefault(v.split("_n")[0].removeprefix("est_"), []).append(v)
    for kind, vs in kinds.items():
        text = KIND_TEXT.get(kind, kind)
        for v in vs:
            secs = f"{sum(by[v][n]['secs'] for n in names) / base_secs:.2f}"
            lines.append(row(f"{text}, n0 = {v.split('_n')[1]}", [by[v][n] for n in names], "", "", secs))
        own = crossval.cross_validate({(v,): by[v] for v in vs}, fold_ids, loss=batch_loss)
        both = crossval.cross_validate({(): base, **{(v,): by[v] for v in vs}}, fold_ids, loss=batch_loss)
        picked = sum(bool(f.chosen) for f in both.folds)
        lines.append(
            row(
                f"{text}, n0 by fold",
                own.oof_records,
                f"{own.oof_loss:.5f}",
                f"{both.oof_loss:.5f} ({picked} of 5)",
                "",
            )
        )
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, help="append each (track, variant) record here")
    ap.add_argument("--report", type=Path, nargs="+", help="only print the table of these JSON-lines files")
    ap.add_argument("--docs", action="store_true", help="with --report: also write the docs fragment")
    ap.add_argument("--ids", default="all", help="all, or comma-separated track numbers")
    ap.add_argument("--kinds", default="sigma,beta,both")
    ap.add_argument("--n0", default="30,300,3000", help="prior weights (fixes), comma-separated")
    args = ap.parse_args()
    if args.report:
        text = report(args.report)
        print(text)
        if args.docs:
            from report import run_header, write_fragment

            print(f"wrote {write_fragment('ablation_estimate', run_header() + text)}")
        return 0
    if args.out is None:
        ap.error("--out or --report is required")
    import bench_batch

    _, _, names = bench_batch._tracks(args.ids)
    variants = [(k, float(n)) for k in args.kinds.split(",") for n in args.n0.split(",")]
    done = set()
    if args.out.exists():
        done = {json.loads(x)["track"] for x in args.out.read_text().splitlines() if x.strip()}
    print(f"load average at the start: {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    for n, name in enumerate(names):
        if name in done:
            continue
        recs = score_track(name, variants)
        with args.out.open("a") as f:
            for r in recs:
                f.write(json.dumps(r) + "\n")
        est = recs[0]["est"]
        print(
            f"# {n + 1}/{len(names)} {name}: "
            + " ".join(f"S{s} σ̂ {est[str(s)]['sigma']:.1f} m̂ {est[str(s)]['scale']:.2f}" for s in SS)
            + " | "
            + " ".join(
                f"{r['variant']} {r['rmf']['1']:.4f}/{r['rmf']['10']:.4f}/{r['rmf']['30']:.4f}" for r in recs
            )
            + f" | load {os.getloadavg()[0]:.2f}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
