"""GIS road lines, read as arrays, -> raw network (every vertex a node).

The attribute columns are decoded once per distinct value (one-way codes, names, classes,
speeds); line ends become nodes from the node id fields or from shared endpoints (snapped
within a tolerance); crossings are noded when asked; each segment becomes one arc per
direction it may be driven. Reading the files is :mod:`graph.gis`.
"""

from __future__ import annotations

import logging
import math
import re
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import shapely
from numpy.typing import NDArray

from graph.components import union_find
from graph.errors import InputError
from graph.keys import dense_labels, unique, unique_inverse
from graph.projection import utm_crs
from graph.raw_network import RawNetwork, compact_raw
from graph.road_graph import Labels
from graph.simplify import _text

if TYPE_CHECKING:
    from graph.gis import GisOptions, Lines

log = logging.getLogger(__name__)

FORWARD = 1
BOTH = 0
REVERSE = -1


def parse_speed(value: Any) -> float:
    """Speed in km/h from a number or text such as ``"50"``, ``"30 mph"``; NaN when unknown."""
    if value is None:
        return math.nan
    if isinstance(value, int | float | np.integer | np.floating):
        return float(value) if float(value) > 0 else math.nan
    m = re.match(r"\s*([\d.]+)\s*(mph|knots|km/h|kmh|kph)?", str(value).lower())
    if not m:
        return math.nan
    try:
        v = float(m.group(1))
    except ValueError:
        return math.nan
    unit = m.group(2)
    if unit == "mph":
        v *= 1.609344
    elif unit == "knots":
        v *= 1.852
    return v if v > 0 else math.nan


class FieldChoice(NamedTuple):
    """The attribute fields of GIS lines that the build reads (None: none)."""

    oneway: str | None
    name: str | None
    speed: str | None
    highway: str | None
    id: str | None
    node_ids: tuple[str, str] | None


class _Features(NamedTuple):
    """Per feature (a line, or a piece of one after noding): id, one-way direction
    (``FORWARD``, ``REVERSE`` or ``BOTH``), name, class and speed in km/h (NaN unknown)."""

    way_id: NDArray[np.int64]
    direction: NDArray[np.int8]
    name: Labels
    highway: Labels
    speed_kph: NDArray[np.float64]

    def take(self, index: NDArray[np.int64]) -> _Features:
        return _Features(
            self.way_id[index],
            self.direction[index],
            self.name.take(index),
            self.highway.take(index),
            self.speed_kph[index],
        )


class _EndNodes(NamedTuple):
    """The nodes at the features' ends: node of each end (first ends, then last ends), the
    nodes' positions in metres and lon/lat, and their source ids (None: generated)."""

    node_of_end: NDArray[np.int64]
    xy: NDArray[np.float64]
    lonlat: NDArray[np.float64]
    ids: NDArray[np.int64] | None


def lines_to_network(
    lines: Lines, dropped: dict[str, int], info: dict[str, Any], fields: FieldChoice, opts: GisOptions
) -> tuple[RawNetwork, dict[str, int], dict[str, Any]]:
    """The raw network of lines read by :func:`graph.gis.lines_to_raw` with the attribute
    ``fields`` chosen there; ``dropped`` and ``info`` are added to and returned."""
    from graph.projection import to_xy

    feats = _features(lines, fields, opts, dropped, info)
    lo, hi = np.nanmin(lines.lonlat, axis=0), np.nanmax(lines.lonlat, axis=0)
    crs = utm_crs(float((lo[0] + hi[0]) / 2), float((lo[1] + hi[1]) / 2))
    src_ids = None
    if fields.node_ids is not None and not opts.node_crossings and len(unique(lines.row)) == lines.n_lines:
        src_ids = _endpoint_id_values(lines, fields.node_ids)
    if opts.node_crossings:
        owner0 = np.repeat(np.arange(lines.n_lines), np.diff(lines.ptr))
        geoms, src = _node_lines(shapely.linestrings(lines.lonlat, indices=owner0))
        feats = feats.take(src)
        ll, owner = shapely.get_coordinates(geoms, return_index=True)
        del geoms
    else:
        ll = lines.lonlat
        owner = np.repeat(np.arange(lines.n_lines), np.diff(lines.ptr))
    del lines
    n_feat = len(feats.way_id)
    xy = to_xy(crs, ll[:, 0], ll[:, 1])
    start = np.zeros(n_feat + 1, dtype=np.int64)
    np.cumsum(np.bincount(owner, minlength=n_feat), out=start[1:])
    ends = np.concatenate([start[:-1], start[1:] - 1])  # every feature's first, then last vertex
    end = _end_nodes(xy[ends], ll[ends], src_ids, opts, info)
    n_end_nodes = len(end.xy)
    # every vertex is a node: endpoints shared, interior vertices private to their feature
    vnode = np.empty(len(xy), dtype=np.int64)
    interior = np.ones(len(xy), dtype=bool)
    interior[ends] = False
    vnode[ends] = end.node_of_end
    vnode[interior] = n_end_nodes + np.arange(int(interior.sum()))
    all_xy = np.vstack([end.xy, xy[interior]])
    all_ll = np.vstack([end.lonlat, ll[interior]])
    del ll
    # node keys are the source ids: u/v fields when they name the endpoints consistently,
    # else 0..N-1; interior vertices get negative keys
    info["node_ids"] = "u/v fields" if end.ids is not None else "generated"
    keys = np.concatenate(
        [
            end.ids if end.ids is not None else np.arange(n_end_nodes, dtype=np.int64),
            -1 - np.arange(int(interior.sum()), dtype=np.int64),
        ]
    )
    del end, interior
    raw, seg_len, seg_feat = _arcs(crs, (keys, all_xy, all_ll), xy, vnode, owner, feats)
    # features that collapsed to one point
    flen = np.bincount(seg_feat, weights=seg_len, minlength=n_feat)
    collapsed = int((flen <= opts.snap_tolerance).sum())
    if collapsed:
        dropped["zero length after snapping"] = collapsed
    return compact_raw(raw), dropped, info


def _features(
    lines: Lines, fields: FieldChoice, opts: GisOptions, dropped: dict[str, int], info: dict[str, Any]
) -> _Features:
    """Each line's id (its row number without an integer id field), direction, name, class and speed."""
    n_feat = lines.n_lines
    fid = _int_column(lines, fields.id) if fields.id is not None else None
    if fid is None and opts.id_field is not None:
        raise InputError(f"the id field {opts.id_field!r} does not hold integers on every line")
    info["id_field"] = fields.id if fid is not None else None  # None: ids are row numbers
    if fid is None:
        fid = np.arange(n_feat, dtype=np.int64)
    if fields.oneway is not None:
        inv, uniq = _factorize(lines.column(fields.oneway))
        ucodes = [opts.oneway_convention.code(v) for v in uniq]
        bad = sum(int((inv == i).sum()) for i, c in enumerate(ucodes) if c is None)
        if bad:
            dropped["unrecognised one-way value (read as two-way)"] = bad
        direction = np.array([BOTH if c is None else c for c in ucodes], dtype=np.int8)[inv]
    else:
        direction = np.full(n_feat, FORWARD if opts.directed else BOTH, dtype=np.int8)
    if fields.speed:
        inv, uniq = _factorize(lines.column(fields.speed))
        speeds = np.array([parse_speed(v) for v in uniq], dtype=np.float64)[inv]
    else:
        speeds = np.full(n_feat, math.nan)
    return _Features(fid, direction, _labels(lines, fields.name), _labels(lines, fields.highway), speeds)


def _end_nodes(
    end_xy: NDArray[np.float64],
    end_ll: NDArray[np.float64],
    src_ids: NDArray[np.int64] | None,
    opts: GisOptions,
    info: dict[str, Any],
) -> _EndNodes:
    """The nodes at the line ends: from the node id fields (``src_ids``) when the topology
    allows, else from shared endpoints within the snap tolerance; each at the mean of its ends."""
    place_of_end, places = _places(end_xy)
    node_of_end, end_ids = None, None
    if opts.topology == "ids" or (opts.topology == "auto" and src_ids is not None):
        node_of_end, end_ids = _nodes_from_ids(src_ids, end_xy, opts)
    if node_of_end is None:
        node_of_end = _nodes_from_coords(places, place_of_end, opts.snap_tolerance)
        end_ids = _consistent_ids(src_ids, node_of_end)
        info["topology"] = "shared endpoints"
    else:
        info["topology"] = "node id fields"
    n = int(node_of_end.max()) + 1 if len(node_of_end) else 0
    node_xy = np.zeros((n, 2))
    np.add.at(node_xy, node_of_end, end_xy)
    node_xy /= np.bincount(node_of_end, minlength=n)[:, None]
    info["merged_endpoints"] = len(places) - n
    return _EndNodes(node_of_end, node_xy, end_ll[unique_inverse(node_of_end)[1]], end_ids)


def _arcs(
    crs: str,
    nodes: tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]],
    xy: NDArray[np.float64],
    vnode: NDArray[np.int64],
    owner: NDArray[np.int64],
    feats: _Features,
) -> tuple[RawNetwork, NDArray[np.float64], NDArray[np.int64]]:
    """The raw network of one arc per segment and direction it may be driven (``nodes``: keys,
    positions and lon/lat; vertex ``i`` at ``xy[i]`` is node ``vnode[i]`` of feature
    ``owner[i]``), and each segment's length and feature (zero-length ones included)."""
    seg_a = np.arange(len(xy) - 1)
    seg_a = seg_a[owner[seg_a] == owner[seg_a + 1]]
    a_n, b_n = vnode[seg_a], vnode[seg_a + 1]
    f = owner[seg_a]
    d = xy[seg_a + 1] - xy[seg_a]
    seg_len = np.hypot(d[:, 0], d[:, 1])
    del d
    ok = a_n != b_n
    a_n, b_n, fo = a_n[ok], b_n[ok], f[ok]
    dirn = feats.direction[fo]
    fwd = (dirn == BOTH) | (dirn == FORWARD)
    bwd = (dirn == BOTH) | (dirn == REVERSE)
    # per segment: forward then backward, as the segments come
    src = np.stack([np.where(fwd, a_n, -1), np.where(bwd, b_n, -1)], axis=1).ravel()
    dst = np.stack([b_n, a_n], axis=1).ravel()
    feat = np.repeat(fo, 2)
    use = src >= 0
    keys, node_xy, node_ll = nodes
    raw = RawNetwork(
        crs=crs,
        node_key=keys,
        node_xy=node_xy,
        node_lonlat=node_ll,
        edge_src=src[use].astype(np.int64, copy=False),
        edge_dst=dst[use].astype(np.int64, copy=False),
        edge_feat=feat[use].astype(np.int64, copy=False),
        edge_oneway=(feats.direction[feat[use]] != BOTH),
        feat_way_id=feats.way_id.astype(np.int64, copy=False),
        feat_name=feats.name,
        feat_highway=feats.highway,
        feat_speed_kph=feats.speed_kph.astype(np.float64),
    )
    return raw, seg_len, f


def _factorize(column: Any) -> tuple[NDArray[np.int64], list[Any]]:
    """Codes into the distinct values of a pyarrow column (missing values, NaN included, one value)."""
    import pyarrow.compute as pc

    enc = pc.dictionary_encode(column, null_encoding="encode")
    codes = np.asarray(enc.indices.to_numpy(zero_copy_only=False), dtype=np.int64)
    vals = [None if isinstance(v, float) and v != v else v for v in enc.dictionary.to_pylist()]
    # NaN and null read alike: give them one code
    first: dict[Any, int] = {}
    remap = np.array(
        [
            first.setdefault(("<missing>",) if v is None else (type(v) is bool, v), i)
            for i, v in enumerate(vals)
        ],
        dtype=np.int64,
    )
    if len(remap) and (remap != np.arange(len(remap))).any():
        codes = remap[codes]
    return codes, vals


def _labels(lines: Lines, name: str | None) -> Labels:
    """A text column per line as :class:`Labels` (each distinct value read as text once)."""
    if name is None:
        return Labels(np.full(lines.n_lines, -1, dtype=np.int32), [])
    import pyarrow.compute as pc

    enc = pc.dictionary_encode(lines.columns[name])
    table: dict[str, int] = {}
    texts = [_text(v) for v in enc.dictionary.to_pylist()]
    code_of = np.array(
        [-1 if t is None else table.setdefault(t, len(table)) for t in texts] + [-1], dtype=np.int32
    )
    idx = np.asarray(enc.indices.fill_null(-1).to_numpy(zero_copy_only=False), dtype=np.int64)
    return Labels(code_of[idx][lines.row], list(table))


def _int_column(lines: Lines, name: str) -> NDArray[np.int64] | None:
    """An integer column per line as int64: integers, whole floats or integer text (a DBF's
    character field); None when it has nulls or other values."""
    import pyarrow as pa

    col = lines.columns[name]
    if col.null_count:
        return None
    if pa.types.is_integer(col.type):
        return np.asarray(col.to_numpy(), dtype=np.int64)[lines.row]
    try:
        if pa.types.is_floating(col.type):
            f = np.asarray(col.to_numpy(), dtype=np.float64)
            if not (np.isfinite(f).all() and (f == np.round(f)).all()):
                return None
            vals = f.astype(np.int64)
        elif pa.types.is_string(col.type) or pa.types.is_large_string(col.type):
            vals = np.asarray([int(v) for v in col.to_pylist()], dtype=np.int64)
        else:
            return None
    except (TypeError, ValueError, OverflowError):
        return None
    return vals[lines.row]


def _endpoint_id_values(lines: Lines, fields: tuple[str, str]) -> NDArray[np.int64] | None:
    """Ids of every line's first then last node from the u/v fields, or None when unusable
    (not integers, nulls, or negative)."""
    import pyarrow as pa

    out = []
    for f in fields:
        col = lines.columns[f]
        if col.null_count:
            return None
        if pa.types.is_integer(col.type) or pa.types.is_floating(col.type):
            vals = np.asarray(col.to_numpy(), dtype=np.int64)
        else:
            try:
                vals = np.asarray(col.to_pylist(), dtype=np.int64)
            except (TypeError, ValueError, OverflowError):
                return None
        out.append(vals[lines.row])
    ids = np.concatenate(out)
    return ids if (ids >= 0).all() else None


def _nodes_from_ids(
    ids: NDArray[np.int64] | None, end_xy: NDArray[np.float64], opts: GisOptions
) -> tuple[NDArray[np.int64] | None, NDArray[np.int64] | None]:
    """Endpoint -> node from the id fields, if every id sits at one place (within 1 m or the
    snap tolerance). Returns ``(None, None)`` for ``topology="auto"`` when that fails."""
    if ids is None:
        if opts.topology == "ids":
            raise InputError("topology from node ids needs integer u/v fields (see --node-id-fields)")
        return None, None
    uniq, _, inv = unique_inverse(ids)
    n = len(uniq)
    mean = np.zeros((n, 2))
    np.add.at(mean, inv, end_xy)
    mean /= np.bincount(inv, minlength=n)[:, None]
    spread = float(np.hypot(*(end_xy - mean[inv]).T).max()) if len(inv) else 0.0
    if spread > max(1.0, opts.snap_tolerance):
        if opts.topology == "ids":
            raise InputError(f"node id fields name line ends up to {spread:.1f} m apart: not node ids")
        log.warning("u/v fields name line ends up to %.1f m apart; using shared endpoints instead", spread)
        return None, None
    return inv.astype(np.int64), uniq.astype(np.int64)


def _places(end_xy: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Distinct endpoint positions (rounded to the micrometre, sorted by x then y) and the
    place of each endpoint."""
    r = np.round(end_xy, 6)
    order = np.lexsort((r[:, 1], r[:, 0]))  # as np.unique(axis=0) orders them, much faster
    rs = r[order]
    new = np.ones(len(rs), dtype=bool)
    new[1:] = (rs[1:] != rs[:-1]).any(axis=1)
    inv = np.empty(len(r), dtype=np.int64)
    inv[order] = np.cumsum(new) - 1
    return inv, rs[new]


def _nodes_from_coords(uniq: NDArray[np.float64], inv: NDArray[np.int64], tol: float) -> NDArray[np.int64]:
    """Endpoint -> node: identical positions (``uniq[inv]``) first, then snapping within
    ``tol`` metres."""
    if tol > 0 and len(uniq) > 1:
        pa, pb = _pairs_within(uniq, tol)
        lab = union_find(len(uniq), pa, pb)
        _, lab = dense_labels(lab, len(uniq))
    else:
        lab = np.arange(len(uniq))
    return np.asarray(lab, dtype=np.int64).ravel()[inv]


def _pairs_within(xy: NDArray[np.float64], tol: float) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """All pairs ``a < b`` of points at most ``tol`` apart: points hashed to cells of side
    ``tol``, each cell compared with itself and the neighbours ahead of it (an STRtree when
    the cells would not fit 64-bit keys)."""
    lo = xy.min(axis=0)
    cell = np.floor((xy - lo) / tol).astype(np.int64)
    width = int(cell[:, 1].max()) + 3
    if (int(cell[:, 0].max()) + 3) * width >= 2**62:
        tree = shapely.STRtree(shapely.points(xy))
        pa, pb = tree.query(shapely.points(xy), predicate="dwithin", distance=tol)
        keep = pa < pb
        return pa[keep].astype(np.int64), pb[keep].astype(np.int64)
    key = cell[:, 0] * width + cell[:, 1] + 1
    del cell
    order = np.argsort(key, kind="stable")
    skey = key[order]
    out_a, out_b = [], []
    for dx, dy in ((0, 0), (0, 1), (1, -1), (1, 0), (1, 1)):
        want = key + dx * width + dy
        first = np.searchsorted(skey, want, side="left")
        n = np.searchsorted(skey, want, side="right") - first
        a = np.repeat(np.arange(len(xy), dtype=np.int64), n)
        b = order[np.repeat(first, n) + np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)]
        near = np.hypot(xy[a, 0] - xy[b, 0], xy[a, 1] - xy[b, 1]) <= tol
        a, b = a[near], b[near]
        out_a.append(np.minimum(a, b)[a != b])
        out_b.append(np.maximum(a, b)[a != b])
    pa, pb = np.concatenate(out_a), np.concatenate(out_b)
    pair = unique(pa * len(xy) + pb)
    return pair // len(xy), pair % len(xy)


def _consistent_ids(
    ids: NDArray[np.int64] | None, node_of_end: NDArray[np.int64]
) -> NDArray[np.int64] | None:
    """One id per node when the u/v fields agree with the coordinate topology, else None."""
    if ids is None or not len(node_of_end):
        return None
    n = int(node_of_end.max()) + 1
    out = np.full(n, -1, dtype=np.int64)
    out[node_of_end] = ids
    if (out < 0).any() or not np.array_equal(out[node_of_end], ids) or len(unique(out)) != n:
        log.info("u/v fields do not match the shared endpoints; generating node ids")
        return None
    return out


def _node_lines(lines: NDArray[Any]) -> tuple[NDArray[Any], NDArray[np.int64]]:
    """Split lines at every crossing; each piece keeps the index of the line it came from."""
    pieces = shapely.get_parts(shapely.node(shapely.multilinestrings(lines)))
    tree = shapely.STRtree(lines)
    mid = shapely.line_interpolate_point(pieces, 0.5, normalized=True)
    pi, li = tree.query(mid, predicate="dwithin", distance=1e-9)
    src = np.full(len(pieces), -1, dtype=np.int64)
    src[pi[::-1]] = li[::-1]  # first match wins
    ok = src >= 0
    pieces, src = pieces[ok], src[ok]
    # orient each piece like its source line
    proj_a = shapely.line_locate_point(lines[src], shapely.get_point(pieces, 0))
    proj_b = shapely.line_locate_point(lines[src], shapely.get_point(pieces, -1))
    flip = proj_b < proj_a
    pieces[flip] = shapely.reverse(pieces[flip])
    return pieces, src
