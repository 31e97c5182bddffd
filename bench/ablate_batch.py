"""Ablation of the batch matcher's mechanisms on the shared Kubicka tracks, cross-validated.

Each variant turns one mechanism off (or to its neutral value) on the batch defaults. Every
track is matched in process once per variant at S = 1, 10 and 30 s (the peers' sub-sampling and
``score.py``, as ``bench_batch.py --cv``), and its full-rate route is checked to cover the 10 s
and 30 s routes (``bench_consistency.py``'s rule). Per mechanism the choice between the default
and the variant is cross-validated over the folds of ``bench/folds.py`` (``bench/crossval.py``,
the batch loss of ``bench_batch.py``: mean RMF over the tracks averaged over the S); a mechanism
whose default does not win out of fold by more than ``--noise`` of the loss does not earn its
place.

    python bench/ablate_batch.py --out /tmp/abl.jsonl                       # run every variant
    python bench/ablate_batch.py --out /tmp/abl.jsonl --variants route_speed_off,beta_per_s_off
    python bench/ablate_batch.py --report /tmp/abl.jsonl                    # the table
    python bench/ablate_batch.py --report /tmp/abl.jsonl --docs   # also the docs fragment
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "bench"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

VARIANTS: dict[str, tuple[str, ...]] = {
    "defaults": (),
    # batch.route
    "route_speed_off": ("batch.route.route_speed=0",),
    "beta_per_s_off": ("batch.route.beta_per_s=0",),
    "turn_cost_off": ("batch.route.turn_cost=0",),
    "reverse_tolerance_off": ("batch.route.reverse_tolerance=0",),
    "stop_uturn_off": ("batch.route.stop_uturn_penalty=1e9",),
    "route_factor_wide": ("batch.route.max_route_factor=6",),
    "route_slack_wide": ("batch.route.route_slack=300",),
    "route_lp_cut_wide": ("batch.route.route_lp_cut=60",),
    # batch.track
    "track_sigma_off": ("batch.track.track_sigma_max=0",),
    "thin_off": ("batch.track.thin_sigmas=0",),
    "motion_heading_off": ("model.straight_max_deg=0",),
    "motion_end_leg_off": ("batch.track.motion_end_leg_max=0",),
    # batch.outliers
    "spike_off": ("batch.outliers.spike_speed=0",),
    "spike_run_off": ("batch.outliers.spike_max_time=0",),
    "max_skip_time_off": ("batch.outliers.max_skip_time=0",),
    "lookahead_off": ("batch.outliers.outlier_lookahead=0",),
    "emission_prune_wide": ("batch.outliers.emission_prune=25",),
    # batch.split
    "split_speed_off": ("batch.split.split_speed=0",),
    "off_map_cut_off": ("batch.split.off_map_cut=0",),
    # model, as the batch uses it
    "beta_per_m_off": ("model.beta_per_m=0",),
    "speed_penalty_off": ("model.speed_penalty=0",),
    "candidates_wide": ("model.max_candidates=16",),
    "search_radius_wide": ("model.search_radius=100",),
    "sigma_estimate_only": ("model.gps_sigma=1",),
}
"""Each variant's settings on the batch defaults (``MatchConfig.with_settings``)."""

SS = (1, 10, 30)


def score_track(name: str, variants: dict[str, tuple[str, ...]]) -> list[dict[str, Any]]:
    """One record per variant: RMF at each S, and the full-rate route's uncovered stretches of
    the 10 s and 30 s routes (``bench_consistency.py``'s rule: 5 m buffer, 30 m length)."""
    import bench_batch
    import numpy as np

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
    t, lat, lon = ek.read_track(data / name)
    truth = json.loads((data / name / "truth.geojson").read_text())
    first_last = ((lon[0], lat[0]), (lon[-1], lat[-1]))
    ends = to_xy(matcher.graph.crs, np.array([lon[0], lon[-1]]), np.array([lat[0], lat[-1]]))
    out = []
    for vname, setting in variants.items():
        config = BATCH_CONFIG.with_settings(list(setting))
        t0 = time.perf_counter()
        rec: dict[str, Any] = {"track": name, "variant": vname, "rmf": {}, "missing": {}}
        routes = {}
        for s in SS:
            idx = ek.subsample(len(t), s)
            track = Track("track", *(np.asarray([v[i] for i in idx], float) for v in (t, lat, lon)))
            res = matcher.match(track, config, lonlat=False)
            routes[s] = res.route_xy
            lines, _ = peers_adapter.convert(matcher, res)
            rec["rmf"][str(s)] = float(scoring.score(truth, lines, first_last)["rmf"])
        for s in SS[1:]:
            trimmed = trim_route_ends(routes[s], first_xy=ends[0], last_xy=ends[1])
            gaps = uncovered_stretches(routes[1], trimmed, buffer_m=5.0, min_length_m=30.0)
            rec["missing"][str(s)] = [round(g.length_m, 1) for g in gaps]
        rec["pieces"] = len(routes[1])
        rec["secs"] = round(time.perf_counter() - t0, 2)
        out.append(rec)
    return out


def run(out: Path, names: list[str], variants: dict[str, tuple[str, ...]]) -> None:
    """Score every track under every variant, one JSON line per (track, variant), appended."""
    done = set()
    if out.exists():
        done = {(r["track"], r["variant"]) for r in map(json.loads, out.read_text().splitlines()) if r}
    for n, name in enumerate(names):
        todo = {k: v for k, v in variants.items() if (name, k) not in done}
        if not todo:
            continue
        recs = score_track(name, todo)
        with out.open("a") as f:
            for r in recs:
                f.write(json.dumps(r) + "\n")
        secs = sum(r["secs"] for r in recs)
        print(f"# {n + 1}/{len(names)} {name}: {secs:.1f} s, load {os.getloadavg()[0]:.2f}", flush=True)


def batch_loss(records: list[dict[str, Any]]) -> float:
    """Mean RMF over the tracks, averaged over the S (``bench_batch.batch_loss``)."""
    return statistics.fmean(statistics.fmean(r["rmf"][str(s)] for r in records) for s in SS)


def verdict(base: dict, per: dict, names: list[str], name: str, *, noise: float) -> tuple[float, str]:
    """The out-of-fold loss of choosing per fold between the default and the variant, and
    whether the mechanism earns its place: its on-setting must beat the off-setting out of
    fold by more than ``noise`` of the loss (a variant ``*_on`` turns on a rule that is off by
    default; ``*_wide`` loosens a bound, which earns nothing and is bounds work where it changes
    no track)."""
    import crossval
    import folds

    fold_ids = folds.folds(names)
    res = crossval.cross_validate({(): base, (name,): per}, fold_ids, loss=batch_loss)
    ld, lv = batch_loss([base[n] for n in names]), batch_loss([per[n] for n in names])
    if name.endswith("_wide"):
        same = all(base[n]["rmf"] == per[n]["rmf"] for n in names)
        return res.oof_loss, "no track changes: bounds work" if same else "changes tracks"
    off = ld if name.endswith("_on") else lv
    if res.oof_loss < off * (1 - noise):
        return res.oof_loss, "earns its place"
    return res.oof_loss, "does not earn its place"


def report(path: Path, *, noise: float) -> str:
    """Per variant: loss with and without, violations, the out-of-fold verdict (markdown)."""
    recs = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
    by: dict[str, dict[str, dict[str, Any]]] = {}
    for r in recs:
        by.setdefault(r["variant"], {})[r["track"]] = r
    base = by["defaults"]
    names = sorted(base)

    def viol(per: dict) -> str:
        return " / ".join(str(sum(bool(per[n]["missing"][str(s)]) for n in names)) for s in SS[1:])

    def rmf(per: dict) -> str:
        return " / ".join(f"{statistics.fmean(per[n]['rmf'][str(s)] for n in names):.4f}" for s in SS)

    lines = [
        f"REAL GPS: {len(names)} Kubicka tracks, batch matcher in process on the batch defaults "
        f"(mean RMF at S = 1 / 10 / 30 s, the peers' `score.py`; loss: their mean over the S). "
        f"Defaults: RMF {rmf(base)}, loss {batch_loss([base[n] for n in names]):.5f}, coverage "
        f"violations (10 s / 30 s) {viol(base)}. Out of fold: per fold of `bench/folds.py` the "
        f"default or the variant, whichever has the least loss on the other four folds. Noise: "
        f"{noise:.0%} of the loss.",
        "",
        "| variant | settings | tracks changed | loss, variant | mean RMF, variant | violations | "
        "out of fold | verdict |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for v, per in by.items():
        if v == "defaults" or set(per) < set(names):
            continue
        oof, said = verdict(base, per, names, v, noise=noise)
        changed = sum(base[n]["rmf"] != per[n]["rmf"] for n in names)
        lines.append(
            f"| {v} | {', '.join(f'`{x}`' for x in VARIANTS.get(v, ()))} | {changed} | "
            f"{batch_loss([per[n] for n in names]):.5f} | {rmf(per)} | {viol(per)} | {oof:.5f} | {said} |"
        )
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, help="append each (track, variant) record to this JSON-lines file")
    ap.add_argument("--variants", default="all", help="comma-separated variant names, or all")
    ap.add_argument("--ids", default="all", help="all, or comma-separated track numbers")
    ap.add_argument("--report", type=Path, help="only print the table of this JSON-lines file")
    ap.add_argument("--noise", type=float, default=0.02, help="relative loss difference that is noise")
    ap.add_argument("--docs", action="store_true", help="with --report: also write the docs fragment")
    a = ap.parse_args()
    if a.report:
        text = report(a.report, noise=a.noise)
        print(text)
        if a.docs:
            from report import run_header, write_fragment

            print(f"wrote {write_fragment('ablation_batch', run_header() + text)}")
        return 0
    import bench_batch

    _, _, names = bench_batch._tracks(a.ids)
    picked = ["defaults", *a.variants.split(",")]
    chosen = VARIANTS if a.variants == "all" else {k: VARIANTS[k] for k in picked}
    print(f"load average at the start: {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    run(a.out, names, chosen)
    print(f"load average at the end: {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
