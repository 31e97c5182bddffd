"""``mapmatch info``: a prepared map's manifest summary, with every array's checksum verified."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

DESCRIPTION = """\
Print what a prepared map file holds (format version, CRS, bounding box, counts, road km,
edge lengths, source file and checksum, build parameters and time) and verify the SHA-256
of every array. Exit status 2 when the file is missing, not a map file, or corrupt."""


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "info",
        help="print a prepared map's summary and verify its checksums",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("map", type=Path, metavar="MAP", help="prepared map file (from mapmatch prep)")
    p.add_argument("--json", action="store_true", help="print the whole manifest as JSON instead")
    p.set_defaults(func=run)


def summary(manifest: dict[str, Any], path: Path) -> str:
    """The manifest as a few readable lines."""
    c = manifest.get("counts", {})
    st = manifest.get("stats", {})
    src = manifest.get("source", {})
    rep = manifest.get("meta", {}).get("report", {})
    bbox = ", ".join(f"{x:.5f}" for x in manifest.get("bbox", []))
    q = st.get("edge_len_p5_p25_p50_p75_p95_m", [0.0] * 5)
    build = {k: v for k, v in manifest.get("build", {}).items() if v is not None}
    pieces = manifest.get("arrays", {}).get("piece_start", {}).get("shape", [c.get("edges", 0)])[0]
    lines = [
        f"map: {path} ({path.stat().st_size / 1e6:.1f} MB, format {manifest.get('format')} "
        f"v{manifest.get('format_version')})",
        f"crs: {manifest.get('crs')}   bbox (lon/lat): {bbox}",
        f"nodes: {c.get('nodes', 0):,}   edges: {c.get('edges', 0):,} "
        f"({st.get('oneway_edges', 0):,} one-way)   way pieces: {pieces:,}   "
        f"restrictions: {c.get('restrictions', 0):,}",
        f"road: {st.get('road_km', 0.0):,.1f} km   edge length: max {st.get('edge_len_max_m', 0.0):,.0f} m, "
        f"median {q[2]:,.0f} m, p95 {q[4]:,.0f} m",
        f"source: {src.get('name') or src.get('place') or src.get('format', '?')} ({src.get('format', '?')}"
        + (f", sha256 {src['sha256'][:16]}…" if src.get("sha256") else "")
        + ")",
        f"build: {json.dumps(build, sort_keys=True)}",
    ]
    secs = rep.get("seconds", {})
    if secs:
        lines.append("build time: " + ", ".join(f"{k} {v:.1f} s" for k, v in secs.items()))
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from graph.artifact import load_map, read_manifest

    manifest = read_manifest(args.map)
    if args.json:
        print(json.dumps(manifest, indent=2))
    else:
        print(summary(manifest, args.map))
    load_map(args.map, verify=True)  # ArtifactError (exit 2) names a corrupt array
    n = len(manifest.get("arrays", {}))
    if not args.json:
        print(f"checksums: ok ({n} arrays)")
    return 0
