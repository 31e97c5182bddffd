"""Angles in degrees, written once: the compass bearing of a vector and the difference of two
bearings. Scalar forms in plain float math (the online path calls them as they are, compiled
kernels their ``*_compiled`` forms), and array forms for numpy."""

from __future__ import annotations

import math
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from graph.jit import njit

__all__ = ["angle_diff", "angle_diff_compiled", "angle_diffs", "bearing", "bearing_compiled", "bearings"]

Angle = TypeVar("Angle", float, NDArray[np.float64])


def bearing(dx: float, dy: float) -> float:
    """Compass bearing in degrees, in [0, 360), of the vector ``(dx, dy)`` (0 = north/+y,
    90 = east/+x)."""
    return math.degrees(math.atan2(dx, dy)) % 360.0


bearing_compiled = njit(cache=True, inline="always")(bearing)


def bearings(dx: NDArray[np.float64], dy: NDArray[np.float64]) -> NDArray[np.float64]:
    """:func:`bearing` of each vector ``(dx[i], dy[i])``."""
    return np.asarray(np.degrees(np.arctan2(dx, dy)) % 360.0, dtype=np.float64)


def angle_diff(a: float, b: float) -> float:
    """The signed smallest difference ``a - b`` of two angles in degrees, in (-180, 180]."""
    d = (a - b + 180.0) % 360.0 - 180.0
    return 180.0 if d == -180.0 else d


angle_diff_compiled = njit(cache=True)(angle_diff)


def angle_diffs(a: Angle, b: Angle) -> Angle:
    """:func:`angle_diff` over arrays (broadcast), except that a difference of exactly 180°
    comes out as -180 (the sign of a half turn is arbitrary; callers take its size or square)."""
    return (a - b + 180.0) % 360.0 - 180.0  # type: ignore[return-value]
