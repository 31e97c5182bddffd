"""Build a RoadGraph from a source file (OSM PBF/XML or GIS lines) or an osmnx download.

Pipeline (``engine="arrays"``, the default): read into a raw network of arrays (every vertex
a node, projected to local UTM; pyosmium for OSM, pyogrio's Arrow stream for GIS) ->
simplify to intersections and dead ends as :func:`osmnx.simplify_graph` does, with
whole-array numpy steps -> :class:`RoadGraph` (way pieces kept, turn restrictions mapped
onto the simplified edges). The reference (``engine="osmnx"``, and downloads or
``consolidate_tolerance``) goes through a networkx graph, :func:`osmnx.simplify_graph` and
:func:`osmnx.consolidate_intersections`; tests assert both give the same map.
"""

from __future__ import annotations

import functools
import gc
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from graph.errors import InputError
from graph.gis import GIS_SUFFIXES, GisOptions, OnewayConvention
from graph.road_graph import RoadGraph

if TYPE_CHECKING:
    import networkx as nx

log = logging.getLogger(__name__)

OSM_PBF_SUFFIXES = (".pbf",)
OSM_XML_SUFFIXES = (".osm", ".osm.bz2", ".osm.gz", ".xml", ".osm.xml")

Progress = Callable[[str], None]
"""Called with one line of text: at the start of each step, and within a long step."""


class StepProgress:
    """Progress within one step: ``update(done, total)`` says ``"<label>: 1,234 of 5,678 <unit> (22%)"``
    through ``say``, at most once per ``interval`` seconds (so a short step says nothing)."""

    def __init__(self, say: Progress, label: str, unit: str, *, interval: float = 1.0) -> None:
        self.say, self.label, self.unit, self.interval = say, label, unit, interval
        self.last = time.perf_counter()

    def update(self, done: int, total: int = 0) -> None:
        now = time.perf_counter()
        if now - self.last < self.interval:
            return
        self.last = now
        of = f" of {total:,}" if total > 0 else ""
        pct = f" ({100.0 * done / total:.0f}%)" if total > 0 else ""
        self.say(f"{self.label}: {done:,}{of} {self.unit}{pct}")


def source_format(path: Path) -> str:
    """``"osm-pbf"``, ``"osm-xml"`` or ``"gis"`` from the file name; InputError otherwise."""
    name = path.name.lower()
    if name.endswith(OSM_PBF_SUFFIXES):
        return "osm-pbf"
    if name.endswith(OSM_XML_SUFFIXES):
        return "osm-xml"
    if name.endswith(GIS_SUFFIXES):
        return "gis"
    raise InputError(
        f"unknown input format: {path.name} "
        "(expected .osm.pbf, .osm, .osm.bz2, .geojson, .gpkg, .shp, .fgb or .parquet)"
    )


@dataclass
class BuildReport:
    """What a build did: raw and final sizes, components, dropped features and why."""

    source_format: str = ""
    raw_nodes: int = 0
    raw_edges: int = 0
    dropped: dict[str, int] = field(default_factory=dict)
    weak_components: int = 0
    strong_components: int = 0
    source_weak_components: int = 0
    source_strong_components: int = 0
    restrictions_read: int = 0
    restrictions_unmapped: int = 0
    self_loops_split: int = 0
    self_loops_dropped: int = 0
    fields: dict[str, Any] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)


def _without_gc(fn: Callable[..., RoadGraph]) -> Callable[..., RoadGraph]:
    """Run ``fn`` with the cyclic garbage collector off: a build makes millions of small
    objects and no cycles, so the collector only costs time there."""

    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> RoadGraph:
        was = gc.isenabled()
        gc.disable()
        try:
            return fn(*args, **kwargs)
        finally:
            if was:
                gc.enable()

    return run


@_without_gc
def build_map(
    source: str | Path | None,
    *,
    place: str | None = None,
    bbox: tuple[float, float, float, float] | None = None,
    consolidate_tolerance: float | None = None,
    snap_tolerance: float = 0.01,
    node_crossings: bool = False,
    oneway_field: str | None = None,
    oneway_convention: OnewayConvention | str | None = None,
    name_field: str | None = None,
    speed_field: str | None = None,
    highway_field: str | None = None,
    id_field: str | None = None,
    node_id_fields: tuple[str, str] | None = None,
    topology: str = "auto",
    directed: bool = False,
    crs: str | None = None,
    layer: str | None = None,
    network_type: str = "drive",
    progress: Progress | None = None,
    progress_interval: float = 1.0,
    engine: str = "arrays",
) -> RoadGraph:
    """Build a prepared road graph.

    Parameters
    ----------
    source
        An OSM file (``.osm.pbf``, ``.osm``, ``.osm.bz2``) or GIS lines (``.geojson``,
        ``.gpkg``, ``.shp``). ``None`` with ``place`` or ``bbox`` downloads through osmnx.
    place, bbox
        Download by place name, or ``bbox=(west, south, east, north)`` in degrees; with an
        OSM ``source`` the bbox clips it instead.
    consolidate_tolerance
        Merge complex intersections whose nodes lie within this many metres
        (:func:`osmnx.consolidate_intersections`); ``None`` (default) keeps every node.
    snap_tolerance, node_crossings, oneway_field, oneway_convention, name_field, speed_field,
    highway_field, id_field, node_id_fields, topology, directed, crs, layer
        GIS options, see :class:`graph.gis.GisOptions`.
    network_type
        osmnx network type for OSM input: ``"drive"`` (default) or ``"drive_service"``.
    progress
        Called with a short message at the start of each step, and within the long ones
        (reading, simplifying, building) with how far they are.
    progress_interval
        Seconds between two messages within a step.
    engine
        ``"arrays"`` (default): read into arrays and simplify with compiled kernels;
        ``"osmnx"``: the reference, a networkx graph simplified by :func:`osmnx.simplify_graph`
        (always used for downloads and with ``consolidate_tolerance``). Both give the same map.

    Returns
    -------
    RoadGraph
        With ``meta`` holding ``source`` (path, format, sha256, bytes), ``build`` (the
        parameters) and ``report`` (a :class:`BuildReport` as a dict).

    Raises
    ------
    InputError
        Missing file, unknown format, corrupt data, no drivable roads, unreadable CRS.
    """
    from graph.artifact import file_sha256
    from graph.components import component_counts
    from graph.raw_network import RawNetwork, raw_to_nx, road_graph_arrays, simplify_arrays
    from graph.simplify import consolidate, simplify, to_road_graph

    if engine not in ("arrays", "osmnx"):
        raise InputError(f"unknown build engine {engine!r} (use arrays or osmnx)")

    say = progress or (lambda msg: log.info("%s", msg))
    report = BuildReport()
    params: dict[str, Any] = {
        "network_type": network_type,
        "consolidate_tolerance": consolidate_tolerance,
        "place": place,
        "bbox": list(bbox) if bbox else None,
    }
    t0 = time.perf_counter()
    restrictions: list[tuple[int, int, int, int]] = []
    src_meta: dict[str, Any]
    raw_net: RawNetwork | None = None
    G: nx.MultiDiGraph | None = None
    if source is None:
        if place is None and bbox is None:
            raise InputError("give a source file, a place name or a bounding box")
        if directed:
            raise InputError("directed lines are a GIS input option; a download is OpenStreetMap data")
        from graph.osm import download_graph

        say(f"downloading the {network_type} network from OpenStreetMap")
        G, crs_out, dropped = download_graph(place=place, bbox=bbox, network_type=network_type)
        report.source_format = "osm-download"
        src_meta = {"format": "osm-download", "place": place, "bbox": list(bbox) if bbox else None}
    else:
        path = Path(source)
        if not path.exists():
            raise InputError(f"no such file: {path}")
        if path.is_dir():
            raise InputError(f"{path} is a directory, not a road data file")
        fmt = source_format(path)
        if directed and fmt != "gis":
            raise InputError(f"directed lines are a GIS input option; {path.name} is OpenStreetMap data")
        report.source_format = fmt
        say(f"checksumming {path.name}")
        src_meta = {
            "path": str(path),
            "name": path.name,
            "format": fmt,
            "bytes": path.stat().st_size,
            "sha256": file_sha256(path),
        }
        if fmt == "gis":
            from graph.gis import lines_to_raw

            conv = (
                OnewayConvention.parse(oneway_convention)
                if isinstance(oneway_convention, str)
                else oneway_convention or OnewayConvention()
            )
            opts = GisOptions(
                oneway_field=oneway_field,
                oneway_convention=conv,
                name_field=name_field,
                speed_field=speed_field,
                highway_field=highway_field,
                id_field=id_field,
                node_id_fields=node_id_fields,
                topology=topology,
                directed=directed,
                snap_tolerance=snap_tolerance,
                node_crossings=node_crossings,
                crs=crs,
                layer=layer,
                bbox=bbox,
            )
            params.update(
                {
                    "snap_tolerance": snap_tolerance,
                    "node_crossings": node_crossings,
                    "oneway_field": oneway_field,
                    "oneway_convention": {k: sorted(v) for k, v in asdict(conv).items()},
                    "name_field": name_field,
                    "speed_field": speed_field,
                    "highway_field": highway_field,
                    "id_field": id_field,
                    "node_id_fields": list(node_id_fields) if node_id_fields else None,
                    "topology": topology,
                    "directed": directed,
                    "crs": crs,
                    "layer": layer,
                }
            )
            say(f"reading GIS lines from {path.name}")
            step = StepProgress(say, f"reading {path.name}", "features", interval=progress_interval)
            raw_net, dropped, fields = lines_to_raw(path, opts, progress=step.update)
            report.fields = fields
        else:
            from graph.osm import read_osm_raw

            say(f"reading OSM {'PBF' if fmt == 'osm-pbf' else 'XML'} from {path.name}")
            step = StepProgress(say, f"reading {path.name}", "roads kept", interval=progress_interval)
            raw_net, dropped, restrictions = read_osm_raw(
                path, network_type=network_type, bbox=bbox, progress=step.update
            )
            report.restrictions_read = len(restrictions)
    report.dropped = dropped
    report.seconds["read"] = time.perf_counter() - t0
    meta = {"source": src_meta, "build": params}
    use_nx = G is not None or engine == "osmnx" or bool(consolidate_tolerance and consolidate_tolerance > 0)
    if raw_net is not None:
        crs_out = raw_net.crs
        report.raw_nodes, report.raw_edges = raw_net.n_nodes, raw_net.n_edges
        if use_nx:
            G = raw_to_nx(raw_net)
    else:
        assert G is not None
        report.raw_nodes, report.raw_edges = G.number_of_nodes(), G.number_of_edges()
    if report.raw_edges == 0:
        raise InputError(f"{src_meta.get('name', 'the source')} has no drivable roads")
    if not use_nx:
        assert raw_net is not None
        w, st = component_counts(raw_net.n_nodes, raw_net.edge_src, raw_net.edge_dst)
        report.source_weak_components, report.source_strong_components = w, st
        t1 = time.perf_counter()
        say(f"simplifying {report.raw_nodes:,} nodes / {report.raw_edges:,} edges to intersections")
        step = StepProgress(say, "simplifying", "paths still growing", interval=progress_interval)
        simp = simplify_arrays(raw_net, on_step=step.update)
        report.seconds["simplify"] = time.perf_counter() - t1
        t2 = time.perf_counter()
        say(f"building {len(simp.ptr) - 1:,} edges with their way pieces")
        kw, info = road_graph_arrays(raw_net, simp, restrictions=restrictions, meta=meta)
        del raw_net, simp  # the raw network goes before the graph's own arrays are made
        say(f"deriving lengths, bearings, reverse edges and adjacency of {len(kw['edge_u']):,} edges")
        rg = RoadGraph.from_edges(**kw)
        del kw
        report.weak_components, report.strong_components = component_counts(rg.n_nodes, rg.edge_u, rg.edge_v)
    else:
        assert G is not None
        import networkx as nx

        report.source_weak_components = nx.number_weakly_connected_components(G)
        report.source_strong_components = nx.number_strongly_connected_components(G)
        t1 = time.perf_counter()
        say(f"simplifying {report.raw_nodes:,} nodes / {report.raw_edges:,} edges to intersections (osmnx)")
        raw = G
        G = simplify(G)
        if consolidate_tolerance is not None and consolidate_tolerance > 0:
            say(f"consolidating intersections within {consolidate_tolerance:g} m")
            G = consolidate(G, consolidate_tolerance)
            if G.number_of_edges() == 0:
                raise InputError(
                    f"no roads left after consolidating intersections within {consolidate_tolerance:g} m"
                )
        report.seconds["simplify"] = time.perf_counter() - t1
        report.weak_components = nx.number_weakly_connected_components(G)
        report.strong_components = nx.number_strongly_connected_components(G)
        t2 = time.perf_counter()
        say(f"converting {G.number_of_nodes():,} nodes / {G.number_of_edges():,} edges to arrays")
        rg, info = to_road_graph(G, crs=crs_out, restrictions=restrictions, meta=meta, raw=raw)
        del raw, G
    report.restrictions_unmapped = int(info["restrictions_unmapped"])
    report.self_loops_split = int(info["self_loops_split"])
    report.self_loops_dropped = int(info["self_loops_dropped"])
    report.seconds["convert"] = time.perf_counter() - t2
    report.seconds["total"] = time.perf_counter() - t0
    rg.meta["report"] = asdict(report)
    return rg
