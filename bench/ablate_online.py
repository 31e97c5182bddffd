"""Ablation of the online matcher's mechanisms on REAL GPS, out of fold.

Each mechanism of :data:`MECHANISMS` is turned off (or, for a rule that is off by default, on)
by one set of ``SECTION.FIELD=VALUE`` settings. Every track's drive with the five outages
(``bench_online_real``) is scored once under the defaults and once under each switch; then,
per mechanism, ``bench/crossval.py`` chooses between the two settings on four folds of
``bench/folds.py`` and scores the fifth. The simpler setting (the mechanism off) is listed
first, so a tie goes to it: a rule stays only when it wins out of fold.

The loss is ``bench_online_real.online_loss`` (the share of wrong-road fixes plus the share of
missed intersections, live), except for the mechanisms that only revise earlier answers
(``loss="fin"``): the same shares after the corrections are applied. ``noise`` is the standard
error of the all-track loss difference, by a bootstrap over tracks (paired: the same drives).

    python bench/ablate_online.py                       # every mechanism, 1 Hz
    python bench/ablate_online.py --only bias_emission stop_line --rates 10
    python bench/ablate_online.py --json out.json       # keep every setting's rows (after each track)
    python bench/ablate_online.py --only rate_rules_all rate_rules_all_fin --rates 10
    python bench/ablate_online.py --load out.json       # report from them without running
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import crossval  # noqa: E402
import folds  # noqa: E402
from bench_online_real import KUBICKA, load_graph, online_loss, score_drive  # noqa: E402

from mapmatch.config import DEFAULT_CONFIG, MatchConfig  # noqa: E402
from mapmatch.online import OnlineMatcher  # noqa: E402
from mapmatch.sim.realgps import real_drive  # noqa: E402

Rows = list[dict[str, object]]


@dataclass(frozen=True)
class Mechanism:
    """One rule: its name, the settings that switch it (off, or on when off by default), and
    which answers it can change (``live``, or ``fin``: only the corrections)."""

    name: str
    switch: tuple[str, ...]
    loss: str = "live"
    off_by_default: bool = False


RATE_RULES = (
    "online.stop.zero_speed=0",
    "online.evidence.evidence_time=0.1",
    "online.stop.stop_time=0.001",
)
"""The rules that exist for the fix rate, all switched off at once (for a 10 Hz run: one
setting instead of six)."""

MECHANISMS: tuple[Mechanism, ...] = (
    Mechanism("region_sigma_term", ("online.region.ambiguous_sigma_factor=0",)),
    Mechanism("region_cap_1000", ("online.region.ambiguous_max_radius=1000",)),
    Mechanism(
        "hypothesis_bounds_x2",
        ("online.region.max_hypotheses=64", "online.region.max_hops=8", "online.region.prune_log_ratio=40"),
    ),
    Mechanism("commit_hold_probability", ("online.region.commit_hold_probability=0",)),
    Mechanism("search_against_heading", ("online.reinit.against_heading_deg=181",)),
    Mechanism(
        "soft_reinit_search",
        ("online.reinit.soft_reinit_sigmas=1000000", "online.reinit.against_heading_deg=181"),
    ),
    Mechanism(
        "hard_reinit", ("online.reinit.reinit_time=1000000000", "online.reinit.reinit_distance=1000000000")
    ),
    Mechanism("return_search", ("online.reinit.return_sigmas=0",)),
    Mechanism("turn_evidence", ("online.evidence.turn_sigma=1000000",)),
    Mechanism("evidence_per_distance", ("online.evidence.evidence_distance=0.000001",)),
    Mechanism("evidence_per_time", ("online.evidence.evidence_time=0.1",)),
    Mechanism("stopped_heading", ("online.evidence.stopped_heading_weight=0",)),
    Mechanism("fix_bias", ("online.bias.bias_time=0",)),
    Mechanism("bias_emission", ("online.bias.bias_emission=0",)),
    Mechanism(
        "learned_residuals",
        ("online.bias.learned_pos_sigma_max=0", "online.bias.learned_heading_sigma_max_deg=3"),
    ),
    Mechanism("drift_decay", ("online.bias.drift_decay_time=0.01",)),
    Mechanism("stop_detection", ("online.stop.stop_speed=0",)),
    Mechanism("node_hold_back", ("online.stop.node_hold_sigmas=0",)),
    Mechanism("zero_velocity", ("online.stop.zero_speed=0",)),
    Mechanism("stop_speed_average", ("online.stop.stop_time=0.001",)),
    Mechanism("turn_anchor", ("online.anchor.turn_anchor_sigma=0",)),
    Mechanism("align_rms_check", ("online.anchor.align_rms_max_deg=180",)),
    Mechanism("align_cover", ("online.anchor.align_cover=0",)),
    Mechanism("scale_from_anchors", ("online.odometer.scale_min_distance=1000000000",)),
    Mechanism("scale_learning", ("online.odometer.odo_scale_sigma=0",)),
    Mechanism("crossing_revision", ("online.corrections.revise_sigmas=1000000",), loss="fin"),
    Mechanism("report_back_ratio", ("online.corrections.report_back_ratio=1",)),
    Mechanism("heading_min_speed", ("model.heading_min_speed=0",)),
    Mechanism("one_sigma_gate", ("online.reinit.reinit_sigmas=3", "online.reinit.return_sigmas=3")),
    Mechanism("reinit_sigmas_as_soft", ("online.reinit.reinit_sigmas=3",)),
    Mechanism("return_sigmas_as_soft", ("online.reinit.return_sigmas=3",)),
    Mechanism("zero_speed_as_stop_speed", ("online.stop.zero_speed=0.5",)),
    Mechanism("reinit_by_time_only", ("online.reinit.reinit_distance=1000000000",)),
    Mechanism("reinit_by_distance_only", ("online.reinit.reinit_time=1000000000",)),
    Mechanism(
        "learned_caps_wide",
        ("online.bias.learned_pos_sigma_max=20", "online.bias.learned_heading_sigma_max_deg=60"),
    ),
    Mechanism(
        "learned_caps_wide_fin",
        ("online.bias.learned_pos_sigma_max=20", "online.bias.learned_heading_sigma_max_deg=60"),
        loss="fin",
    ),
    Mechanism("residual_time_as_bias_time", ("online.bias.residual_time=30",)),
    Mechanism("residual_time_as_bias_time_fin", ("online.bias.residual_time=30",), loss="fin"),
    Mechanism("rate_rules_all", RATE_RULES),
    Mechanism("rate_rules_all_fin", RATE_RULES, loss="fin"),
)
"""Every mechanism ablated, with the settings that switch it."""


def fin_loss(records: list[Rows]) -> float:
    """:func:`online_loss` on the answers with the corrections applied."""
    g = pd.DataFrame([r for rec in records for r in rec]).sum(numeric_only=True)
    wrong = 1.0 - g["ok_fin"] / max(g["scored"], 1)
    missed = 1.0 - (g["jn_gps_fin"] + g["jn_out_fin"]) / max(g["jn_gps"] + g["jn_out"], 1)
    return float(wrong + missed)


LOSSES = {"live": online_loss, "fin": fin_loss}


def key(setting: tuple[str, ...]) -> str:
    """A setting as the key of the scores (``defaults`` for none)."""
    return ";".join(setting) or "defaults"


def score_all(
    names: list[str],
    settings: list[tuple[str, ...]],
    rates: list[float],
    cache: Path | None,
    save: Path | None,
) -> dict[str, dict[str, Rows]]:
    """Every setting's rows of every track (each drive made once per rate); written to ``save``
    after every track when given, so that a long run can be read back in part."""
    out: dict[str, dict[str, Rows]] = {key(s): {} for s in settings}
    configs: dict[str, MatchConfig] = {key(s): DEFAULT_CONFIG.with_settings(list(s)) for s in settings}
    for n, name in enumerate(names):
        folder = KUBICKA / name
        graph = load_graph(folder, cache)
        drives = [real_drive(graph, folder, rate_hz=r, outages=True, seed=int(name)) for r in rates]
        for k, cfg in configs.items():
            matcher = OnlineMatcher(graph, config=cfg)
            rows = [
                score_drive(graph, matcher, d, track=name, rate=r) for d, r in zip(drives, rates, strict=True)
            ]
            for r in rows:
                r.pop("us")
            out[k][name] = rows
        if save:
            save.write_text(json.dumps(out, default=str))
        print(f"# {n + 1}/{len(names)} {name}: load {os.getloadavg()[0]:.2f}", flush=True)
    return out


def bootstrap_se(
    on: dict[str, Rows], off: dict[str, Rows], names: list[str], loss: object, n: int = 200
) -> float:
    """Standard error of ``loss(off) - loss(on)`` over all tracks, by resampling the tracks."""
    rng = np.random.default_rng(48)
    f = loss  # type: ignore[assignment]
    diffs = []
    for _ in range(n):
        pick = [names[i] for i in rng.integers(0, len(names), len(names))]
        diffs.append(f([off[t] for t in pick]) - f([on[t] for t in pick]))  # type: ignore[operator]
    return float(np.std(diffs))


def verdict_row(m: Mechanism, scores: dict[str, dict[str, Rows]], names: list[str]) -> dict[str, object]:
    """The figures of one mechanism: losses with and without, out of fold, the folds' choices."""
    loss = LOSSES[m.loss]
    base, alt = scores["defaults"], scores[key(m.switch)]
    on, off = (alt, base) if m.off_by_default else (base, alt)
    fold_ids = folds.folds(names)
    # the mechanism off first: a tie goes to the simpler rule
    result = crossval.cross_validate({("off",): off, ("on",): on}, fold_ids, loss=loss)
    loss_on, loss_off = loss([on[t] for t in names]), loss([off[t] for t in names])
    se = bootstrap_se(on, off, names, loss)
    chosen = [c.chosen[0] for c in result.folds]
    wins = chosen.count("on")
    gain = loss_off - result.oof_loss
    keep = wins >= 3 and gain > se
    per_track = [loss([off[t]]) - loss([on[t]]) for t in names]
    return {
        "mechanism": m.name,
        "switch": ", ".join(s.split("online.", 1)[-1] for s in m.switch),
        "loss": m.loss,
        "with": loss_on,
        "without": loss_off,
        "oof": result.oof_loss,
        "gain": gain,
        "noise": se,
        "folds_on": wins,
        "tracks_better_worse": f"{sum(d > 1e-9 for d in per_track)}/{sum(d < -1e-9 for d in per_track)}",
        "verdict": "kept" if keep else "removed",
    }


def table(rows: list[dict[str, object]]) -> str:
    """The verdicts as markdown."""
    lines = [
        "| mechanism | switched by | loss | with | without | out of fold | gain out of fold | noise "
        "| folds choosing it | tracks better / worse with it | verdict |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['mechanism']} | `{r['switch']}` | {r['loss']} | {r['with']:.4f} | {r['without']:.4f} "
            f"| {r['oof']:.4f} | {r['gain']:+.4f} | {r['noise']:.4f} | {r['folds_on']}/5 "
            f"| {r['tracks_better_worse']} | {r['verdict']} |"
        )
    return "\n".join(lines)


def parse_args() -> argparse.Namespace:
    """The command line."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="*", default=None, help="mechanism names (default: all)")
    ap.add_argument("--rates", nargs="*", type=float, default=[1.0], help="Hz (default: 1)")
    ap.add_argument("--tracks", nargs="*", default=None, help="track folder names (default: all)")
    ap.add_argument("--map-cache", type=Path, default=None, help="keep the prepared maps in this folder")
    ap.add_argument("--json", type=Path, default=None, help="write every setting's rows here")
    ap.add_argument("--load", nargs="*", type=Path, default=[], help="read rows written by --json instead")
    ap.add_argument(
        "--docs", action="store_true", help="also write the table as the fragment ablation_online"
    )
    return ap.parse_args()


def main() -> int:
    """Score (or load), then print the verdicts."""
    args = parse_args()
    known = {m.name: m for m in MECHANISMS}
    chosen = [known[n] for n in args.only] if args.only else list(MECHANISMS)
    names = args.tracks or folds.track_ids(KUBICKA)
    load0 = os.getloadavg()[0]
    scores: dict[str, dict[str, Rows]] = {}
    for path in args.load:
        for k, v in json.loads(path.read_text()).items():
            scores.setdefault(k, {}).update(v)
    want = [()] + [m.switch for m in chosen]
    todo = [s for s in want if key(s) not in scores]
    if todo:
        scores.update(score_all(names, todo, args.rates, args.map_cache, args.json))
    for k in scores:
        scores[k] = {t: [r for r in rows if float(r["hz"]) in args.rates] for t, rows in scores[k].items()}  # type: ignore[arg-type]
    rows = [verdict_row(m, scores, names) for m in chosen]
    rates = ", ".join(f"{r:g} Hz" for r in args.rates)
    text = (
        f"REAL GPS: {len(names)} Kubicka tracks with the five outages ({rates}); 5 folds by track "
        f"(seed {folds.SEED}). Load average {load0:.2f} at the start, {os.getloadavg()[0]:.2f} at "
        f"the end ({os.cpu_count()} cores).\n\n{table(rows)}"
    )
    print(f"\n{text}")
    if args.docs:
        from report import run_header, write_fragment

        print(f"wrote {write_fragment('ablation_online', run_header() + text)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
