"""Pictures of a match: a PNG map (matplotlib) and an interactive HTML map (Leaflet, inlined).

Both show the road graph, the true route, the raw GPS and fused fixes (fixes in GPS outages,
i.e. dead reckoning, in red), the snapped positions (on the wrong edge in red), the fixes the
matcher reported as ambiguous (inside an ambiguous region), the decisions it committed on
leaving one, and the fixes that carried a correction.
"""

from __future__ import annotations

import html
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from graph.files import atomic_path
from graph.projection import to_lonlat, to_xy
from graph.road_graph import RoadGraph
from mapmatch.evaluate import align_by_time, matched_edges_dense


@dataclass(frozen=True)
class PlotData:
    """Everything a picture shows, in the map's metres (NaN where absent)."""

    route_xy: NDArray[np.float64]
    fix_xy: NDArray[np.float64]
    fix_valid: NDArray[np.bool_]
    gps_xy: NDArray[np.float64]
    snap_xy: NDArray[np.float64]
    snap_ok: NDArray[np.bool_]
    ambiguous: NDArray[np.bool_]
    decided: NDArray[np.bool_]
    corrected: NDArray[np.bool_]
    outages: list[tuple[int, int]]
    info: pd.DataFrame | None = None
    """Per fix (aligned with ``fix_xy``): time, state, edge, way_id, probability, correction."""


def _xy(graph: RoadGraph, df: pd.DataFrame | None) -> NDArray[np.float64]:
    if df is None or len(df) == 0 or "lat" not in df.columns:
        return np.empty((0, 2))
    lat = pd.to_numeric(df["lat"], errors="coerce").to_numpy(float)
    lon = pd.to_numeric(df["lon"], errors="coerce").to_numpy(float)
    out = np.full((len(df), 2), np.nan)
    ok = ~np.isnan(lat) & ~np.isnan(lon)
    if ok.any():
        out[ok] = to_xy(graph.crs, lon[ok], lat[ok])
    return out


def _runs(mask: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """(first, last) indices of each run of True."""
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    return list(zip(np.flatnonzero(d == 1).tolist(), (np.flatnonzero(d == -1) - 1).tolist(), strict=True))


def plot_data(
    graph: RoadGraph,
    *,
    route_xy: ArrayLike,
    fixes: pd.DataFrame,
    matched: pd.DataFrame | None = None,
    truth: pd.DataFrame | None = None,
    gps: pd.DataFrame | None = None,
) -> PlotData:
    """Gather the layers of a picture from the drive's frames (matched rows align with fixes by time)."""
    fxy = _xy(graph, fixes)
    valid = (
        fixes["gps_valid"].fillna(1).astype(int).to_numpy() > 0
        if "gps_valid" in fixes.columns
        else np.ones(len(fixes), dtype=bool)
    )
    n = len(fixes)
    snap = np.full((n, 2), np.nan)
    ok = np.ones(n, dtype=bool)
    amb = np.zeros(n, dtype=bool)
    dec = np.zeros(n, dtype=bool)
    cor = np.zeros(n, dtype=bool)
    if matched is not None and len(matched):
        idx = align_by_time(fixes["time"].to_numpy(float), matched["time"].to_numpy(float))
        have = idx >= 0
        mxy = _xy(graph, matched)
        snap[idx[have]] = mxy[have]
        if "state" in matched.columns:
            st = matched["state"].astype(str).str.lower().to_numpy()
            a = np.zeros(n, dtype=bool)
            a[idx[have]] = st[have] == "ambiguous"
            amb = a
            prev = np.concatenate([[False], a[:-1]])
            dec = prev & ~a & ~np.isnan(snap[:, 0])
        if "correction" in matched.columns:
            c = matched["correction"]
            flag = (c.notna() & (c.astype(str).str.strip() != "") & (c.astype(str) != "0")).to_numpy()
            cor[idx[have]] = flag[have]
        if truth is not None and "edge" in truth.columns:
            ti = align_by_time(truth["time"].to_numpy(float), fixes["time"].to_numpy(float))
            medge = np.full(n, -1, dtype=np.int64)
            medge[idx[have]] = matched_edges_dense(graph, matched)[have]
            tedge = np.where(ti >= 0, truth["edge"].to_numpy(np.int64)[np.maximum(ti, 0)], -2)
            ok = (medge == tedge) | (medge < 0)
    info = _fix_info(fixes, matched)
    gxy = _xy(graph, gps)
    # outages: the simulator's truth knows them; otherwise runs of >= 5 fixes without GPS
    if truth is not None and "gps_outage" in truth.columns:
        ti = align_by_time(truth["time"].to_numpy(float), fixes["time"].to_numpy(float))
        flag = truth["gps_outage"].to_numpy(bool)[np.maximum(ti, 0)] & (ti >= 0)
        runs = _runs(flag)
    else:
        runs = [(a, b) for a, b in _runs(~valid) if b - a >= 4]
    return PlotData(
        route_xy=np.asarray(route_xy, dtype=np.float64).reshape(-1, 2),
        fix_xy=fxy,
        fix_valid=valid,
        gps_xy=gxy,
        snap_xy=snap,
        snap_ok=ok,
        ambiguous=amb,
        decided=dec,
        corrected=cor,
        outages=runs,
        info=info,
    )


def _reported_probability(candidates: Any, edge: Any) -> float:
    """The probability the matcher gave the edge it reported ("edge:p;edge:p" cells)."""
    if not isinstance(candidates, str) or not candidates:
        return float("nan")
    for item in candidates.split(";"):
        e, _, p = item.partition(":")
        if e.strip() == str(edge):
            try:
                return float(p)
            except ValueError:
                return float("nan")
    return float("nan")


def _fix_info(fixes: pd.DataFrame, matched: pd.DataFrame | None) -> pd.DataFrame:
    """The tooltip fields per fix: time, state, edge, way, reported probability, correction."""
    n = len(fixes)
    time = pd.to_numeric(fixes["time"], errors="coerce").to_numpy(float)
    state = [""] * n
    edge = np.full(n, -1, dtype=np.int64)
    way = [""] * n
    prob = np.full(n, np.nan)
    corr = [""] * n
    if matched is not None and len(matched):
        idx = align_by_time(time, matched["time"].to_numpy(float))

        def cells(name: str) -> list[Any]:
            return matched[name].tolist() if name in matched.columns else [None] * len(matched)

        m_state, m_way, m_cand, m_corr = (cells(c) for c in ("state", "way_id", "candidates", "correction"))
        m_edge = pd.to_numeric(pd.Series(cells("edge")), errors="coerce").fillna(-1).to_numpy(np.int64)
        for i in np.flatnonzero(idx >= 0).tolist():
            j = int(idx[i])
            state[i] = "" if m_state[j] is None else str(m_state[j])
            edge[i] = m_edge[j]
            w = pd.to_numeric(m_way[j], errors="coerce")
            way[i] = "" if pd.isna(w) else str(int(w))
            prob[i] = _reported_probability(m_cand[j], m_edge[j])
            c = m_corr[j]
            corr[i] = f"edges {c}" if isinstance(c, str) and c.strip() else ""
    return pd.DataFrame(
        {"time": time, "state": state, "edge": edge, "way_id": way, "probability": prob, "correction": corr}
    )


def _layers(
    ax: Any, graph: RoadGraph, data: PlotData, lo: NDArray[np.float64], hi: NDArray[np.float64]
) -> None:
    """Draw every layer on ``ax`` inside the box ``lo``..``hi``."""
    from matplotlib.collections import LineCollection

    ptr = graph.edge_seg_ptr
    keep = (graph.edge_reverse < 0) | (np.arange(graph.n_edges) < graph.edge_reverse)
    segs = [graph.seg_xy[ptr[e] : ptr[e + 1]] for e in np.flatnonzero(keep)]
    segs = [s for s in segs if (s.max(0) >= lo).all() and (s.min(0) <= hi).all()]
    ax.add_collection(LineCollection(segs, colors="#b0b0b0", linewidths=0.8, zorder=1, label="road graph"))
    ax.plot(
        *data.route_xy.T,
        color="#2ca02c",
        lw=6,
        alpha=0.45,
        zorder=2,
        solid_capstyle="round",
        label="true route",
    )
    if len(data.gps_xy):
        ax.plot(*data.gps_xy.T, "+", color="#555555", ms=3, alpha=0.5, zorder=3, label="raw GPS")
    v = data.fix_valid
    if len(data.fix_xy):
        ax.plot(*data.fix_xy[v].T, ".", color="#1f77b4", ms=3, zorder=4, label="fused fix (GPS valid)")
    s = data.snap_xy
    has = ~np.isnan(s[:, 0])
    if has.any():
        ax.plot(*s[has & data.snap_ok].T, "o", color="#ff7f0e", ms=2.5, zorder=5, label="snapped")
        amb = has & data.ambiguous
        if amb.any():
            ax.plot(
                *s[amb].T, "o", mfc="none", mec="#9467bd", ms=7, mew=1.0, zorder=6, label="ambiguous region"
            )
        dec = has & data.decided
        if dec.any():
            ax.plot(*s[dec].T, "D", color="#9467bd", ms=6, zorder=7, label="decision on leaving region")
    # dead reckoning on top, so outages stay visible under the snapped points
    if len(data.fix_xy) and (~v).any():
        ax.plot(*data.fix_xy[~v].T, ".", color="#d62728", ms=5, zorder=8, label="fused fix, no GPS (DR)")
    for a, b in data.outages:
        ax.plot(*data.fix_xy[a : b + 1].T, "-", color="#d62728", lw=4, alpha=0.35, zorder=8)
    if has.any():
        bad = has & ~data.snap_ok
        if bad.any():
            ax.plot(*s[bad].T, "x", color="#d62728", ms=6, mew=1.5, zorder=9, label="snapped on wrong edge")
        cor = has & data.corrected
        if cor.any():
            ax.plot(*s[cor].T, "*", color="#e377c2", mec="k", mew=0.5, ms=13, zorder=10, label="correction")
    if len(data.route_xy):
        ax.plot(*data.route_xy[0], "s", color="#2ca02c", ms=9, mec="k", zorder=11, label="start")
        ax.plot(*data.route_xy[-1], "^", color="#2ca02c", ms=10, mec="k", zorder=11, label="end")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")


def draw_png(
    graph: RoadGraph,
    data: PlotData,
    path: str | os.PathLike[str],
    *,
    title: str = "",
    margin_m: float = 120.0,
    size_in: float = 12.0,
) -> None:
    """Draw the PNG map (atomic write): the whole drive, and a zoom on the longest GPS outage."""
    from mapmatch.extras import require

    matplotlib = require("matplotlib", extra="plots", needed_for="drawing the PNG map")

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = [data.route_xy, data.fix_xy[~np.isnan(data.fix_xy[:, 0])]] if len(data.fix_xy) else [data.route_xy]
    allp = np.vstack([p for p in pts if len(p)])
    lo, hi = allp.min(axis=0) - margin_m, allp.max(axis=0) + margin_m
    span = hi - lo
    zoom = max(data.outages, key=lambda r: r[1] - r[0]) if data.outages else None
    width = size_in * (1.5 if zoom else 1.0)
    height = max(5.0, min(size_in * span[1] / max(span[0], 1.0), 2 * size_in)) + 1.2
    if zoom:
        fig, (ax, axz) = plt.subplots(
            1, 2, figsize=(width, height), dpi=110, gridspec_kw={"width_ratios": [2, 1]}
        )
    else:
        fig, ax = plt.subplots(figsize=(width, height), dpi=110)
    _layers(ax, graph, data, lo, hi)
    ax.set_xlabel(f"easting, m ({graph.crs})")
    ax.set_ylabel("northing, m")
    ax.ticklabel_format(useOffset=False, style="plain")
    for k, (a, b) in enumerate(data.outages, start=1):
        if len(data.fix_xy) and not np.isnan(data.fix_xy[a, 0]):
            ax.annotate(
                f"GPS outage {k} ({b - a + 1} fixes)",
                data.fix_xy[a],
                xytext=(14, 14),
                textcoords="offset points",
                fontsize=8,
                color="#d62728",
                arrowprops={"arrowstyle": "-", "color": "#d62728", "lw": 0.8},
                zorder=12,
            )
    if zoom:
        a, b = zoom
        seg = data.fix_xy[a : b + 1]
        seg = seg[~np.isnan(seg[:, 0])]
        c = 0.5 * (seg.min(axis=0) + seg.max(axis=0))
        half = max(60.0, 0.6 * float((seg.max(axis=0) - seg.min(axis=0)).max()))
        zlo, zhi = c - half, c + half
        _layers(axz, graph, data, zlo, zhi)
        axz.set_title(f"zoom: longest GPS outage ({b - a + 1} fixes)", fontsize=9)
        axz.tick_params(labelsize=7)
        axz.ticklabel_format(useOffset=False, style="plain")
        ax.add_patch(
            matplotlib.patches.Rectangle(
                tuple(zlo), *(zhi - zlo), fill=False, ec="#d62728", lw=1.0, ls="--", zorder=12
            )
        )
    if title:
        fig.suptitle(title, fontsize=9, x=0.01, ha="left", family="monospace")
    handles, labels = ax.get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=5, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 0.96))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


LEGEND = (
    ("true route", "#2ca02c", "line"),
    ("road graph", "#888888", "line"),
    ("raw GPS", "#555555", "dot"),
    ("fused fix, GPS valid", "#1f77b4", "dot"),
    ("fused fix, no GPS (dead reckoning)", "#d62728", "dot"),
    ("snapped", "#ff7f0e", "dot"),
    ("snapped on the wrong edge", "#d62728", "ring"),
    ("ambiguous region", "#9467bd", "ring"),
    ("decision on leaving a region", "#9467bd", "dot"),
    ("correction", "#e377c2", "dot"),
)


def draw_html(
    graph: RoadGraph,
    data: PlotData,
    path: str | os.PathLike[str],
    *,
    title: str = "",
    max_points: int = 20000,
) -> None:
    """Write the interactive HTML map (atomic): one toggleable GeoJSON layer per kind.

    The page is self-contained (:func:`leaflet_page`): Leaflet is inlined from the package, so
    the map, its roads and fixes show offline. Every fix is a point of its layer's
    FeatureCollection (not a marker of its own), so the file grows with the drive only by its
    coordinates and tooltip fields (time, state, edge, way, probability, correction). A legend
    names the colours. Layers of more than ``max_points`` points are thinned evenly.
    """

    def lonlat(xy: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.round(to_lonlat(graph.crs, xy[:, 0], xy[:, 1]), 7) if len(xy) else np.empty((0, 2))

    route_ll = lonlat(data.route_xy[~np.isnan(data.route_xy[:, 0])])
    lo = data.route_xy.min(axis=0) - 300
    hi = data.route_xy.max(axis=0) + 300
    layers = [road_layer(graph, lo, hi)]
    if len(route_ll) >= 2:
        layers.append(line_layer("true route", [route_ll], color="#2ca02c", weight=7, opacity=0.5))
    info = data.info
    fields = ["time", "state", "edge", "way_id", "probability", "correction"]

    def props(i: int) -> dict[str, Any]:
        if info is None:
            return {"fix": i}
        r = info.iloc[i]
        p = float(r["probability"])
        return {
            "fix": i,
            "time": float(r["time"]),
            "state": str(r["state"]),
            "edge": int(r["edge"]),
            "way_id": str(r["way_id"]),
            "probability": "" if np.isnan(p) else round(p, 4),
            "correction": str(r["correction"]),
        }

    def points(name: str, xy: NDArray[np.float64], mask: NDArray[np.bool_] | None, color: str, radius: float,
               fill: bool = True, tip: bool = True) -> None:  # fmt: skip
        rows = np.flatnonzero(~np.isnan(xy[:, 0]) & (True if mask is None else mask))
        if not len(rows):
            return
        rows = rows[:: max(1, len(rows) // max_points)]
        feats = [
            {"type": "Feature", "geometry": {"type": "Point", "coordinates": c},
             "properties": props(int(i)) if tip else {}}
            for i, c in zip(rows.tolist(), lonlat(xy[rows]).tolist(), strict=True)
        ]  # fmt: skip
        style = {"radius": radius, "color": color, "fill": fill, "fillColor": color, "weight": 1,
                 "fillOpacity": 0.8}  # fmt: skip
        tips = (["fix", *fields] if info is not None else ["fix"]) if tip else []
        layers.append(_layer(name, "points", feats, style, tips))

    if len(data.gps_xy):
        points("raw GPS", data.gps_xy, None, "#555555", 1.5, tip=False)
    if len(data.fix_xy):
        points("fused fixes (GPS valid)", data.fix_xy, data.fix_valid, "#1f77b4", 2)
        points("fused fixes in GPS outage", data.fix_xy, ~data.fix_valid, "#d62728", 2.5)
    s = data.snap_xy
    points("snapped", s, data.snap_ok, "#ff7f0e", 2.5)
    points("snapped on wrong edge", s, ~data.snap_ok, "#d62728", 5, fill=False)
    points("ambiguous region", s, data.ambiguous, "#9467bd", 6, fill=False)
    points("decisions", s, data.decided, "#9467bd", 5)
    points("corrections", s, data.corrected, "#e377c2", 7)
    write_html(path, leaflet_page(layers, title=title, legend=LEGEND))


# ---------------------------------------------------------------------- self-contained HTML
TILES_URL = "https://tile.openstreetmap.org/{z}/{x}/{y}.png"
"""The optional background layer of the HTML map (shown when online; the map works without it)."""


def _layer(name: str, kind: str, features: list[dict[str, Any]], style: dict[str, Any],
           tip: list[str]) -> dict[str, Any]:  # fmt: skip
    css_class = "mm-" + "-".join("".join(c if c.isalnum() else " " for c in name.lower()).split())
    style = {**style, "className": css_class}  # the SVG paths of a layer carry its class
    return {"name": name, "kind": kind, "style": style, "tip": tip,
            "data": {"type": "FeatureCollection", "features": features}}  # fmt: skip


def line_layer(
    name: str, parts: list[NDArray[np.float64]], *, color: str, weight: float, opacity: float = 0.8
) -> dict[str, Any]:
    """A layer of lines, each part an ``(n, 2)`` lon/lat array (parts of fewer than 2 points dropped)."""
    feats = [
        {"type": "Feature", "geometry": {"type": "LineString", "coordinates": np.round(p, 7).tolist()},
         "properties": {}}
        for p in parts if len(p) >= 2
    ]  # fmt: skip
    return _layer(name, "lines", feats, {"color": color, "weight": weight, "opacity": opacity}, [])


def point_layer(name: str, lonlat: NDArray[np.float64], *, color: str, radius: float = 3.0) -> dict[str, Any]:
    """A layer of points at ``(n, 2)`` lon/lat (NaN rows dropped), each with its index as tooltip."""
    ll = np.asarray(lonlat, dtype=np.float64).reshape(-1, 2)
    rows = np.flatnonzero(np.isfinite(ll).all(axis=1))
    feats = [
        {"type": "Feature", "geometry": {"type": "Point", "coordinates": np.round(ll[i], 7).tolist()},
         "properties": {"fix": int(i)}}
        for i in rows.tolist()
    ]  # fmt: skip
    style = {"radius": radius, "color": color, "fill": True, "fillColor": color, "weight": 1,
             "fillOpacity": 0.8}  # fmt: skip
    return _layer(name, "points", feats, style, ["fix"])


def road_layer(graph: RoadGraph, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> dict[str, Any]:
    """The roads of ``graph`` inside the box ``lo``..``hi`` (map metres), one feature per road."""
    feats = []
    for e in range(graph.n_edges):
        if graph.edge_reverse[e] >= 0 and graph.edge_reverse[e] < e:
            continue
        seg = graph.edge_xy(e)
        if (seg.max(0) >= lo).all() and (seg.min(0) <= hi).all():
            ll = np.round(to_lonlat(graph.crs, seg[:, 0], seg[:, 1]), 7)
            feats.append(
                {
                    "type": "Feature",
                    "geometry": {"type": "LineString", "coordinates": ll.tolist()},
                    "properties": {
                        "edge": int(e),
                        "way": int(graph.edge_way_id[e]),
                        "name": graph.edge_name(e),
                    },
                }
            )
    return _layer("road graph", "lines", feats, {"color": "#888888", "weight": 2, "opacity": 0.6},
                  ["edge", "way", "name"])  # fmt: skip


def leaflet_assets() -> tuple[str, str]:
    """Leaflet's JavaScript and CSS as shipped in the package (``mapmatch/static/leaflet``)."""
    from importlib.resources import files

    root = files("mapmatch").joinpath("static", "leaflet")
    js = root.joinpath("leaflet.js").read_text(encoding="utf-8")
    css = root.joinpath("leaflet.css").read_text(encoding="utf-8")
    js = "\n".join(line for line in js.splitlines() if not line.startswith("//# sourceMappingURL"))
    return js, css


_PAGE_SCRIPT = """
const LAYERS = %s;
const map = L.map("map", {zoomControl: true});
const tiles = L.tileLayer("%s", {maxZoom: 19,
  attribution: "&copy; OpenStreetMap contributors"});
const overlays = {};
let bounds = null;
for (const l of LAYERS) {
  const opts = {};
  if (l.kind === "lines") { opts.style = () => l.style; }
  else { opts.pointToLayer = (f, ll) => L.circleMarker(ll, l.style); }
  if (l.tip.length) {
    opts.onEachFeature = (f, layer) => layer.bindTooltip(
      l.tip.map(k => k + ": " + f.properties[k]).join("<br>"));
  }
  const g = L.geoJSON(l.data, opts).addTo(map);
  overlays[l.name] = g;
  if (l.data.features.length) {
    bounds = bounds ? bounds.extend(g.getBounds()) : g.getBounds();
  }
}
L.control.layers({"no background": L.layerGroup().addTo(map), "OpenStreetMap tiles": tiles},
  overlays, {collapsed: false}).addTo(map);
L.control.scale().addTo(map);
if (bounds) { map.fitBounds(bounds.pad(0.05)); } else { map.setView([0, 0], 2); }
"""


def _legend_rows(legend: tuple[tuple[str, str, str], ...]) -> str:
    shape = {
        "line": "width:18px;height:4px;background:{c};vertical-align:middle",
        "ring": "width:9px;height:9px;border:2px solid {c};border-radius:50%",
        "dot": "width:11px;height:11px;background:{c};border-radius:50%",
    }
    items = []
    for label, color, kind in legend:
        mark = f"<span style='display:inline-block;{shape[kind].format(c=color)}'></span>"
        items.append(f"<div>{mark}&nbsp;{html.escape(label)}</div>")
    return (
        "<div style='position:fixed;bottom:24px;left:12px;z-index:9999;background:rgba(255,255,255,.9);"
        "padding:6px 9px;border:1px solid #999;border-radius:4px;font:12px sans-serif;line-height:17px'>"
        + "".join(items)
        + "</div>"
    )


def leaflet_page(
    layers: list[dict[str, Any]], *, title: str = "", legend: tuple[tuple[str, str, str], ...] = ()
) -> str:
    """A self-contained HTML page: Leaflet inlined, one toggleable GeoJSON layer per entry of
    ``layers`` (:func:`line_layer`, :func:`point_layer`, :func:`road_layer`), a legend, a title.

    Nothing is loaded from elsewhere except the optional OpenStreetMap background tiles.
    """
    js, css = leaflet_assets()
    data = json.dumps(layers).replace("</", "<\\/")
    script = _PAGE_SCRIPT % (data, TILES_URL)
    head = (
        "<!DOCTYPE html>\n<html><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<title>{html.escape(title.splitlines()[0] if title else 'mapmatch')}</title>"
        f"<style>{css}</style><style>html,body{{height:100%;margin:0}}#map{{height:100%}}</style>"
        f"<script>{js}</script></head>"
    )
    caption = (
        "<div style='position:fixed;top:8px;left:52px;z-index:9999;background:rgba(255,255,255,.85);"
        f"font:12px monospace;white-space:pre;padding:4px'>{html.escape(title)}</div>"
        if title
        else ""
    )
    body = f"<body><div id='map'></div>{caption}{_legend_rows(legend)}<script>{script}</script></body>"
    return f"{head}{body}</html>\n"


def write_html(path: str | os.PathLike[str], page: str) -> None:
    """Write an HTML page atomically."""
    with atomic_path(path) as tmp:
        Path(tmp).write_text(page, encoding="utf-8")


# ---------------------------------------------------------------------- a matched route
ROUTE_LEGEND = (
    ("true route", "#2ca02c", "line"),
    ("matched route", "#ff7f0e", "line"),
    ("fix", "#1f77b4", "dot"),
    ("road graph", "#888888", "line"),
)


@dataclass(frozen=True)
class RoutePicture:
    """What ``mapmatch eval --route`` draws, in lon/lat: the true route, the matched route (each
    a list of ``(n, 2)`` parts), the fixes (``(n, 2)``, may be empty) and optionally the roads."""

    truth: list[NDArray[np.float64]]
    matched: list[NDArray[np.float64]]
    fixes: NDArray[np.float64]
    roads: list[NDArray[np.float64]]

    def check(self) -> None:
        """Raise :class:`ValueError` when there is nothing to draw."""
        if not any(len(p) >= 2 for p in self.truth) and not any(len(p) >= 2 for p in self.matched):
            raise ValueError("nothing to draw: neither the true nor the matched route has a line")


def _metres(ll: NDArray[np.float64], lat0: float) -> NDArray[np.float64]:
    """Local metres of lon/lat points (equirectangular about ``lat0``; enough for a picture)."""
    ll = np.asarray(ll, dtype=np.float64).reshape(-1, 2)
    return np.column_stack([ll[:, 0] * 111_320.0 * np.cos(np.radians(lat0)), ll[:, 1] * 110_574.0])


def draw_route_png(pic: RoutePicture, path: str | os.PathLike[str], *, title: str = "") -> None:
    """Draw a matched route against the true route, with the fixes (PNG, atomic write)."""
    from mapmatch.extras import require

    matplotlib = require("matplotlib", extra="plots", needed_for="drawing the PNG map")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    pic.check()
    lines = [p for p in (*pic.truth, *pic.matched) if len(p)]
    lat0 = float(np.nanmean(np.vstack(lines)[:, 1]))
    fig, ax = plt.subplots(figsize=(10, 8), dpi=110)
    if pic.roads:
        roads = [_metres(p, lat0) for p in pic.roads if len(p) >= 2]
        ax.add_collection(
            LineCollection(roads, colors="#b0b0b0", linewidths=0.8, zorder=1, label="road graph")
        )
    for k, part in enumerate(pic.truth):
        xy = _metres(part, lat0)
        ax.plot(*xy.T, color="#2ca02c", lw=6, alpha=0.45, zorder=2, solid_capstyle="round",
                label="true route" if k == 0 else None)  # fmt: skip
    for k, part in enumerate(pic.matched):
        xy = _metres(part, lat0)
        ax.plot(*xy.T, color="#ff7f0e", lw=2, zorder=3, label="matched route" if k == 0 else None)
    if len(pic.fixes):
        ax.plot(*_metres(pic.fixes, lat0).T, ".", color="#1f77b4", ms=3, zorder=4, label="fix")
    allp = np.vstack([_metres(p, lat0) for p in lines])
    lo, hi = np.nanmin(allp, axis=0) - 60.0, np.nanmax(allp, axis=0) + 60.0
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("east, m")
    ax.set_ylabel("north, m")
    ax.ticklabel_format(useOffset=True, style="plain")
    if title:
        fig.suptitle(title, fontsize=9, x=0.01, ha="left", family="monospace")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def draw_route_html(pic: RoutePicture, path: str | os.PathLike[str], *, title: str = "") -> None:
    """Draw a matched route against the true route, with the fixes (self-contained HTML, atomic)."""
    pic.check()
    layers = []
    if pic.roads:
        layers.append(line_layer("road graph", pic.roads, color="#888888", weight=2, opacity=0.6))
    layers.append(line_layer("true route", pic.truth, color="#2ca02c", weight=7, opacity=0.5))
    layers.append(line_layer("matched route", pic.matched, color="#ff7f0e", weight=3, opacity=0.9))
    if len(pic.fixes):
        layers.append(point_layer("fixes", pic.fixes, color="#1f77b4", radius=2.5))
    write_html(path, leaflet_page(layers, title=title, legend=ROUTE_LEGEND))
