"""Map matching of fused vehicle positions: online per-vehicle filtering and batch Viterbi.

The public API, importable from ``mapmatch`` directly (loaded on first use, so ``import
mapmatch`` stays light):

Maps
    :func:`build_map` (OSM or GIS source → :class:`RoadGraph`), :func:`save_map`,
    :func:`load_map`, :func:`open_map` (a map file, or a source built on the fly).
Online matching
    :class:`OnlineMatcher`, :class:`SessionState`, :class:`MatchConfig`, :data:`DEFAULT_CONFIG`,
    :class:`Fix`, :class:`SnapResult`, :func:`read_fixes`.
Batch matching
    :class:`BatchMatcher`, :data:`BATCH_CONFIG`, :class:`Track`, :class:`TrackMatch`,
    :func:`read_tracks`, :func:`run_batch` (files in, files out, local cores or Dask),
    :func:`results_table`, :func:`write_results`.
Scoring
    :func:`evaluate`, :func:`route_mismatch`, :func:`read_route_geojson`, :func:`score_route`.
Errors
    :class:`MatchError` (:class:`ValidationError`, :class:`ConfigError`), :class:`GraphError`
    (:class:`InputError`, :class:`ArtifactError`), :class:`MissingExtraError`.

``__version__`` is the installed distribution's version.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_API: dict[str, str] = {
    "RoadGraph": "graph.road_graph",
    "build_map": "graph.build",
    "save_map": "graph.artifact",
    "load_map": "graph.artifact",
    "open_map": "graph.artifact",
    "OnlineMatcher": "mapmatch.online",
    "SessionState": "mapmatch.online",
    "MatchConfig": "mapmatch.config",
    "DEFAULT_CONFIG": "mapmatch.config",
    "BatchMatcher": "mapmatch.batch",
    "BATCH_CONFIG": "mapmatch.batch",
    "Fix": "mapmatch.types",
    "SnapResult": "mapmatch.types",
    "Track": "mapmatch.types",
    "TrackMatch": "mapmatch.types",
    "read_fixes": "mapmatch.io",
    "read_tracks": "mapmatch.io",
    "results_table": "mapmatch.io",
    "write_results": "mapmatch.io",
    "run_batch": "mapmatch.parallel",
    "evaluate": "mapmatch.evaluate",
    "route_mismatch": "mapmatch.route_score",
    "read_route_geojson": "mapmatch.route_score",
    "score_route": "mapmatch.route_score",
    "MatchError": "mapmatch.errors",
    "ValidationError": "mapmatch.errors",
    "ConfigError": "mapmatch.errors",
    "GraphError": "graph.errors",
    "InputError": "graph.errors",
    "ArtifactError": "graph.errors",
    "MissingExtraError": "mapmatch.extras",
}
__all__ = [
    "BATCH_CONFIG",
    "DEFAULT_CONFIG",
    "ArtifactError",
    "BatchMatcher",
    "ConfigError",
    "Fix",
    "GraphError",
    "InputError",
    "MatchConfig",
    "MatchError",
    "MissingExtraError",
    "OnlineMatcher",
    "RoadGraph",
    "SessionState",
    "SnapResult",
    "Track",
    "TrackMatch",
    "ValidationError",
    "__version__",
    "build_map",
    "evaluate",
    "load_map",
    "open_map",
    "read_fixes",
    "read_route_geojson",
    "read_tracks",
    "results_table",
    "route_mismatch",
    "run_batch",
    "save_map",
    "score_route",
    "write_results",
]


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("mapmatch")
    except PackageNotFoundError:  # a source tree that was never installed
        return "0+unknown"


def __getattr__(name: str) -> Any:
    # everything is loaded on first use, so importing the package (as `python -m mapmatch`
    # does before any handler runs) takes no time and a Ctrl-C finds the CLI's handler
    if name == "__version__":
        globals()[name] = value = _version()
        return value
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'mapmatch' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))


if TYPE_CHECKING:
    __version__: str
    from graph.artifact import load_map, open_map, save_map
    from graph.build import build_map
    from graph.errors import ArtifactError, GraphError, InputError
    from graph.road_graph import RoadGraph
    from mapmatch.batch import BATCH_CONFIG, BatchMatcher
    from mapmatch.config import DEFAULT_CONFIG, MatchConfig
    from mapmatch.errors import ConfigError, MatchError, ValidationError
    from mapmatch.evaluate import evaluate
    from mapmatch.extras import MissingExtraError
    from mapmatch.io import read_fixes, read_tracks, results_table, write_results
    from mapmatch.online import OnlineMatcher, SessionState
    from mapmatch.parallel import run_batch
    from mapmatch.route_score import read_route_geojson, route_mismatch, score_route
    from mapmatch.types import Fix, SnapResult, Track, TrackMatch
