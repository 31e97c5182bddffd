"""Why a whole track or vehicle is unmatched, when its coordinates tell (``match``, ``replay``)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

MARGIN_DEG = 0.05
"""Degrees round the map's bounding box that still count as on the map (a few kilometres)."""


def coordinate_hint(lat: ArrayLike, lon: ArrayLike, bbox: tuple[float, float, float, float]) -> str:
    """Why points ``lat``/``lon`` cannot lie on a map of ``bbox`` (min lon, min lat, max lon, max lat).

    Not degrees (projected coordinates, wrong columns), off the map, or on it with lat and lon
    swapped; "" when they do not tell (the points are on the map but far from its roads).
    """
    lon0, lat0, lon1, lat1 = (float(v) for v in bbox)
    la = np.asarray(lat, dtype=np.float64)
    lo = np.asarray(lon, dtype=np.float64)
    if not len(la):
        return ""
    ok = np.isfinite(la) & np.isfinite(lo) & (np.abs(la) <= 90) & (np.abs(lo) <= 180)
    if not ok.any():
        return (
            "no point has lat/lon in degrees (lat within ±90, lon within ±180): projected "
            "coordinates, or the wrong columns (--lat-col, --lon-col)?"
        )
    m = MARGIN_DEG

    def on_map(a: Any, b: Any) -> Any:
        return (a >= lat0 - m) & (a <= lat1 + m) & (b >= lon0 - m) & (b <= lon1 + m)

    if on_map(la[ok], lo[ok]).any():
        return ""
    where = f"lat {np.median(la[ok]):.4f}, lon {np.median(lo[ok]):.4f}"
    extent = f"lat {lat0:.4f} to {lat1:.4f}, lon {lon0:.4f} to {lon1:.4f}"
    if on_map(lo[ok], la[ok]).any():
        return (
            f"its points ({where}) lie off the map ({extent}) but would lie on it with lat and lon "
            "swapped: check --lat-col and --lon-col"
        )
    return f"its points ({where}) lie off the map ({extent}): another city's map?"
