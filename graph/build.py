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
from typing import TYPE_CHECKING, Any, NamedTuple

from graph.errors import InputError
from graph.extras import require_prep
from graph.gis import GIS_SUFFIXES, GisOptions
from graph.road_graph import RoadGraph

if TYPE_CHECKING:
    import networkx as nx

    from graph.raw_network import RawNetwork, Simplified

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


@dataclass(frozen=True)
class OsmOptions:
    """Options for OpenStreetMap input: a file, or a download through osmnx.

    Attributes
    ----------
    network_type
        osmnx network type: ``"drive"`` (default) or ``"drive_service"``.
    place
        Download the network of this place name (with no source file).
    bbox
        ``(west, south, east, north)`` in degrees: the area to download, or the part of an
        OSM file to keep.
    """

    network_type: str = "drive"
    place: str | None = None
    bbox: tuple[float, float, float, float] | None = None


@dataclass(frozen=True)
class BuildOptions:
    """How a map is built from what was read.

    Attributes
    ----------
    engine
        ``"arrays"`` (default): simplify with whole-array steps; ``"osmnx"``: the reference, a
        networkx graph simplified by :func:`osmnx.simplify_graph` (always used for downloads
        and with ``consolidate_tolerance``). Both give the same map.
    consolidate_tolerance
        Merge complex intersections whose nodes lie within this many metres
        (:func:`osmnx.consolidate_intersections`); ``None`` (default) keeps every node.
    progress_interval
        Seconds between two progress messages within a step.
    """

    engine: str = "arrays"
    consolidate_tolerance: float | None = None
    progress_interval: float = 1.0


DEFAULT_GIS = GisOptions()
DEFAULT_OSM = OsmOptions()
DEFAULT_BUILD = BuildOptions()


@_without_gc
def build_map(
    source: str | Path | None,
    *,
    gis: GisOptions = DEFAULT_GIS,
    osm: OsmOptions = DEFAULT_OSM,
    options: BuildOptions = DEFAULT_BUILD,
    progress: Progress | None = None,
) -> RoadGraph:
    """Build a prepared road graph.

    Parameters
    ----------
    source
        An OSM file (``.osm.pbf``, ``.osm``, ``.osm.bz2``) or GIS lines (``.geojson``,
        ``.gpkg``, ``.shp``, ``.fgb``, ``.parquet``). ``None`` downloads ``osm.place`` or
        ``osm.bbox`` through osmnx.
    gis
        How GIS lines are read (:class:`graph.gis.GisOptions`); for GIS sources.
    osm
        OpenStreetMap options (:class:`OsmOptions`); for OSM files and downloads.
    options
        How the map is built (:class:`BuildOptions`).
    progress
        Called with a short message at the start of each step, and within the long ones
        (reading, simplifying, building) with how far they are.

    Returns
    -------
    RoadGraph
        With ``meta`` holding ``source`` (path, format, sha256, bytes), ``build`` (the
        parameters) and ``report`` (a :class:`BuildReport` as a dict).

    Raises
    ------
    InputError
        Missing file, unknown format, corrupt data, no drivable roads, unreadable CRS.
    MissingExtraError
        The ``prep`` extra is not installed.
    """
    require_prep(needed_for="map preparation")
    if options.engine not in ("arrays", "osmnx"):
        raise InputError(f"unknown build engine {options.engine!r} (use arrays or osmnx)")
    step = _Steps(progress or (lambda msg: log.info("%s", msg)), options.progress_interval)
    report = BuildReport()
    t0 = time.perf_counter()
    if source is None:
        read = _download(osm, gis, step=step, report=report)
    else:
        read = _read_file(Path(source), gis, osm, step=step, report=report)
    report.dropped = read.dropped
    report.seconds["read"] = time.perf_counter() - t0
    meta = {"source": read.source, "build": _build_params(read, gis, osm, options)}
    tol = options.consolidate_tolerance
    if read.raw is not None:
        report.raw_nodes, report.raw_edges = read.raw.n_nodes, read.raw.n_edges
    else:
        assert read.graph is not None
        report.raw_nodes, report.raw_edges = read.graph.number_of_nodes(), read.graph.number_of_edges()
    if report.raw_edges == 0:
        raise InputError(f"{read.source.get('name', 'the source')} has no drivable roads")
    if read.raw is not None and options.engine == "arrays" and not (tol and tol > 0):
        from graph.raw_network import road_graph_arrays

        simp = _simplify_arrays(read.raw, step=step, report=report)
        t2 = time.perf_counter()
        step.say(f"building {len(simp.ptr) - 1:,} edges with their way pieces")
        kw, info = road_graph_arrays(read.raw, simp, restrictions=read.restrictions, meta=meta)
        del read, simp  # the raw network goes before the graph's own arrays are made
        rg = _graph_of(kw, step=step, report=report)
        report.seconds["convert"] = time.perf_counter() - t2
    else:
        rg, info = _build_with_osmnx(read, meta, tol, step=step, report=report)
    report.restrictions_unmapped = int(info["restrictions_unmapped"])
    report.self_loops_split = int(info["self_loops_split"])
    report.self_loops_dropped = int(info["self_loops_dropped"])
    report.seconds["total"] = time.perf_counter() - t0
    rg.meta["report"] = asdict(report)
    return rg


class _Steps:
    """The build's progress: a line at the start of each step, :class:`StepProgress` within one."""

    def __init__(self, say: Progress, interval: float) -> None:
        self.say, self.interval = say, interval

    def within(self, label: str, unit: str) -> StepProgress:
        return StepProgress(self.say, label, unit, interval=self.interval)


class _Read(NamedTuple):
    """What reading the source gave: a raw network of arrays (files) or a networkx graph
    (downloads), what was dropped, the turn restrictions and the source's description."""

    raw: RawNetwork | None
    graph: nx.MultiDiGraph | None
    crs: str
    dropped: dict[str, int]
    restrictions: list[tuple[int, int, int, int]]
    source: dict[str, Any]
    format: str


def _download(osm: OsmOptions, gis: GisOptions, *, step: _Steps, report: BuildReport) -> _Read:
    """Download ``osm.place`` or ``osm.bbox`` from OpenStreetMap as a raw networkx graph."""
    if osm.place is None and osm.bbox is None:
        raise InputError("give a source file, a place name or a bounding box")
    if gis.directed:
        raise InputError("directed lines are a GIS input option; a download is OpenStreetMap data")
    from graph.osm import download_graph

    step.say(f"downloading the {osm.network_type} network from OpenStreetMap")
    G, crs, dropped = download_graph(place=osm.place, bbox=osm.bbox, network_type=osm.network_type)
    report.source_format = "osm-download"
    src = {"format": "osm-download", "place": osm.place, "bbox": list(osm.bbox) if osm.bbox else None}
    return _Read(None, G, crs, dropped, [], src, "osm-download")


def _read_file(path: Path, gis: GisOptions, osm: OsmOptions, *, step: _Steps, report: BuildReport) -> _Read:
    """Read an OSM or GIS file into a raw network of arrays."""
    from graph.artifact import file_sha256

    if not path.exists():
        raise InputError(f"no such file: {path}")
    if path.is_dir():
        raise InputError(f"{path} is a directory, not a road data file")
    fmt = source_format(path)
    if gis.directed and fmt != "gis":
        raise InputError(f"directed lines are a GIS input option; {path.name} is OpenStreetMap data")
    report.source_format = fmt
    step.say(f"checksumming {path.name}")
    src = {
        "path": str(path),
        "name": path.name,
        "format": fmt,
        "bytes": path.stat().st_size,
        "sha256": file_sha256(path),
    }
    if fmt == "gis":
        from graph.gis import lines_to_raw

        step.say(f"reading GIS lines from {path.name}")
        within = step.within(f"reading {path.name}", "features")
        raw, dropped, fields = lines_to_raw(path, gis, progress=within.update)
        report.fields = fields
        return _Read(raw, None, raw.crs, dropped, [], src, fmt)
    from graph.osm import read_osm_raw

    step.say(f"reading OSM {'PBF' if fmt == 'osm-pbf' else 'XML'} from {path.name}")
    within = step.within(f"reading {path.name}", "roads kept")
    raw, dropped, restrictions = read_osm_raw(
        path, network_type=osm.network_type, bbox=osm.bbox, progress=within.update
    )
    report.restrictions_read = len(restrictions)
    return _Read(raw, None, raw.crs, dropped, restrictions, src, fmt)


def _build_params(read: _Read, gis: GisOptions, osm: OsmOptions, options: BuildOptions) -> dict[str, Any]:
    """The build parameters recorded in the map: the OSM ones, and the GIS ones for GIS lines."""
    bbox = gis.bbox if read.format == "gis" else osm.bbox
    params: dict[str, Any] = {
        "network_type": osm.network_type,
        "consolidate_tolerance": options.consolidate_tolerance,
        "place": osm.place,
        "bbox": list(bbox) if bbox else None,
    }
    if read.format == "gis":
        params.update(
            {
                "snap_tolerance": gis.snap_tolerance,
                "node_crossings": gis.node_crossings,
                "oneway_field": gis.oneway_field,
                "oneway_convention": {k: sorted(v) for k, v in asdict(gis.oneway_convention).items()},
                "name_field": gis.name_field,
                "speed_field": gis.speed_field,
                "highway_field": gis.highway_field,
                "id_field": gis.id_field,
                "node_id_fields": list(gis.node_id_fields) if gis.node_id_fields else None,
                "topology": gis.topology,
                "directed": gis.directed,
                "crs": gis.crs,
                "layer": gis.layer,
            }
        )
    return params


def _simplify_arrays(raw: RawNetwork, *, step: _Steps, report: BuildReport) -> Simplified:
    """Simplify the raw network with whole-array steps (the default engine)."""
    from graph.components import component_counts
    from graph.raw_network import simplify_arrays

    w, st = component_counts(raw.n_nodes, raw.edge_src, raw.edge_dst)
    report.source_weak_components, report.source_strong_components = w, st
    t1 = time.perf_counter()
    step.say(f"simplifying {report.raw_nodes:,} nodes / {report.raw_edges:,} edges to intersections")
    simp = simplify_arrays(raw, on_step=step.within("simplifying", "paths still growing").update)
    report.seconds["simplify"] = time.perf_counter() - t1
    return simp


def _graph_of(kw: dict[str, Any], *, step: _Steps, report: BuildReport) -> RoadGraph:
    """The graph of :meth:`RoadGraph.from_edges` arguments, and its components counted."""
    from graph.components import component_counts

    step.say(f"deriving lengths, bearings, reverse edges and adjacency of {len(kw['edges'].u):,} edges")
    rg = RoadGraph.from_edges(**kw)
    report.weak_components, report.strong_components = component_counts(rg.n_nodes, rg.edge_u, rg.edge_v)
    return rg


def _build_with_osmnx(
    read: _Read, meta: dict[str, Any], tolerance: float | None, *, step: _Steps, report: BuildReport
) -> tuple[RoadGraph, dict[str, Any]]:
    """Simplify (and consolidate) a networkx graph with osmnx and convert it (the reference)."""
    import networkx as nx

    from graph.simplify import consolidate, simplify, to_road_graph

    if read.graph is not None:
        raw = read.graph
    else:
        from graph.raw_network import raw_to_nx

        assert read.raw is not None
        raw = raw_to_nx(read.raw)
    crs, restrictions = read.crs, read.restrictions
    del read
    report.source_weak_components = nx.number_weakly_connected_components(raw)
    report.source_strong_components = nx.number_strongly_connected_components(raw)
    t1 = time.perf_counter()
    step.say(f"simplifying {report.raw_nodes:,} nodes / {report.raw_edges:,} edges to intersections (osmnx)")
    G = simplify(raw)
    if tolerance is not None and tolerance > 0:
        step.say(f"consolidating intersections within {tolerance:g} m")
        G = consolidate(G, tolerance)
        if G.number_of_edges() == 0:
            raise InputError(f"no roads left after consolidating intersections within {tolerance:g} m")
    report.seconds["simplify"] = time.perf_counter() - t1
    report.weak_components = nx.number_weakly_connected_components(G)
    report.strong_components = nx.number_strongly_connected_components(G)
    t2 = time.perf_counter()
    step.say(f"converting {G.number_of_nodes():,} nodes / {G.number_of_edges():,} edges to arrays")
    rg, info = to_road_graph(G, crs=crs, restrictions=restrictions, meta=meta, raw=raw)
    del raw, G
    report.seconds["convert"] = time.perf_counter() - t2
    return rg, info
