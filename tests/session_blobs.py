"""The fixed drives whose session blobs ``tests/data/session_blobs.txt.gz`` pins, byte for byte
(one blob a line, after every fix of each drive in turn); ``session_blobs_v2.txt.gz`` holds
the same states in version 2 of the format."""

from __future__ import annotations

import base64
import gzip
import json
import math
from pathlib import Path
from typing import Any

from online_helpers import DriveSpec, drive
from service_util import city

from mapmatch.online import OnlineMatcher
from mapmatch.types import Fix

PINNED = Path(__file__).parent / "data" / "session_blobs.txt.gz"
PINNED_V2 = Path(__file__).parent / "data" / "session_blobs_v2.txt.gz"


def drives() -> tuple[OnlineMatcher, list[list[Fix]]]:
    """A matcher on the city map and two drives: one GPS-aided; one losing GPS for a stretch
    and then wandering 80 m off the road."""
    amap = city()
    plain = drive(amap, "abefc", DriveSpec(speed=10.0, dt=1.0, noise=1.5, seed=7, sigma=3.0))
    wander = drive(
        amap, "abefcd", DriveSpec(speed=12.0, dt=1.0, noise=6.0, seed=11, sigma=2.0, heading_noise=8.0)
    )
    for i, f in enumerate(wander):
        if 8 <= i < 20:  # dead reckoning only
            wander[i] = f._replace(gps_valid=False)
        elif 24 <= i < 30:
            wander[i] = f._replace(lat=f.lat + 0.0007)
    return OnlineMatcher(amap.graph), [plain, wander]


def blobs() -> list[list[bytes]]:
    """Each drive's blobs, after every fix, from the matcher as it is."""
    m, runs = drives()
    out = []
    for fixes in runs:
        st = m.new_session()
        out.append([(m.update(st, f), st.to_bytes())[1] for f in fixes])
    return out


def pinned(path: Path = PINNED) -> list[list[bytes]]:
    """The pinned blobs (of ``path``), split by drive as :func:`blobs` returns them."""
    lines = gzip.decompress(path.read_bytes()).splitlines()
    _, runs = drives()
    out, at = [], 0
    for fixes in runs:
        out.append(lines[at : at + len(fixes)])
        at += len(fixes)
    assert at == len(lines), "the pinned file does not match the drives"
    return out


ULP_TOLERANCE = 1e-12
"""Relative difference allowed between a float of a pinned blob and the matcher's: numpy's
SIMD paths (AVX-512 or not) round a few operations differently in the last bit, so the same
code on another processor moves a value by an ulp."""


def blob_difference(got: bytes, want: bytes) -> str | None:
    """Where ``got`` differs from the pinned ``want`` beyond :data:`ULP_TOLERANCE`, or None: the
    same keys in the same order, the same types and whole numbers, floats (also those packed
    as little-endian float64 in base64 under keys ending ``_f64``) within the tolerance."""
    if got == want:
        return None
    return _diff(json.loads(got), json.loads(want), "")


def _diff(a: Any, b: Any, at: str) -> str | None:
    if isinstance(a, dict) and isinstance(b, dict):
        if list(a) != list(b):
            return f"{at}: keys {list(a)} against {list(b)}"
        for k in a:
            x, y = a[k], b[k]
            if k.endswith("_f64") and isinstance(x, str) and isinstance(y, str):
                x, y = (_floats(v) for v in (x, y))
            if (d := _diff(x, y, f"{at}.{k}")) is not None:
                return d
        return None
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{at}: {len(a)} items against {len(b)}"
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            if (d := _diff(x, y, f"{at}[{i}]")) is not None:
                return d
        return None
    if isinstance(a, float) and isinstance(b, float):
        same = (math.isnan(a) and math.isnan(b)) or math.isclose(a, b, rel_tol=ULP_TOLERANCE, abs_tol=1e-300)
        return None if same else f"{at}: {a!r} against {b!r}"
    return None if (type(a), a) == (type(b), b) else f"{at}: {a!r} against {b!r}"


def _floats(text: str) -> list[float]:
    import numpy as np

    return np.frombuffer(base64.b64decode(text), "<f8").tolist()


def write() -> None:
    """Rewrite the pinned files from the matcher as it is (only when the answers or the format
    change on purpose): the blobs, and the same states in version 2."""
    from mapmatch.online import SessionState
    from mapmatch.online.codec import to_bytes

    runs = blobs()
    data = b"".join(b + b"\n" for run in runs for b in run)
    PINNED.write_bytes(gzip.compress(data, mtime=0))
    old = b"".join(to_bytes(SessionState.from_bytes(b), version=2) + b"\n" for run in runs for b in run)
    PINNED_V2.write_bytes(gzip.compress(old, mtime=0))


if __name__ == "__main__":
    write()
