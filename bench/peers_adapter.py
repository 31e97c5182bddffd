"""Our batch matcher behind the peers' custom-engine hook (``../shared/peers/README.md``).

``load`` prepares the map (not timed); ``call`` is the timed match of one sub-sampled track;
``convert`` returns the matched route as lon/lat polylines, one per connected piece.

Timing is the harness's, as for every peer: ``engines_kubicka.py`` times ``call`` alone (the second
of two calls on the loaded map). ``call`` does what fastmm's does inside its timed call: the fixes
from lon/lat lists to the map's CRS and the whole match; the route stays in the map's CRS, and its
projection back to lon/lat happens in ``convert`` (untimed), as fastmm's does. Valhalla and OSRM
return lon/lat from their timed call.
Map: ``graph.build.build_map(roads.geojson)`` when the project has it, else a small
bench-only loader of ``roads.geojson`` (degree-2 chains contracted, as for fastmm).
"""

from __future__ import annotations

import gc
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from graph.road_graph import RoadGraph  # noqa: E402
from mapmatch.batch import BatchMatcher, fill_route_lonlat  # noqa: E402
from mapmatch.config import UBODT_MAX_BYTES  # noqa: E402
from mapmatch.route_table import Ubodt  # noqa: E402
from mapmatch.types import Track  # noqa: E402


def version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as v

    try:
        return f"mapmatch {v('mapmatch')}"
    except PackageNotFoundError:
        return "mapmatch (source tree)"


def load_graph(work: Path) -> RoadGraph:
    """The track's map, prepared from its roads.geojson as ``mapmatch prep`` would (not timed)."""
    from graph.build import build_map

    return build_map(work / "roads.geojson")


UBODT_DELTA = 2000.0
"""Route table bound in metres built at load time (fastmm's adapter uses a 3000 m UBODT); a
shorter one where it would not fit in ``UBODT_MAX_BYTES`` (1 GiB), as ``mapmatch match``
does."""


SETTINGS_ENV = "MAPMATCH_BENCH_SET"
"""``SECTION.FIELD=VALUE`` settings, comma-separated, for our batch config (``MatchConfig.with_settings``)."""


def load(work: Path) -> BatchMatcher:
    from mapmatch.batch import BATCH_CONFIG

    graph = load_graph(Path(work))
    settings = [s for s in os.environ.get(SETTINGS_ENV, "").split(",") if s.strip()]
    config = BATCH_CONFIG.with_settings(settings)
    matcher = BatchMatcher(
        graph,
        config=config,
        ubodt=(
            Ubodt.build(graph, UBODT_DELTA, turn_cost=config.batch.route.turn_cost, max_bytes=UBODT_MAX_BYTES)
            if UBODT_DELTA
            else None
        ),
    )
    # warm up: loads the numba cache before the timed calls
    lon, lat = matcher.graph.node_lonlat[0]
    matcher.match(Track("warmup", np.array([0.0, 1.0]), np.array([lat, lat]), np.array([lon, lon])))
    # the map build leaves millions of long-lived objects: keep them out of the timed calls' GC
    gc.collect()
    gc.freeze()
    return matcher


def call(obj: BatchMatcher, t: list[float], lat: list[float], lon: list[float]) -> Any:
    # the route stays in the map's projected CRS here, as fastmm's does; convert() projects it
    track = Track("track", np.asarray(t, float), np.asarray(lat, float), np.asarray(lon, float))
    return obj.match(track, lonlat=False)


def convert(obj: BatchMatcher, raw: Any) -> tuple[list[list[list[float]]], dict[str, Any]]:
    fill_route_lonlat(raw, obj.graph.crs)
    lines = [[[x, y] for x, y in piece] for piece in raw.route_lonlat if len(piece) >= 2]
    n_matched = sum(1 for p in raw.points if p.status != "unmatched")
    info = {
        "pieces": len(lines),
        "splits": list(raw.splits),
        "points_matched": n_matched,
        "confidence": round(raw.confidence, 4),
        "length_m": round(raw.length_m, 1),
    }
    return lines, info
