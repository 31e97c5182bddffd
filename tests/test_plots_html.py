"""The HTML map: GeoJSON layers (not a marker per fix), per-fix tooltips, a legend; the PNG's legend."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from graph.ascii import parse_ascii_map
from mapmatch.plots import LEGEND, draw_html, draw_png, plot_data

DRAWING = """
a-----------b-----------c
"""


def _frames(n: int) -> tuple[object, pd.DataFrame, pd.DataFrame]:
    m = parse_ascii_map(DRAWING, scale=10)
    x0, y0 = m.xy("a")
    x1, _ = m.xy("c")
    xs = np.linspace(x0 + 2, x1 - 2, n)
    ll = np.array([m.lonlat(x, y0 + 1.0) for x in xs])
    t = np.arange(n, dtype=float)
    fixes = pd.DataFrame(
        {"time": t, "lat": ll[:, 1], "lon": ll[:, 0], "gps_valid": (t % 10 != 3).astype(int)}
    )
    e = m.edge("a", "b")
    matched = pd.DataFrame(
        {
            "time": t,
            "state": ["ambiguous" if i % 7 == 0 else "on_road" for i in range(n)],
            "edge": e,
            "way_id": 42,
            "lat": ll[:, 1],
            "lon": ll[:, 0],
            "candidates": f"{e}:0.8125;{e + 1}:0.1875",
            "correction": ["1;2" if i == 5 else "" for i in range(n)],
        }
    )
    return m, fixes, matched


def test_html_map_has_tooltips_legend_and_grows_with_the_drive(tmp_path: Path) -> None:
    sizes = {}
    for n in (100, 400):
        m, fixes, matched = _frames(n)
        gps = fixes[["time", "lat", "lon"]]
        data = plot_data(
            m.graph, route_xy=np.array([m.xy("a"), m.xy("c")]), fixes=fixes, matched=matched, gps=gps
        )
        out = tmp_path / f"m{n}.html"
        draw_html(m.graph, data, out, title="test")
        html = out.read_text()
        sizes[n] = len(html)
        for label, _, _ in LEGEND:
            assert label in html
        for field in ("time", "state", "edge", "way_id", "probability", "correction"):
            assert f'"{field}"' in html
        assert '"probability": 0.8125' in html and '"correction": "edges 1;2"' in html
        # points are features of a few GeoJSON layers, not one marker object each
        assert len(re.findall(r"L\.circleMarker\(", html)) < 20
        assert len(re.findall(r'"type": "Point"', html)) >= 2 * n
    # proportional to the drive: 4x the fixes, about 4x the per-fix bytes
    per_fix = (sizes[400] - sizes[100]) / 300
    assert per_fix < 1500, per_fix


def test_png_keeps_its_legend(tmp_path: Path) -> None:
    m, fixes, matched = _frames(60)
    data = plot_data(m.graph, route_xy=np.array([m.xy("a"), m.xy("c")]), fixes=fixes, matched=matched)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seen: list[list[str]] = []
    orig = plt.Figure.legend

    def spy(self, handles, labels, **kw):  # type: ignore[no-untyped-def]
        seen.append(list(labels))
        return orig(self, handles, labels, **kw)

    plt.Figure.legend = spy  # type: ignore[method-assign]
    try:
        draw_png(m.graph, data, tmp_path / "m.png")
    finally:
        plt.Figure.legend = orig  # type: ignore[method-assign]
    assert (tmp_path / "m.png").stat().st_size > 10_000
    assert seen and {"true route", "snapped", "ambiguous region", "correction"} <= set(seen[0])
