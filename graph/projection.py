"""Local metric projections: the UTM zone of a place, and transforms to and from WGS84."""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pyproj import Transformer
from pyproj.enums import TransformDirection


def utm_crs(lon: float, lat: float) -> str:
    """The UTM zone CRS (``"EPSG:326zz"`` or ``"EPSG:327zz"``) containing ``(lon, lat)``."""
    zone = min(max(math.floor((lon + 180.0) / 6.0) + 1, 1), 60)
    return f"EPSG:{(32600 if lat >= 0 else 32700) + zone}"


_local = threading.local()


def _transformer(src: str, dst: str) -> Transformer:
    """A cached transformer for this thread (pyproj transformers are not shared across threads)."""
    cache: dict[tuple[str, str], Transformer] | None = getattr(_local, "cache", None)
    if cache is None:
        cache = _local.cache = {}
    tf = cache.get((src, dst))
    if tf is None:
        tf = cache[(src, dst)] = Transformer.from_crs(src, dst, always_xy=True)
    return tf


def to_xy(crs: str, lon: ArrayLike, lat: ArrayLike) -> NDArray[np.float64]:
    """WGS84 lon/lat to (P, 2) metres in ``crs``."""
    x, y = _transformer("EPSG:4326", crs).transform(np.asarray(lon, float), np.asarray(lat, float))
    return np.column_stack([np.atleast_1d(x), np.atleast_1d(y)])


def to_lonlat(crs: str, x: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
    """(P, 2) WGS84 lon/lat from metres in ``crs``."""
    lon, lat = _transformer(crs, "EPSG:4326").transform(np.asarray(x, float), np.asarray(y, float))
    return np.column_stack([np.atleast_1d(lon), np.atleast_1d(lat)])


def rows_to_lonlat(crs: str, buf: NDArray[np.float64]) -> None:
    """Project the rows of a C-contiguous (2, P) float64 buffer (x, y in ``crs``) to WGS84
    lon/lat in place: the numbers of :func:`to_lonlat`, without its argument checks and copies.

    :meth:`Transformer.transform` spends most of its time on a handful of points checking and
    copying its arguments before it calls the projection; with pyproj's own buffers this calls
    the projection directly (the same PROJ call, so the same numbers), else the public method.
    """
    tf = _transformer(crs, "EPSG:4326")
    core = getattr(tf, "_transformer", None)
    if core is not None and hasattr(core, "_transform"):
        try:
            core._transform(buf[0], buf[1], None, None, TransformDirection.FORWARD, False, False)
            return
        except TypeError:  # a pyproj whose private call differs: the public one below
            pass
    tf.transform(buf[0], buf[1], inplace=True)


_FORWARD = TransformDirection.FORWARD


def _point_call(kind: str, src: str, dst: str) -> Any:
    """pyproj's own projection of one point from ``src`` to ``dst`` for this thread (kept in
    this thread's ``kind`` cache), or None when this pyproj has none that gives the public
    method's numbers.

    :meth:`Transformer.transform` spends most of its microsecond on one point looking up the
    thread's transformer and trying its arguments; its point projection is the same PROJ call,
    so the same numbers.
    """
    cache: dict[str, Any] | None = getattr(_local, kind, None)
    if cache is None:
        cache = {}
        setattr(_local, kind, cache)
    tf = _transformer(src, dst)
    point = getattr(getattr(tf, "_transformer", None), "_transform_point", None)
    try:
        probe = (1.0, 1.0)
        same = point is not None and point(*probe, None, None, _FORWARD, False, False) == tf.transform(*probe)
    except TypeError:
        same = False
    if not same:
        point = None
    cache[dst if src == "EPSG:4326" else src] = point
    return point


def point_to_xy(crs: str, lon: float, lat: float) -> tuple[float, float]:
    """One WGS84 point to metres in ``crs`` (plain floats; the online matcher's hot path)."""
    try:
        point = _local.to_xy[crs]
    except (AttributeError, KeyError):
        point = _point_call("to_xy", "EPSG:4326", crs)
    if point is not None:
        try:
            return point(lon, lat, None, None, _FORWARD, False, False)  # type: ignore[no-any-return]
        except TypeError:  # not a Python int or float (a numpy float32, say)
            pass
    x, y = _transformer("EPSG:4326", crs).transform(lon, lat)
    return float(x), float(y)


def point_to_lonlat(crs: str, x: float, y: float) -> tuple[float, float]:
    """One point in metres in ``crs`` to WGS84 ``(lon, lat)`` (plain floats)."""
    try:
        point = _local.to_lonlat[crs]
    except (AttributeError, KeyError):
        point = _point_call("to_lonlat", crs, "EPSG:4326")
    if point is not None:
        try:
            return point(x, y, None, None, _FORWARD, False, False)  # type: ignore[no-any-return]
        except TypeError:
            pass
    lon, lat = _transformer(crs, "EPSG:4326").transform(x, y)
    return float(lon), float(lat)
