"""OpenStreetMap (PBF, XML, XML.bz2) -> raw MultiDiGraph, plus turn restrictions.

pyosmium reads every format in one pass (node locations kept in its C++ index, only
highway ways and restriction relations reach Python). Ways are filtered with osmnx's own
network filter (``"drive"`` by default), one-way rules follow osmnx, and references to nodes
missing from a clipped extract split the way there instead of failing.
"""

from __future__ import annotations

import itertools
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import networkx as nx
import numpy as np

from graph.errors import InputError
from graph.gis import _parse_speed
from graph.projection import to_xy, utm_crs
from graph.road_graph import RESTRICTION_NO, RESTRICTION_ONLY
from graph.simplify import RawNetwork, compact_raw

log = logging.getLogger(__name__)

# osmnx's one-way conventions (osmnx.graph._is_path_one_way / _is_path_reversed)
ONEWAY_VALUES = frozenset({"yes", "true", "1", "-1", "reverse", "T", "F"})
REVERSED_VALUES = frozenset({"-1", "reverse", "T"})

# copy of osmnx 2.0's "drive" filter, used only if osmnx's private helper moves
_DRIVE_FALLBACK = (
    '["highway"]["area"!~"yes"]["access"!~"private"]'
    '["highway"!~"abandoned|bridleway|bus_guideway|construction|corridor|'
    "cycleway|elevator|escalator|footway|no|path|pedestrian|planned|platform|"
    'proposed|raceway|razed|rest_area|service|services|steps|track"]'
    '["motor_vehicle"!~"no"]["motorcar"!~"no"]'
    '["service"!~"alley|driveway|emergency_access|parking|parking_aisle|private"]'
)
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

    def __call__(self, tags: dict[str, str]) -> bool:
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
    """osmnx's way filter for ``network_type`` (``"drive"``, ``"drive_service"``, ...)."""
    try:
        from osmnx import _overpass

        text = _overpass._get_network_filter(network_type)
    except (ImportError, AttributeError):
        if network_type != "drive":
            raise InputError(f"unsupported network type {network_type!r}") from None
        text = _DRIVE_FALLBACK
    except ValueError as exc:
        raise InputError(f"unsupported network type {network_type!r}") from exc
    if network_type.startswith("drive"):
        # osmnx lets non-standard highway=trail through; it is never a road for cars
        text += _NOT_FOR_CARS
    return TagFilter.from_overpass(text)


def is_oneway(tags: dict[str, str]) -> bool:
    """osmnx's rule: an explicit one-way value, or a roundabout."""
    return tags.get("oneway") in ONEWAY_VALUES or tags.get("junction") == "roundabout"


Way = tuple[int, dict[str, str], list[tuple[int, float, float, bool]]]
Relation = tuple[dict[str, str], list[tuple[str, str, int]]]


def scan_osm(path: Path, keep: TagFilter, dropped: dict[str, int]) -> tuple[list[Way], list[Relation]]:
    """One pyosmium pass: ways passing ``keep`` with node refs and locations, and restrictions.

    A node reference whose node is missing from the file has ``valid=False``.
    """
    import osmium

    ways: list[Way] = []
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
                tags = dict(obj.tags)
                if "highway" not in tags:
                    continue
                if not keep(tags):
                    _drop("way not drivable (osmnx network filter)")
                    continue
                refs = [
                    (n.ref, n.location.lon, n.location.lat, True)
                    if n.location.valid()
                    else (n.ref, 0.0, 0.0, False)
                    for n in obj.nodes
                ]
                ways.append((obj.id, tags, refs))
            elif isinstance(obj, osmium.osm.Relation):
                tags = dict(obj.tags)
                if tags.get("type") != "restriction":
                    continue
                relations.append((tags, [(m.role, m.type, m.ref) for m in obj.members]))
    except RuntimeError as exc:
        raise InputError(f"corrupt or unreadable OSM file {path.name}: {exc}") from exc
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
    from graph.simplify import raw_to_nx

    return raw_to_nx(raw), raw.crs, dropped, restrictions


def read_osm_raw(
    path: Path,
    *,
    network_type: str = "drive",
    bbox: tuple[float, float, float, float] | None = None,
) -> tuple[RawNetwork, dict[str, int], list[tuple[int, int, int, int]]]:
    """Read drivable ways of an OSM file into a raw network (arrays; see :func:`read_osm`)."""
    keep = network_filter(network_type)
    dropped: dict[str, int] = {}
    ways, relations = scan_osm(path, keep, dropped)
    raw = _ways_to_raw(ways, bbox=bbox, dropped=dropped)
    restrictions = _restrictions(relations, dropped)
    return raw, dropped, restrictions


def _ways_to_raw(
    ways: list[Way],
    *,
    bbox: tuple[float, float, float, float] | None,
    dropped: dict[str, int],
) -> RawNetwork:
    coords: dict[int, tuple[float, float]] = {}
    pieces: list[tuple[int, dict[str, str], list[int]]] = []
    n_dangling = 0
    n_outside = 0
    for wid, tags, refs in ways:
        run: list[int] = []
        runs: list[list[int]] = []
        for ref, lon, lat, ok in refs:
            if ok and bbox is not None and not (bbox[0] <= lon <= bbox[2] and bbox[1] <= lat <= bbox[3]):
                ok = False
                n_outside += 1
            elif not ok:
                n_dangling += 1
            if ok:
                coords[ref] = (lon, lat)
                if not run or run[-1] != ref:
                    run.append(ref)
            else:
                if len(run) >= 2:
                    runs.append(run)
                run = []
        if len(run) >= 2:
            runs.append(run)
        if not runs:
            dropped["way with fewer than 2 known nodes"] = (
                dropped.get("way with fewer than 2 known nodes", 0) + 1
            )
        pieces.extend((wid, tags, r) for r in runs)
    if n_dangling:
        dropped["dangling node references (missing from the extract)"] = n_dangling
    if n_outside:
        dropped["node references outside the bbox"] = n_outside
    ids = np.fromiter(coords.keys(), dtype=np.int64, count=len(coords))
    ll = np.array(list(coords.values()), dtype=np.float64).reshape(-1, 2)
    if len(ids) == 0:
        return _empty_raw()
    crs = utm_crs(float(np.median(ll[:, 0])), float(np.median(ll[:, 1])))
    xy = to_xy(crs, ll[:, 0], ll[:, 1])
    index = {int(i): k for k, i in enumerate(ids.tolist())}
    src: list[int] = []
    dst: list[int] = []
    feat: list[int] = []
    oneways: list[bool] = []
    way_ids: list[int] = []
    names: list[str | None] = []
    hws: list[str | None] = []
    speeds: list[float] = []
    for fi, (wid, tags, run) in enumerate(pieces):
        oneway = is_oneway(tags)
        nodes = [index[r] for r in (run[::-1] if tags.get("oneway") in REVERSED_VALUES else run)]
        way_ids.append(wid)
        names.append(tags.get("name"))
        hws.append(tags.get("highway"))
        speeds.append(_maxspeed(tags.get("maxspeed")))
        for a, b in itertools.pairwise(nodes):
            src.append(a)
            dst.append(b)
            feat.append(fi)
            oneways.append(oneway)
            if not oneway:
                src.append(b)
                dst.append(a)
                feat.append(fi)
                oneways.append(oneway)
    raw = RawNetwork(
        crs=crs,
        node_key=ids,
        node_xy=xy,
        node_lonlat=ll,
        edge_src=np.asarray(src, dtype=np.int64),
        edge_dst=np.asarray(dst, dtype=np.int64),
        edge_feat=np.asarray(feat, dtype=np.int64),
        edge_oneway=np.asarray(oneways, dtype=bool),
        feat_way_id=np.asarray(way_ids, dtype=np.int64),
        feat_name=names,
        feat_highway=hws,
        feat_speed_kph=np.asarray(speeds, dtype=np.float64),
    )
    return compact_raw(raw)


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
        feat_name=[],
        feat_highway=[],
        feat_speed_kph=np.zeros(0),
    )


def _maxspeed(value: str | None) -> float:
    """km/h from an OSM maxspeed (``"50"``, ``"30 mph"``, ``"50;30"`` -> the lowest); NaN otherwise."""
    if not value:
        return float("nan")
    speeds = [_parse_speed(v) for v in value.split(";")]
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
