"""The fixed drives whose session blobs ``tests/data/session_blobs.txt.gz`` pins, byte for byte
(one blob a line, after every fix of each drive in turn); ``session_blobs_v2.txt.gz`` holds
the same states in version 2 of the format."""

from __future__ import annotations

import gzip
from pathlib import Path

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


def write() -> None:
    """Rewrite the pinned file from the matcher as it is (only when the format changes on purpose)."""
    data = b"".join(b + b"\n" for run in blobs() for b in run)
    PINNED.write_bytes(gzip.compress(data, mtime=0))


if __name__ == "__main__":
    write()
