"""OpenStreetMap (PBF, XML, XML.bz2) -> raw MultiDiGraph, plus turn restrictions.

pyosmium reads every format in one pass (node locations kept in its C++ index, only
highway ways and restriction relations reach Python). Ways are filtered with osmnx's own
network filter (``"drive"`` by default), one-way rules follow osmnx, and references to nodes
missing from a clipped extract split the way there instead of failing.
"""

from __future__ import annotations

import logging
import re
from array import array
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.errors import InputError
from graph.gis_network import parse_speed
from graph.keys import unique_inverse
from graph.projection import to_xy, utm_crs
from graph.raw_network import RawNetwork, compact_raw
from graph.road_graph import RESTRICTION_NO, RESTRICTION_ONLY, Labels

if TYPE_CHECKING:
    import networkx as nx

log = logging.getLogger(__name__)

# osmnx's one-way conventions (osmnx.graph._is_path_one_way / _is_path_reversed)
ONEWAY_VALUES = frozenset({"yes", "true", "1", "-1", "reverse", "T", "F"})
REVERSED_VALUES = frozenset({"-1", "reverse", "T"})

# osmnx 2.x's "drive" and "drive_service" filters, owned here (osmnx keeps them in a private
# module; tests/test_prep_osm.py compares them with the installed osmnx's): importing osmnx
# costs seconds and ~50 MB in every build
_DRIVE_FILTERS = {
    "drive": (
        '["highway"]["area"!~"yes"]["access"!~"private"]'
        '["highway"!~"abandoned|bridleway|bus_guideway|construction|corridor|'
        "cycleway|elevator|escalator|footway|no|path|pedestrian|planned|platform|"
        'proposed|raceway|razed|rest_area|service|services|steps|track"]'
        '["motor_vehicle"!~"no"]["motorcar"!~"no"]'
        '["service"!~"alley|driveway|emergency_access|parking|parking_aisle|private"]'
    ),
    "drive_service": (
        '["highway"]["area"!~"yes"]["access"!~"private"]'
        '["highway"!~"abandoned|bridleway|bus_guideway|construction|corridor|'
        "cycleway|elevator|escalator|footway|no|path|pedestrian|planned|platform|"
        'proposed|raceway|razed|rest_area|services|steps|track"]'
        '["motor_vehicle"!~"no"]["motorcar"!~"no"]'
        '["service"!~"emergency_access|parking|parking_aisle|private"]'
    ),
}
_NOT_FOR_CARS = '["highway"!~"^(trail|bus_stop|via_ferrata|busway)$"]'
_CLAUSE = re.compile(r'\["([^"]+)"(?:(!~|~|!=|=)"([^"]*)")?\]')


@dataclass(frozen=True)
class TagFilter:
    """An Overpass-style way filter (the subset osmnx uses), applied to a tag dict."""

    clauses: tuple[tuple[str, str | None, re.Pattern[str] | str | None], ...]

    @classmethod
    def from_overpass(cls, text: str) -> TagFilter:
        out: list[tuple[str, str | None, re.Pattern[str] | str | None]] = []
        for key, op, val in _CLAUSE.findall(text):
            if not op:
                out.append((key, None, None))
            elif op in ("~", "!~"):
                out.append((key, op, re.compile(val)))
            else:
                out.append((key, op, val))
        return cls(tuple(out))

    def __call__(self, tags: Mapping[str, str] | Any) -> bool:
        """True when ``tags`` (a dict or pyosmium's TagList: ``get`` is all it needs) pass."""
        for key, op, val in self.clauses:
            v = tags.get(key)
            if op is None:
                if v is None:
                    return False
            elif op == "!~":
                if v is not None and val.search(v):  # type: ignore[union-attr]
                    return False
            elif op == "~":
                if v is None or not val.search(v):  # type: ignore[union-attr]
                    return False
            elif op == "=":
                if v != val:
                    return False
            elif op == "!=" and v == val:
                return False
        return True


def network_filter(network_type: str) -> TagFilter:
    """osmnx's way filter for ``network_type`` (``"drive"`` or ``"drive_service"``), with the
    roads that are never for cars left out."""
    text = _DRIVE_FILTERS.get(network_type)
    if text is None:
        raise InputError(f"unsupported network type {network_type!r} (use {' or '.join(_DRIVE_FILTERS)})")
    # osmnx lets non-standard highway=trail through; it is never a road for cars
    return TagFilter.from_overpass(text + _NOT_FOR_CARS)


def is_oneway(tags: dict[str, str]) -> bool:
    """osmnx's rule: an explicit one-way value, or a roundabout."""
    return tags.get("oneway") in ONEWAY_VALUES or tags.get("junction") == "roundabout"


Relation = tuple[dict[str, str], list[tuple[str, str, int]]]
WAY_KEYS = ("highway", "name", "oneway", "junction", "maxspeed")
"""The tags of a kept way that the build reads."""


class Ways(NamedTuple):
    """Kept ways: ``ids``, and ``tags`` by key of :data:`WAY_KEYS` as one code per way into
    that key's table of values (-1: absent or empty); their node refs flattened, way ``i``
    owning ``ref[ptr[i]:ptr[i+1]]`` with each node's location (``ok`` false when missing)."""

    ids: list[int]
    tags: dict[str, Labels]
    ptr: NDArray[np.int64]
    ref: NDArray[np.int64]
    lon: NDArray[np.float64]
    lat: NDArray[np.float64]
    ok: NDArray[np.bool_]


def scan_osm(
    path: Path, keep: TagFilter, dropped: dict[str, int], *, progress: Callable[[int], None] | None = None
) -> tuple[Ways, list[Relation]]:
    """One pyosmium pass: ways passing ``keep`` with node refs and locations (flat arrays),
    and restrictions. A node reference whose node is missing from the file has ``ok`` false.
    ``progress`` is called now and then with the number of ways kept so far.
    """
    import osmium

    ids: list[int] = []
    tables: dict[str, dict[str, int]] = {k: {} for k in WAY_KEYS}
    codes: dict[str, array[int]] = {k: array("i") for k in WAY_KEYS}
    key_tables = [(k, tables[k].setdefault, codes[k].append) for k in WAY_KEYS]
    counts: list[int] = []
    refs = array("q")
    lons = array("d")
    lats = array("d")
    oks = array("b")
    relations: list[Relation] = []

    def _drop(reason: str, n: int = 1) -> None:
        dropped[reason] = dropped.get(reason, 0) + n

    try:
        fp = (
            osmium.FileProcessor(str(path), osmium.osm.WAY | osmium.osm.RELATION | osmium.osm.NODE)
            .with_locations()
            .with_filter(osmium.filter.EntityFilter(osmium.osm.WAY | osmium.osm.RELATION))
            .with_filter(osmium.filter.KeyFilter("highway", "restriction", "restriction:motorcar"))
        )
        for obj in fp:
            if isinstance(obj, osmium.osm.Way):
                tags = obj.tags
                if "highway" not in tags:
                    continue
                if not keep(tags):
                    _drop("way not drivable (osmnx network filter)")
                    continue
                n = 0
                for nd in obj.nodes:
                    loc = nd.location
                    refs.append(nd.ref)
                    if loc.valid():
                        lons.append(loc.lon)
                        lats.append(loc.lat)
                        oks.append(1)
                    else:
                        lons.append(0.0)
                        lats.append(0.0)
                        oks.append(0)
                    n += 1
                ids.append(obj.id)
                for k, put, add in key_tables:
                    v = tags.get(k)
                    add(put(v, len(tables[k])) if v else -1)
                counts.append(n)
                if progress is not None and not len(ids) % 4096:
                    progress(len(ids))
            elif isinstance(obj, osmium.osm.Relation):
                rtags = dict(obj.tags)
                if rtags.get("type") != "restriction":
                    continue
                relations.append((rtags, [(m.role, m.type, m.ref) for m in obj.members]))
    except RuntimeError as exc:
        raise InputError(f"corrupt or unreadable OSM file {path.name}: {exc}") from exc
    ptr = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(np.asarray(counts, dtype=np.int64), out=ptr[1:])
    ways = Ways(
        ids=ids,
        tags={k: Labels(np.frombuffer(codes[k], dtype=np.int32).copy(), list(tables[k])) for k in WAY_KEYS},
        ptr=ptr,
        ref=np.frombuffer(refs, dtype=np.int64).copy() if len(refs) else np.zeros(0, np.int64),
        lon=np.frombuffer(lons, dtype=np.float64).copy() if len(lons) else np.zeros(0),
        lat=np.frombuffer(lats, dtype=np.float64).copy() if len(lats) else np.zeros(0),
        ok=np.frombuffer(oks, dtype=np.int8).astype(bool),
    )
    return ways, relations


def read_osm(
    path: Path,
    *,
    network_type: str = "drive",
    bbox: tuple[float, float, float, float] | None = None,
) -> tuple[nx.MultiDiGraph, str, dict[str, int], list[tuple[int, int, int, int]]]:
    """Read drivable ways of an OSM file into a raw MultiDiGraph in the local UTM CRS.

    Parameters
    ----------
    path
        ``.osm.pbf``, ``.osm`` or ``.osm.bz2``.
    network_type
        osmnx network type deciding which ways are roads.
    bbox
        ``(west, south, east, north)``: drop nodes outside (ways are cut there).

    Returns
    -------
    G, crs, dropped, restrictions
        Raw graph (nodes ``x``, ``y``, ``lon``, ``lat``, ``osmid``; edges ``osmid`` = way id,
        ``name``, ``highway``, ``speed_kph``, ``oneway``), the CRS, dropped items by reason,
        and restrictions as ``(from_way, via_node_id, to_way, kind)``.
    """
    raw, dropped, restrictions = read_osm_raw(path, network_type=network_type, bbox=bbox)
    from graph.raw_network import raw_to_nx

    return raw_to_nx(raw), raw.crs, dropped, restrictions


def read_osm_raw(
    path: Path,
    *,
    network_type: str = "drive",
    bbox: tuple[float, float, float, float] | None = None,
    progress: Callable[[int], None] | None = None,
) -> tuple[RawNetwork, dict[str, int], list[tuple[int, int, int, int]]]:
    """Read drivable ways of an OSM file into a raw network (arrays; see :func:`read_osm`);
    ``progress`` gets the number of ways kept so far, now and then."""
    keep = network_filter(network_type)
    dropped: dict[str, int] = {}
    ways, relations = scan_osm(path, keep, dropped, progress=progress)
    raw = _ways_to_raw(ways, bbox=bbox, dropped=dropped)
    restrictions = _restrictions(relations, dropped)
    return raw, dropped, restrictions


def _ways_to_raw(
    ways: Ways,
    *,
    bbox: tuple[float, float, float, float] | None,
    dropped: dict[str, int],
) -> RawNetwork:
    """Ways -> raw network: each way cut at missing (or, with ``bbox``, outside) nodes into
    runs of at least two nodes; a run is one feature, its consecutive node pairs its edges
    (both directions unless one-way; reversed ways run backwards)."""
    ok = _usable_refs(ways, bbox, dropped)
    runs = _runs(ways, ok, dropped)
    # nodes: every usable reference, in order of first appearance (its last location wins)
    ok_pos = np.nonzero(ok)[0]
    ids, first, inv = unique_inverse(ways.ref[ok_pos])
    if len(ids) == 0:
        return _empty_raw()
    order = np.argsort(first, kind="stable")
    rank = np.empty(len(ids), dtype=np.int64)
    rank[order] = np.arange(len(ids))
    last = np.zeros(len(ids), dtype=np.int64)
    last[inv.ravel()] = ok_pos  # later positions overwrite earlier ones
    ll = np.column_stack([ways.lon[last], ways.lat[last]])[order]
    crs = utm_crs(float(np.median(ll[:, 0])), float(np.median(ll[:, 1])))
    node = rank[np.searchsorted(ids, ways.ref[runs.pos])]
    # features: the long runs
    keep_pos = runs.long_run[runs.g]
    node, g = node[keep_pos], runs.g[keep_pos]
    feat_runs = np.nonzero(runs.long_run)[0]
    feat_of_run = np.full(len(runs.long_run), -1, dtype=np.int64)
    feat_of_run[feat_runs] = np.arange(len(feat_runs))
    fw = runs.way[feat_runs]
    tags = {k: v.take(fw) for k, v in ways.tags.items()}
    ow, junction = tags["oneway"], tags["junction"]
    oneway = _flag(ow, ONEWAY_VALUES) | _flag(junction, {"roundabout"})  # osmnx's rule, see is_oneway
    src, dst, feat = _feature_edges(node, feat_of_run[g], oneway, _flag(ow, REVERSED_VALUES))
    raw = RawNetwork(
        crs=crs,
        node_key=ids[order].astype(np.int64, copy=False),
        node_xy=to_xy(crs, ll[:, 0], ll[:, 1]),
        node_lonlat=ll,
        edge_src=src,
        edge_dst=dst,
        edge_feat=feat,
        edge_oneway=oneway[feat],
        feat_way_id=np.asarray(ways.ids, dtype=np.int64)[fw],
        feat_name=tags["name"],
        feat_highway=tags["highway"],
        feat_speed_kph=_per_value(tags["maxspeed"], _maxspeed),
    )
    return compact_raw(raw)


def _usable_refs(
    ways: Ways, bbox: tuple[float, float, float, float] | None, dropped: dict[str, int]
) -> NDArray[np.bool_]:
    """Which node references are usable: known in the extract and, with ``bbox``, inside it
    (the others counted in ``dropped``)."""
    ok = ways.ok.copy()
    n_dangling = int((~ok).sum())
    n_outside = 0
    if bbox is not None:
        inside = (bbox[0] <= ways.lon) & (ways.lon <= bbox[2]) & (bbox[1] <= ways.lat) & (ways.lat <= bbox[3])
        n_outside = int((ok & ~inside).sum())
        ok &= inside
    if n_dangling:
        dropped["dangling node references (missing from the extract)"] = n_dangling
    if n_outside:
        dropped["node references outside the bbox"] = n_outside
    return ok


class _Runs(NamedTuple):
    """The runs of usable references: the kept references' positions ``pos`` and runs ``g``
    (a node repeated in a row kept once), which runs have at least two nodes, and each run's
    way."""

    pos: NDArray[np.int64]
    g: NDArray[np.int64]
    long_run: NDArray[np.bool_]
    way: NDArray[np.int64]


def _runs(ways: Ways, ok: NDArray[np.bool_], dropped: dict[str, int]) -> _Runs:
    """A new run at each way start and after each unusable node; ways with no run of two known
    nodes are counted in ``dropped``."""
    n_ref, n_way = len(ways.ref), len(ways.ids)
    way_of = np.repeat(np.arange(n_way), np.diff(ways.ptr))
    start = np.zeros(n_ref, dtype=bool)
    start[ways.ptr[:-1][np.diff(ways.ptr) > 0]] = True
    start[1:] |= ~ok[:-1]
    grp = np.cumsum(start) - 1
    pos = np.nonzero(ok)[0]
    g = grp[pos]
    r = ways.ref[pos]
    dup = np.zeros(len(pos), dtype=bool)
    dup[1:] = (g[1:] == g[:-1]) & (r[1:] == r[:-1])  # a node repeated in a row
    pos, g = pos[~dup], g[~dup]
    run_len = np.bincount(g, minlength=int(grp.max()) + 1 if n_ref else 0)
    long_run = run_len >= 2
    run_way = np.full(len(run_len), -1, dtype=np.int64)
    run_way[grp[start]] = way_of[start]
    has = np.zeros(n_way, dtype=bool)
    has[run_way[long_run]] = True
    if (~has).any():
        key = "way with fewer than 2 known nodes"
        dropped[key] = dropped.get(key, 0) + int((~has).sum())
    return _Runs(pos, g, long_run, run_way)


def _feature_edges(
    node: NDArray[np.int64], f: NDArray[np.int64], oneway: NDArray[np.bool_], backwards: NDArray[np.bool_]
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """The directed edges ``(src, dst, feature)`` of the features' consecutive node pairs:
    both ways unless one-way; reversed ways run from their last node to their first."""
    k = np.arange(len(node))
    order_k = np.lexsort((np.where(backwards[f], -k, k), f))
    node, f = node[order_k], f[order_k]
    same = f[1:] == f[:-1]
    a, b, fe = node[:-1][same], node[1:][same], f[:-1][same]
    two = ~oneway[fe]
    src = np.stack([a, np.where(two, b, -1)], axis=1).ravel()
    dst = np.stack([b, a], axis=1).ravel()
    feat = np.repeat(fe, 2)
    use = src >= 0
    i8 = np.int64
    return src[use].astype(i8, copy=False), dst[use].astype(i8, copy=False), feat[use].astype(i8, copy=False)


def _flag(labels: Labels, values: frozenset[str] | set[str]) -> NDArray[np.bool_]:
    """Whether each row's value is one of ``values``."""
    hit = np.array([t in values for t in labels.table] + [False], dtype=bool)
    return hit[labels.codes]


def _per_value(labels: Labels, fn: Callable[[str | None], float]) -> NDArray[np.float64]:
    """``fn`` of each row's value, computed once per distinct value (None for none)."""
    vals = np.array([fn(t) for t in labels.table] + [fn(None)], dtype=np.float64)
    return vals[labels.codes]


def _empty_raw() -> RawNetwork:
    z = np.zeros(0, dtype=np.int64)
    return RawNetwork(
        crs="EPSG:4326",
        node_key=z,
        node_xy=np.zeros((0, 2)),
        node_lonlat=np.zeros((0, 2)),
        edge_src=z,
        edge_dst=z,
        edge_feat=z,
        edge_oneway=np.zeros(0, dtype=bool),
        feat_way_id=z,
        feat_name=Labels.of([]),
        feat_highway=Labels.of([]),
        feat_speed_kph=np.zeros(0),
    )


def _maxspeed(value: str | None) -> float:
    """km/h from an OSM maxspeed (``"50"``, ``"30 mph"``, ``"50;30"`` -> the lowest); NaN otherwise."""
    if not value:
        return float("nan")
    speeds = [parse_speed(v) for v in value.split(";")]
    speeds = [s for s in speeds if s == s]
    return min(speeds) if speeds else float("nan")


def _restrictions(relations: list[Relation], dropped: dict[str, int]) -> list[tuple[int, int, int, int]]:
    """``(from_way, via_node, to_way, kind)`` for simple no_*/only_* restrictions for cars."""
    out: list[tuple[int, int, int, int]] = []
    for tags, members in relations:
        value = tags.get("restriction") or tags.get("restriction:motorcar") or ""
        if value.startswith("no_"):
            kind = RESTRICTION_NO
        elif value.startswith("only_"):
            kind = RESTRICTION_ONLY
        else:
            dropped["restriction of another kind or for other vehicles"] = (
                dropped.get("restriction of another kind or for other vehicles", 0) + 1
            )
            continue
        if "motorcar" in tags.get("except", "").split(";"):
            continue
        frm = [ref for role, t, ref in members if role == "from" and t == "w"]
        via = [ref for role, t, ref in members if role == "via"]
        via_n = [ref for role, t, ref in members if role == "via" and t == "n"]
        to = [ref for role, t, ref in members if role == "to" and t == "w"]
        if len(frm) != 1 or len(to) != 1 or len(via) != 1 or len(via_n) != 1:
            dropped["restriction not from-way/via-node/to-way"] = (
                dropped.get("restriction not from-way/via-node/to-way", 0) + 1
            )
            continue
        out.append((frm[0], via_n[0], to[0], kind))
    return out


def download_graph(
    *,
    place: str | None,
    bbox: tuple[float, float, float, float] | None,
    network_type: str = "drive",
) -> tuple[nx.MultiDiGraph, str, dict[str, int]]:
    """Download an unsimplified network with osmnx (needs the network) as a raw graph."""
    import osmnx as ox

    try:
        if place is not None:
            Gd = ox.graph_from_place(place, network_type=network_type, simplify=False, retain_all=True)
        else:
            assert bbox is not None
            Gd = ox.graph_from_bbox(bbox, network_type=network_type, simplify=False, retain_all=True)
    except Exception as exc:  # osmnx raises many kinds (network, geocoding, empty response)
        raise InputError(f"download failed: {exc}") from exc
    ids = list(Gd.nodes)
    ll = np.array([[Gd.nodes[n]["x"], Gd.nodes[n]["y"]] for n in ids], dtype=np.float64).reshape(-1, 2)
    if not len(ll):
        raise InputError("the download has no drivable roads")
    crs = utm_crs(float(np.median(ll[:, 0])), float(np.median(ll[:, 1])))
    xy = to_xy(crs, ll[:, 0], ll[:, 1])
    import networkx as nx

    G = nx.MultiDiGraph(crs=crs)
    G.add_nodes_from(
        (n, {"x": p[0], "y": p[1], "lon": q[0], "lat": q[1], "osmid": int(n)})
        for n, p, q in zip(ids, xy.tolist(), ll.tolist(), strict=True)
    )
    for u, v, d in Gd.edges(data=True):
        ms = d.get("maxspeed")
        G.add_edge(
            u,
            v,
            osmid=d.get("osmid"),
            name=d.get("name"),
            highway=d.get("highway"),
            speed_kph=_maxspeed(ms if isinstance(ms, str) else None),
            oneway=bool(d.get("oneway")),
        )
    return G, crs, {}
