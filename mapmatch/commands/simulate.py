"""``mapmatch simulate``: a fused drive (fixes CSV) and its ground truth from a map and a route."""

from __future__ import annotations

import argparse
import functools
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mapmatch.cli import EXIT_CONNECT, CommandError
from mapmatch.commands._fixio import STDIO, output_path, summary_stream
from mapmatch.extras import EVAL_MODULES

if TYPE_CHECKING:
    from mapmatch.types import Fix, SnapResult

if TYPE_CHECKING:
    from mapmatch.sim.drive import Drive


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "simulate",
        help="simulate a fusion node's fused fixes along a route, with ground truth",
        description=(
            "Drive a route (given, or random and legal) with a realistic speed profile, simulate GPS "
            "(noise, multipath, outages), gyro, odometer and compass, fuse them with a DR/GPS Kalman "
            "filter and write the fused fixes (the columns mapmatch replay and send read) and the truth."
        ),
    )
    p.add_argument("--map", required=True, help="prepared map file (mapmatch prep) or an OSM/GIS source")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--route", help="GeoJSON LineString of the route to drive (e.g. a truth file)")
    src.add_argument("--random-route", action="store_true", help="drive a random legal route")
    p.add_argument("--length-km", type=float, default=10.0, help="length of a random route (default 10)")
    p.add_argument("--rate", type=int, choices=(1, 10), default=1, help="fused output rate in Hz (default 1)")
    p.add_argument(
        "--outages",
        default="paper",
        help="GPS outages: 'paper' (60, 90, 92, 83, 48 s from 296, 896, 1510, 2160, 3230 s), 'none', "
        "or START:DURATION[,START:DURATION...] in seconds (default paper)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--vehicle-id", default="sim-1", help="vehicle id written to the fixes (default sim-1)")
    p.add_argument("--time0", type=float, default=0.0, help="time of the first fix in seconds (default 0)")
    p.add_argument("-o", "--output", required=True, help="fused fixes CSV to write ('-': stdout)")
    p.add_argument(
        "--truth",
        help="truth to write: per-fix CSV and route GeoJSON with the same stem (give either name)",
    )
    p.add_argument(
        "--map-aided",
        action="store_true",
        help="close the loop: feed each answer's map-aided measurement back into the fusion filter "
        "at the next fix (matcher in process, or the --server); the fixes written are the closed loop's",
    )
    p.add_argument(
        "--server",
        metavar="HOST:PORT",
        help="also replay the fixes to a running server "
        "(with --map-aided: the server is the matcher in the loop)",
    )
    p.add_argument("--realtime", action="store_true", help="with --server: send at the fixes' own pace")
    p.add_argument("--speedup", type=float, default=1.0, help="with --realtime: pace this many times faster")
    p.add_argument("--map-id", default="", help="with --server: the server's map id (default: its only map)")
    p.add_argument(
        "--matched",
        help="with --server or --map-aided: results CSV to write (default with --server: OUTPUT.matched.csv)",
    )
    p.set_defaults(func=run, kernel_items=drive_items)


DRIVE_MPS = 7.6
"""About the mean speed of a simulated drive (m/s; 10.3 km in 1,343 s on Monaco), to tell a
random route's seconds of driving from its length (:func:`drive_items`)."""


def drive_items(args: argparse.Namespace) -> int | None:
    """About the seconds of driving (the simulator's work, in 1 Hz fixes) of a random route of
    ``--length-km``, for the kernel mode; ``None`` for a given route, a closed loop
    (``--map-aided``, which also runs the online matcher) or a map to build from its source."""
    if not getattr(args, "random_route", True) or getattr(args, "map_aided", False):
        return None
    if hasattr(args, "map") and not str(args.map).endswith(".map"):  # a map to build first
        return None
    return max(0, round(args.length_km * 1000.0 / DRIVE_MPS))


def run(args: argparse.Namespace) -> int:
    from mapmatch.extras import require_installed

    if args.map_aided:
        require_installed(*EVAL_MODULES, extra="eval", needed_for="mapmatch simulate --map-aided")
    require_installed("pandas", extra="tables", needed_for="mapmatch simulate")
    import numpy as np

    from graph.artifact import open_map
    from mapmatch.sim.drive import position_error, read_route, simulate_drive, write_fixes_csv, write_truth
    from mapmatch.sim.routes import random_route
    from mapmatch.sim.sensors import parse_outages

    if args.output == STDIO and args.server and not args.matched and not args.map_aided:
        raise CommandError("with -o - and --server, give --matched (where the server's answers go)")
    if args.length_km <= 0:
        raise CommandError("--length-km must be positive")
    if args.speedup <= 0:
        raise CommandError("--speedup must be positive")
    outages = parse_outages(args.outages)
    graph = open_map(args.map)
    if args.route:
        route = read_route(graph, args.route)
    else:
        route = random_route(graph, length_m=args.length_km * 1000.0, rng=np.random.default_rng(args.seed))
    drive = simulate_drive(
        graph,
        route,
        rate=args.rate,
        outages=outages,
        seed=args.seed,
        vehicle_id=args.vehicle_id,
        time0=args.time0,
    )
    loop = open_err = None
    if args.map_aided:
        open_err = position_error(drive)
        loop = _map_aided(args, graph, drive)
        drive = loop.drive
    with output_path(Path(args.output)) as out:
        write_fixes_csv(drive, out)
    written = ["standard output" if args.output == STDIO else args.output]
    if args.truth:
        written += [str(p) for p in write_truth(graph, drive, args.truth)]
    err = position_error(drive)
    valid = drive.fixes["gps_valid"].to_numpy() > 0
    say = functools.partial(print, file=summary_stream(args))
    say(
        f"{len(drive.fixes)} fixes at {args.rate} Hz, {route.length / 1000:.2f} km in "
        f"{drive.trajectory.duration:.0f} s, {len(drive.node_index)} intersections, "
        f"{sum(1 for a, _ in drive.outages if a < drive.trajectory.duration)} GPS outages"
    )
    say(
        f"fused position error: {err[valid].mean():.1f} m mean with GPS"
        + (f", {err[~valid].max():.1f} m max without" if (~valid).any() else "")
    )
    if loop is not None and open_err is not None:
        say(
            f"map-aided: {int(loop.fed.sum())} of {len(loop.fed)} answers fed back, "
            f"{int(loop.rejected.sum())} rejected by the filter's gate; open loop "
            f"{open_err[valid].mean():.1f} m mean with GPS"
            + (f", {open_err[~valid].max():.1f} m max without" if (~valid).any() else "")
        )
        if args.matched:
            from mapmatch.fixes import write_results_csv

            rows = [(args.vehicle_id, f, r) for f, r in zip(drive.fix_objects(), loop.results, strict=True)]
            write_results_csv(args.matched, rows)
            written.append(args.matched)
    say("wrote " + ", ".join(written))
    if loop is not None:
        return 0 if all(r is not None for r in loop.results) else 1
    if args.server:
        return _replay(args, drive)
    return 0


def _map_aided(args: argparse.Namespace, graph: Any, drive: Any) -> Any:
    """The drive run again with the matcher's answers fed back into its filter (in process, or
    through ``--server``)."""
    import grpc

    from mapmatch.sim.loop_eval import run_map_aided

    try:
        if args.server is None:
            return run_map_aided(graph, drive)
        from service.client import ServerMatcher

        with ServerMatcher(args.server, vehicle_id=args.vehicle_id, map_id=args.map_id) as match:
            return run_map_aided(graph, drive, match=match)
    except grpc.RpcError as exc:
        raise CommandError(f"server {args.server}: {exc.code().name}: {exc.details()}", code=3) from None


def paced(fixes: list[tuple[str, Fix]], *, realtime: bool, speedup: float = 1.0) -> Iterator[tuple[str, Fix]]:
    """Yield the fixes, sleeping so that they go out at their own pace when ``realtime``."""
    if not fixes:
        return
    t_first = fixes[0][1].time
    wall0 = time.monotonic()
    for vid, fix in fixes:
        if realtime:
            wait = (fix.time - t_first) / speedup - (time.monotonic() - wall0)
            if wait > 0:
                time.sleep(wait)
        yield vid, fix


def replay_to_server(
    drive: Drive,
    server: str,
    *,
    vehicle_id: str,
    map_id: str = "",
    realtime: bool = False,
    speedup: float = 1.0,
    timeout: float | None = None,
) -> list[tuple[str, Fix, SnapResult | None, str]]:
    """Stream the drive's fixes to a running server; one ``(vehicle, fix, result, error)`` per fix."""
    from service.client import MapMatchClient

    out: list[tuple[str, Fix, SnapResult | None, str]] = []
    pairs = [(vehicle_id, f) for f in drive.fix_objects()]
    with MapMatchClient(server) as client:
        for a in client.stream(
            paced(pairs, realtime=realtime, speedup=speedup), map_id=map_id, timeout=timeout
        ):
            err = "" if a.error is None else f"{a.error.code.name}: {a.error.field}: {a.error.message}"
            out.append((a.vehicle_id, a.fix, a.result, err))
    return out


def _replay(args: argparse.Namespace, drive: Drive) -> int:
    import grpc

    from mapmatch.fixes import write_results_csv

    matched = Path(args.matched) if args.matched else Path(args.output).with_suffix(".matched.csv")
    try:
        rows = replay_to_server(
            drive,
            args.server,
            vehicle_id=args.vehicle_id,
            map_id=args.map_id,
            realtime=args.realtime,
            speedup=args.speedup,
        )
    except grpc.RpcError as exc:
        raise CommandError(
            f"server {args.server}: {exc.code().name}: {exc.details()}", EXIT_CONNECT
        ) from None
    write_results_csv(matched, rows)
    bad = sum(1 for r in rows if r[2] is None)
    print(
        f"replayed {len(rows)} fixes to {args.server} ({bad} rejected); wrote {matched}",
        file=summary_stream(args),
    )
    return 0 if bad == 0 else 1
