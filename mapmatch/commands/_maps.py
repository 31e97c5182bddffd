"""Loading the ``--map`` of a subcommand: a prepared map file, or a source built on the fly."""

from __future__ import annotations

from pathlib import Path

from graph.road_graph import RoadGraph


def load_any_map(path: str | Path) -> RoadGraph:
    """A map file written by ``mapmatch prep`` (fast), else an OSM/GIS source (built, slow)."""
    from graph.artifact import MAGIC, load_map

    p = Path(path)
    with open(p, "rb") as f:
        head = f.read(len(MAGIC))
    if head[:-1] == MAGIC[:-1]:
        return load_map(p)
    from graph.build import build_map

    return build_map(p)
