"""Closed-loop benchmark: the map-aided measurement fed back into the fusion filter.

Open loop against closed loop on the same drives (same route, same raw sensors, same filter;
the closed loop feeds each usable answer back at the next fix), with the seed papers' five
GPS outages (60, 90, 92, 83, 48 s; spread over the drive when it is shorter than the paper's
schedule), at 1 Hz and 10 Hz:

* SIMULATED: Kubicka true routes on their maps, simulated sensors (GPS σ 5 m), as
  ``bench/bench_online.py`` makes its drives;
* REAL GPS: the Kubicka tracks' real fixes (:func:`mapmatch.sim.realgps.real_drive`) with
  modelled dead-reckoning sensors (:func:`mapmatch.sim.loop_eval.real_sensors`).

Figures: error at the end of each outage (median, p90 over all outages) and the maximum
during each, fused error with GPS, heading error, intersections traversed and correct road.
Then the failure guard: drives where the matcher errs (parallel roads with a biased GPS, an
outage ending at a fork), fed back as the flag says, ignoring the flag, and without the
filter's χ² gate.

    python bench/bench_closed_loop.py                  # 4 tracks, 1 and 10 Hz, both kinds
    python bench/bench_closed_loop.py --quick          # 1 track, 1 Hz
    python bench/bench_closed_loop.py --tracks all     # all 15 visible tracks
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_online import sensors_for, simulate  # noqa: E402

from graph.ascii import parse_ascii_map  # noqa: E402
from graph.build import build_map  # noqa: E402
from mapmatch.online import OnlineMatcher  # noqa: E402
from mapmatch.sim.closed_loop import closed_loop_drive, in_process  # noqa: E402
from mapmatch.sim.drive import Drive, DriveConfig, position_error, read_route, simulate_drive  # noqa: E402
from mapmatch.sim.kalman import DEFAULT_KALMAN  # noqa: E402
from mapmatch.sim.loop_eval import compare_loops, real_sensors, summary_table  # noqa: E402
from mapmatch.sim.routes import route_from_edges  # noqa: E402

KUBICKA = ROOT.parent / "shared" / "data" / "kubicka"
DEFAULT_TRACKS = ("00000000", "00000007", "00000014", "00000063")


def real(graph, folder: Path, rate: float, seed: int) -> Drive:  # type: ignore[no-untyped-def]
    from mapmatch.sim.realgps import real_drive

    d = real_drive(graph, folder, rate_hz=rate, outages=True, seed=seed)
    return dataclasses.replace(d, sensors=real_sensors(d))


def loops(tracks: list[str], rates: list[float], kinds: list[str]) -> list[dict[str, object]]:
    rows: list[dict[str, object]] = []
    for name in tracks:
        folder = KUBICKA / name
        g = build_map(folder / "roads.geojson")
        matcher = OnlineMatcher(g)
        for kind in kinds:
            for rate in rates:
                t0 = time.perf_counter()
                if kind == "SIMULATED":
                    route = read_route(g, folder / "truth.geojson")
                    drive = simulate(g, route, rate=rate, sigma=5.0, seed=int(50 + rate), outages=True)
                else:
                    drive = real(g, folder, rate, seed=int(rate))
                op, cl, _ = compare_loops(g, drive, lambda m=matcher: in_process(m))
                group = f"{kind} {rate:g} Hz"
                for loop, m in (("open", op), ("closed", cl)):
                    rows.append({"group": group, "loop": loop, "track": name, **dataclasses.asdict(m)})
                print(
                    f"{group:>16} {name}: outage end open {np.round(op.outage_end, 1).tolist()} "
                    f"closed {np.round(cl.outage_end, 1).tolist()} m; with GPS {op.error_gps_mean:.2f} -> "
                    f"{cl.error_gps_mean:.2f} m; ix {op.intersections:.3f} -> {cl.intersections:.3f}, "
                    f"edge {op.correct_edge:.3f} -> {cl.correct_edge:.3f}; "
                    f"fed {cl.fed:.2f} gated {cl.gated:.3f} "
                    f"({time.perf_counter() - t0:.0f} s)",
                    flush=True,
                )
    return rows


def verdict(table: pd.DataFrame) -> list[str]:
    """The issue's "done means" per group."""
    out = []
    for group, g in table.groupby("group", sort=False):
        o = g[g["loop"] == "open"].iloc[0]
        c = g[g["loop"] == "closed"].iloc[0]
        med = 1.0 - c["end_median_m"] / o["end_median_m"]
        p90 = 1.0 - c["end_p90_m"] / o["end_p90_m"]
        ok = (
            med >= 0.5
            and p90 >= 0.5
            and c["gps_mean_m"] <= o["gps_mean_m"]
            and c["intersections"] >= o["intersections"]
            and c["correct_edge"] >= o["correct_edge"]
        )
        out.append(
            f"{group:>16}: outage-end median -{100 * med:.0f} %, p90 -{100 * p90:.0f} %; with GPS "
            f"{o['gps_mean_m']:.2f} -> {c['gps_mean_m']:.2f} m; intersections {o['intersections']:.3f} -> "
            f"{c['intersections']:.3f}; correct road {o['correct_edge']:.3f} -> {c['correct_edge']:.3f}: "
            + ("MET" if ok else "NOT MET")
        )
    return out


# --------------------------------------------------------------------------- failure guard
PARALLEL_GAP_M = 15.0
FORK = """
a-----------------------------b------------------------------c
                               \\
                                \\
                                 \\
                                  \\
                                   \\
                                    \\
                                     \\
                                      d
"""


def guard_drives(seeds: int) -> list[tuple[str, object, list[Drive]]]:
    """Drives where the matcher may err: parallel roads with a large correlated GPS error, and
    outages ending just past a fork (both branches driven)."""
    out: list[tuple[str, object, list[Drive]]] = []
    road = "-" * 100
    par = parse_ascii_map(f"a{road}b\nc{road}d", scale=PARALLEL_GAP_M / 2)
    rp = route_from_edges(par.graph, [par.edge("a", "b")], start_offset=10.0)
    sens = dataclasses.replace(sensors_for(10.0), gyro_bias=0.6)
    drives = [
        simulate_drive(
            par.graph, rp, rate=1.0, outages=[(40.0, 40.0)], seed=s, config=DriveConfig(sensors=sens)
        )
        for s in range(seeds)
    ]
    out.append(("parallel roads 15 m apart, GPS σ 10 m, a 40 s outage", par, drives))
    fk = parse_ascii_map(FORK, scale=10)
    drives = []
    for s in range(seeds):
        end = ("c", "d")[s % 2]
        r = route_from_edges(fk.graph, [fk.edge("a", "b"), fk.edge("b", end)], start_offset=5.0)
        # the outage starts ~150 m before the fork and ends ~40 m past it
        probe = simulate_drive(fk.graph, r, rate=1.0, outages="none", seed=s)
        t_fork = float(
            np.interp(fk.graph.edge_len[fk.edge("a", "b")] - 5.0, probe.trajectory.s, probe.trajectory.t)
        )
        t_a = float(
            np.interp(fk.graph.edge_len[fk.edge("a", "b")] - 155.0, probe.trajectory.s, probe.trajectory.t)
        )
        t_b = float(
            np.interp(fk.graph.edge_len[fk.edge("a", "b")] + 35.0, probe.trajectory.s, probe.trajectory.t)
        )
        assert t_a < t_fork < t_b
        drives.append(
            simulate_drive(
                fk.graph,
                r,
                rate=1.0,
                outages=[(t_a, t_b - t_a)],
                seed=s,
                config=DriveConfig(sensors=dataclasses.replace(sens, gyro_bias=1.0)),
            )
        )
    out.append(("an outage ending 40 m past a fork (60° branch or straight on)", fk, drives))
    return out


def guard(seeds: int) -> list[dict[str, object]]:
    rows: list[dict[str, object]] = []
    no_gate = dataclasses.replace(DEFAULT_KALMAN, gate_map_cross=1e12, gate_map_pos=1e12)
    for title, amap, drives in guard_drives(seeds):
        g = amap.graph  # type: ignore[attr-defined]
        matcher = OnlineMatcher(g)
        variants = [
            ("open loop", "none", DEFAULT_KALMAN),
            ("usable + χ² gate", "usable", DEFAULT_KALMAN),
            ("usable, no χ² gate", "usable", no_gate),
            ("all answers + χ² gate", "all", DEFAULT_KALMAN),
            ("all answers, no χ² gate", "all", no_gate),
        ]
        print(f"\n### {title} ({len(drives)} drives, 1 Hz)")
        for label, feed, kcfg in variants:
            wrong = wrong_fed = wrong_taken = fixes = 0
            gps_err, out_err = [], []
            for d in drives:
                run = closed_loop_drive(g, d, in_process(matcher), kalman=kcfg, feed=feed)
                te = d.truth["edge"].to_numpy()
                edges = np.array([r.edge if r is not None else -1 for r in run.results])
                bad = (edges != te) & (edges >= 0)
                wrong += int(bad.sum())
                usable = np.array([r is not None and r.map_aided.usable for r in run.results])
                wrong_fed += int((bad & (usable if feed != "all" else edges >= 0)).sum())
                wrong_taken += int((bad & run.accepted).sum())
                fixes += len(edges)
                err = position_error(run.drive)
                o = run.drive.truth["gps_outage"].to_numpy() > 0
                gps_err.append(err[~o])
                out_err.append(err[o])
            ge, oe = np.concatenate(gps_err), np.concatenate(out_err)
            row = {
                "case": title,
                "variant": label,
                "fixes": fixes,
                "wrong_road": wrong,
                "wrong_fed": wrong_fed if feed != "none" else 0,
                "wrong_accepted": wrong_taken,
                "gps_mean_m": float(ge.mean()),
                "gps_max_m": float(ge.max()),
                "outage_mean_m": float(oe.mean()),
                "outage_max_m": float(oe.max()),
            }
            rows.append(row)
            print(
                f"{label:>24}: wrong road {wrong} of {fixes} fixes, fed back {row['wrong_fed']}, accepted "
                f"{wrong_taken}; error with GPS mean {row['gps_mean_m']:.2f} max {row['gps_max_m']:.1f} m, "
                f"in outages mean {row['outage_mean_m']:.2f} max {row['outage_max_m']:.1f} m",
                flush=True,
            )
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="one track, 1 Hz, both kinds; 4 guard drives")
    ap.add_argument("--tracks", nargs="*", default=None, help="Kubicka track ids, or 'all'")
    ap.add_argument("--rates", nargs="*", type=float, default=None)
    ap.add_argument(
        "--kinds", nargs="*", default=["SIMULATED", "REAL GPS"], choices=["SIMULATED", "REAL GPS"]
    )
    ap.add_argument("--no-guard", action="store_true")
    ap.add_argument("--guard-seeds", type=int, default=10)
    ap.add_argument("--json", type=Path, default=None, help="also write all rows here")
    args = ap.parse_args()
    if not KUBICKA.is_dir():
        print(f"no Kubicka tracks at {KUBICKA}", file=sys.stderr)
        return 2
    if args.tracks == ["all"]:
        tracks = sorted(p.name for p in KUBICKA.iterdir() if (p / "track.csv").is_file())
    else:
        tracks = args.tracks or (["00000007"] if args.quick else list(DEFAULT_TRACKS))
    rates = args.rates or ([1.0] if args.quick else [1.0, 10.0])
    out: dict[str, object] = {}
    print("## open vs closed loop, five GPS outages per drive")
    rows = loops(tracks, rates, args.kinds)
    table = summary_table(rows)
    pd.set_option("display.width", 250)
    print("\n## summary (outage figures over all outages of the group; others: mean over drives)")
    print(table.round(3).to_string(index=False))
    print("\n## done means (issue #18)")
    print("\n".join(verdict(table)))
    out["loops"] = rows
    out["summary"] = table.to_dict(orient="records")
    if not args.no_guard:
        print("\n## failure guard: drives where the matcher errs")
        out["guard"] = guard(4 if args.quick else args.guard_seeds)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
