"""Pictures of a match: a PNG map (matplotlib) and an interactive HTML map (folium).

Both show the road graph, the true route, the raw GPS and fused fixes (fixes in GPS outages,
i.e. dead reckoning, in red), the snapped positions (on the wrong edge in red), the fixes the
matcher reported as ambiguous (inside an ambiguous region), the decisions it committed on
leaving one, and the fixes that carried a correction.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
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


def draw_html(
    graph: RoadGraph, data: PlotData, path: str | os.PathLike[str], *, title: str = "", max_points: int = 4000
) -> None:
    """Write the interactive HTML map (folium, atomic), one toggleable layer per kind."""
    from mapmatch.extras import require

    folium = require("folium", extra="plots", needed_for="drawing the HTML map")

    def ll(xy: NDArray[np.float64]) -> list[list[float]]:
        ok = ~np.isnan(xy[:, 0])
        if not ok.any():
            return []
        g = to_lonlat(graph.crs, xy[ok, 0], xy[ok, 1])
        return np.round(g[:, ::-1], 7).tolist()

    def thin(xy: NDArray[np.float64]) -> NDArray[np.float64]:
        step = max(1, len(xy) // max_points)
        return xy[::step]

    route = ll(data.route_xy)
    centre = np.mean(route, axis=0).tolist() if route else [0.0, 0.0]
    m = folium.Map(location=centre, zoom_start=15, tiles="OpenStreetMap", control_scale=True)
    if title:
        m.get_root().html.add_child(  # type: ignore[attr-defined]
            folium.Element(f"<div style='font:12px monospace;white-space:pre'>{title}</div>")
        )
    lo = data.route_xy.min(axis=0) - 300
    hi = data.route_xy.max(axis=0) + 300
    roads = folium.FeatureGroup(name="road graph")
    for e in range(graph.n_edges):
        if graph.edge_reverse[e] >= 0 and graph.edge_reverse[e] < e:
            continue
        s = graph.edge_xy(e)
        if (s.max(0) >= lo).all() and (s.min(0) <= hi).all():
            folium.PolyLine(ll(s), color="#888888", weight=2, opacity=0.6).add_to(roads)
    roads.add_to(m)
    fg = folium.FeatureGroup(name="true route")
    folium.PolyLine(route, color="#2ca02c", weight=7, opacity=0.5).add_to(fg)
    fg.add_to(m)

    def points(name: str, xy: NDArray[np.float64], color: str, radius: float, fill: bool = True) -> None:
        g = folium.FeatureGroup(name=name)
        for lat, lon in ll(thin(xy)):
            folium.CircleMarker(
                [lat, lon], radius=radius, color=color, fill=fill, weight=1, fill_opacity=0.8
            ).add_to(g)
        g.add_to(m)

    if len(data.gps_xy):
        points("raw GPS", data.gps_xy, "#555555", 1.5)
    if len(data.fix_xy):
        points("fused fixes (GPS valid)", data.fix_xy[data.fix_valid], "#1f77b4", 2)
        points("fused fixes in GPS outage", data.fix_xy[~data.fix_valid], "#d62728", 2.5)
    s = data.snap_xy
    points("snapped", s[data.snap_ok], "#ff7f0e", 2)
    points("snapped on wrong edge", s[~data.snap_ok], "#d62728", 4)
    points("ambiguous region", s[data.ambiguous], "#9467bd", 5, fill=False)
    points("decisions", s[data.decided], "#9467bd", 5)
    points("corrections", s[data.corrected], "#e377c2", 7)
    folium.LayerControl(collapsed=False).add_to(m)
    with atomic_path(path) as tmp:
        m.save(str(tmp))
