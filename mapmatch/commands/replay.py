"""``mapmatch replay``: run the online matcher in-process over a file of fused fixes."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from mapmatch.types import Fix, SnapResult

DESCRIPTION = """\
Replay fused fixes through the online matcher, one session per vehicle_id, exactly as the
service would see them, and write one result row per fix.

FIXES.csv is read as `mapmatch match` reads its input: CSV, GPX, Parquet or GeoParquet, or GIS
line files (each track a vehicle). CSV columns: vehicle_id, time (seconds or ISO 8601), lat,
lon, heading (degrees, empty when unknown) and optional pos_sigma (m), heading_sigma (deg),
speed (m/s), distance (odometer metres since the previous fix), gps_valid (1/0); other names
with --time-col etc. Without a vehicle_id column the file is one vehicle; without heading,
headings are unknown. "-" reads the fixes from standard input; "-o -" writes the results to
standard output. OUT.csv columns are listed in README ("Online matching and mapmatch replay").
A fix the matcher rejects (NaN, time going backwards, ...) gets a row with state "rejected" and
the reason in "error"; the vehicle's session continues with its next fix; the run then exits 1
with a one-line summary that says what to do. It exits 1 as well when no fix of some vehicle
was placed on a road, and says why when the coordinates tell (not degrees, off the map, lat and
lon swapped). --vehicle-id names the vehicle of a one-vehicle input (default: the file's name,
"stdin" for standard input)."""

EPILOG = """\
examples:
  mapmatch replay --map helsinki.map drive.csv -o snapped.csv
  mapmatch replay --map monaco.osm.pbf fleet.csv -o out.csv --drift-rate 0.02"""


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "replay",
        help="run the online matcher over a CSV of fused fixes (one session per vehicle)",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    from mapmatch.commands._fixio import add_fix_options

    p.add_argument("--map", required=True, type=Path, metavar="MAP",
                   help="map file from `mapmatch prep` (or an OSM/GIS source, built first)")  # fmt: skip
    add_fix_options(p)
    p.add_argument(
        "--new-session", action="store_true",
        help="start a new session where a vehicle's time goes back (drives joined in one file) "
        "instead of rejecting those fixes",
    )  # fmt: skip
    model = p.add_argument_group("model")
    model.add_argument("--gps-sigma", type=float, default=None, metavar="M", help="default position σ (m)")
    model.add_argument(
        "--drift-rate",
        type=float,
        default=None,
        metavar="F",
        help="DR drift per metre (0.04; online.bias.dr_sigma_growth)",
    )
    model.add_argument(
        "--reinit-time", type=float, default=None, metavar="S", help="seconds off road to reinit"
    )
    model.add_argument(
        "--set", action="append", default=[], metavar="SECTION.FIELD=VALUE", dest="settings",
        help="any other matcher parameter by its full name in mapmatch.config (repeatable), "
        "e.g. --set online.evidence.turn_window=40",
    )  # fmt: skip
    from mapmatch.commands._fixio import fixes_items, precheck_fixes

    p.set_defaults(func=run_replay, precheck=precheck_fixes, kernel_items=fixes_items)


def load_map_any(path: Path) -> Any:
    """A prepared map file, or an OSM/GIS source built on the fly."""
    from graph.artifact import MAGIC, load_map

    with open(path, "rb") as f:
        head = f.read(len(MAGIC))
    if head[:-1] == MAGIC[:-1]:  # any format version: load_map reports a mismatch
        return load_map(path)
    from graph.build import build_map  # heavy (osmnx); only for raw sources

    return build_map(path)


def run_replay(args: argparse.Namespace) -> int:
    from mapmatch.cli import EXIT_OK, EXIT_PARTIAL, CommandError
    from mapmatch.commands._fixio import output_path, read_fixes_arg, rejected_failure, summary_stream
    from mapmatch.config import DEFAULT_CONFIG
    from mapmatch.errors import ConfigError
    from mapmatch.fixes import write_results_csv
    from mapmatch.online import OnlineMatcher

    if not args.map.is_file():
        raise CommandError(f"no such map: {args.map}")
    over = {
        k: v
        for k, v in (
            ("gps_sigma", args.gps_sigma),
            ("dr_sigma_growth", args.drift_rate),
            ("reinit_time", args.reinit_time),
        )
        if v is not None
    }
    try:
        config = DEFAULT_CONFIG.replace(**over).with_settings(args.settings)
    except ConfigError as exc:
        raise CommandError(str(exc)) from None
    vehicles = read_fixes_arg(args)
    graph = load_map_any(args.map)
    run = _Run(matcher=OnlineMatcher(graph, config=config), new_session=args.new_session)
    t0 = time.perf_counter()
    with output_path(args.output) as out:
        n = write_results_csv(out, run.rows(vehicles), graph)
    dt = time.perf_counter() - t0
    summary = ", ".join(f"{k} {v}" for k, v in sorted(run.counts.items()))
    if not getattr(args, "quiet", False):
        print(
            f"{n} fixes of {len(vehicles)} vehicle(s) matched in {dt:.2f} s -> {args.output} ({summary})",
            file=summary_stream(args),
        )
    failed = rejected_failure(run.counts, n, run.first_error) or _never_placed(run, vehicles, graph.bbox)
    if failed:
        print(f"mapmatch replay: error: {failed}", file=sys.stderr)
        return EXIT_PARTIAL
    return EXIT_OK


@dataclass
class _Run:
    """One replay: the matcher, what was counted, the first rejection (with what to do)."""

    matcher: Any
    new_session: bool = False
    counts: dict[str, int] = field(default_factory=dict)
    first_error: str = ""
    placed: dict[str, int] = field(default_factory=dict)

    def count(self, key: str) -> None:
        self.counts[key] = self.counts.get(key, 0) + 1

    def rows(self, vehicles: dict[str, list[Fix]]) -> Iterator[tuple[str, Fix, SnapResult | None, str]]:
        from mapmatch.commands._fixio import TIME_REJECTED
        from mapmatch.errors import ValidationError

        for vid, fixes in vehicles.items():
            state = self.matcher.new_session()
            self.placed[vid] = 0
            last = float("-inf")
            for fix in fixes:
                if self.new_session and fix.time <= last:
                    state = self.matcher.new_session()
                    self.count("new sessions")
                try:
                    res = self.matcher.update(state, fix)
                except ValidationError as exc:
                    self.count("rejected")
                    if not self.first_error:
                        hint = TIME_HINT if str(exc).startswith(TIME_REJECTED) else ""
                        self.first_error = f"vehicle {vid} at time {fix.time!r}: {exc}{hint}"
                    yield vid, fix, None, str(exc)
                    continue
                last = fix.time
                self.count(str(res.state))
                self.placed[vid] += res.edge >= 0
                if res.correction is not None:
                    self.count("corrections")
                yield vid, fix, res, ""


TIME_HINT = (
    "; the vehicle's times go back (drives joined in one file?): --new-session starts a new "
    "session where they do, or give each drive its own vehicle id"
)


def _never_placed(run: _Run, vehicles: dict[str, list[Fix]], bbox: tuple[float, float, float, float]) -> str:
    """The failure summary when no fix of some vehicle was placed on a road (with why), else ""."""
    from mapmatch.commands._hints import coordinate_hint

    lost = [vid for vid, k in run.placed.items() if k == 0 and vehicles[vid]]
    if not lost:
        return ""
    fixes = vehicles[lost[0]]
    why = coordinate_hint([f.lat for f in fixes], [f.lon for f in fixes], bbox)
    return (
        f"nothing matched for {len(lost)} of {len(vehicles)} vehicle(s): no fix placed on a road "
        f"(first: {lost[0]}{f'; {why}' if why else ''})"
    )
