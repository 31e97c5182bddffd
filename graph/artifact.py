"""The prepared map artifact: one versioned file, written atomically, memory-mapped on load.

Layout of a map file (little-endian)::

    8 bytes   magic  b"RGMAP\\x00\\x00\\x01"
    8 bytes   uint64 length H of the JSON manifest
    H bytes   manifest (UTF-8 JSON), padded with spaces to a 64-byte boundary
    ...       the arrays, raw C order, each starting on a 64-byte boundary

The manifest holds the format version, CRS, bbox, counts, map statistics, the source's
checksum, the build parameters, the lookup tables, per array its dtype, shape, offset and
SHA-256, and ``manifest_sha256``: the SHA-256 of the first ``16 + H`` bytes of the file
(magic, length, manifest and its padding) with that digest written as 64 zeros. With the
arrays' checksums and zero padding between them, every byte of the file is checked.
Loading opens the file once and memory-maps that descriptor (read-only), verifies every checksum and
validates every manifest field it uses before allocating anything; it imports neither osmnx
nor networkx.
"""

from __future__ import annotations

import hashlib
import json
import math
import mmap
import os
import re
import stat
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeGuard

import numpy as np
from numpy.typing import NDArray

from graph.errors import ArtifactError
from graph.road_graph import ARRAY_FIELDS, PIECE_FIELDS, RoadGraph

MAGIC = b"RGMAP\x00\x00\x01"
FORMAT = "mapmatch-roadgraph"
FORMAT_VERSION = 1
_ALIGN = 64
MAX_MANIFEST_BYTES = 256 * 1024 * 1024
_DIGEST_KEY = "manifest_sha256"
_ZERO_DIGEST = "0" * 64
_DIGEST_RE = re.compile(rb'"manifest_sha256":"([0-9a-f]{64})"')
_UTM_CRS = re.compile(r"EPSG:32[67](0[1-9]|[1-5][0-9]|60)")
"""A UTM zone's EPSG code (zones 1-60, north 326zz and south 327zz)."""


def _pad(n: int) -> int:
    return (-n) % _ALIGN


def _jsonable(obj: Any) -> Any:
    """Coerce numpy scalars, paths, tuples and sets into plain JSON values."""
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple | set):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if obj is None or isinstance(obj, bool | int | float | str):
        return obj
    return str(obj)


def edge_length_histogram(graph: RoadGraph) -> dict[str, list[float]]:
    """Counts of edge lengths in log-spaced bins (1 m .. 100 km; the first bin starts at 0)."""
    edges = [0.0, *np.logspace(0, 5, 11).tolist()]
    counts, _ = np.histogram(np.clip(graph.edge_len, 0.0, edges[-1]), bins=edges)
    return {"bins_m": [round(x, 3) for x in edges], "counts": counts.tolist()}


def manifest_for(graph: RoadGraph) -> dict[str, Any]:
    """The manifest fields that describe a graph (without the array table)."""
    meta = _jsonable(graph.meta)
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "crs": graph.crs,
        "bbox": list(graph.bbox),
        "counts": {
            "nodes": graph.n_nodes,
            "edges": graph.n_edges,
            "segments": len(graph.seg_xy),
            "restrictions": len(graph.restrictions),
        },
        "stats": _jsonable({**graph.stats(), "edge_len_histogram": edge_length_histogram(graph)}),
        "source": meta.get("source", {}),
        "build": meta.get("build", {}),
        "meta": meta,
        "names": list(graph.names),
        "highways": list(graph.highways),
    }


def save_map(graph: RoadGraph, path: str | os.PathLike[str]) -> None:
    """Write ``graph`` to the map file ``path`` atomically (temporary file, then rename).

    Parameters
    ----------
    graph
        The road graph to store.
    path
        Destination file. An existing file is replaced only once the new one is complete.

    Raises
    ------
    ArtifactError
        When the file cannot be written.
    """
    dest = Path(path)
    arrays = {k: np.ascontiguousarray(v) for k, v in graph.arrays().items()}
    raw = {k: a.reshape(-1).view(np.uint8) for k, a in arrays.items()}
    table: dict[str, dict[str, Any]] = {}
    offset = 0
    for name in ARRAY_FIELDS:
        a = arrays[name]
        table[name] = {
            "dtype": a.dtype.str,
            "shape": list(a.shape),
            "offset": offset,
            "nbytes": int(a.nbytes),
            "sha256": hashlib.sha256(raw[name].data).hexdigest(),
        }
        offset += a.nbytes + _pad(a.nbytes)
    manifest = manifest_for(graph)
    manifest["arrays"] = table
    manifest[_DIGEST_KEY] = _ZERO_DIGEST
    head = json.dumps(manifest, separators=(",", ":"), allow_nan=False, default=str).encode()
    head += b" " * _pad(len(MAGIC) + 8 + len(head))
    digest = hashlib.sha256(MAGIC + np.uint64(len(head)).tobytes() + head).hexdigest()
    head = head.replace(_digest_field(_ZERO_DIGEST), _digest_field(digest), 1)
    tmp_name = ""
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent)
        with os.fdopen(fd, "wb") as f:
            f.write(MAGIC)
            f.write(np.uint64(len(head)).tobytes())
            f.write(head)
            for name in ARRAY_FIELDS:
                a = arrays[name]
                f.write(raw[name].data)
                f.write(b"\0" * _pad(a.nbytes))
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp_name, 0o644)
        os.replace(tmp_name, dest)
    except (OSError, ValueError) as exc:
        if tmp_name:
            Path(tmp_name).unlink(missing_ok=True)
        raise ArtifactError(f"cannot write map file {dest}: {exc}") from exc
    except BaseException:
        if tmp_name:
            Path(tmp_name).unlink(missing_ok=True)
        raise


def _digest_field(digest: str) -> bytes:
    return f'"{_DIGEST_KEY}":"{digest}"'.encode()


def _read_head(f: Any, path: Path) -> tuple[dict[str, Any], int]:
    start = f.read(len(MAGIC) + 8)
    if len(start) < len(MAGIC) + 8 or start[: len(MAGIC) - 1] != MAGIC[:-1]:
        raise ArtifactError(f"{path} is not a prepared map file")
    if start[len(MAGIC) - 1] != MAGIC[-1]:
        raise ArtifactError(f"{path}: unsupported map file version {start[len(MAGIC) - 1]}")
    hlen = int(np.frombuffer(start[len(MAGIC) :], dtype="<u8")[0])
    if hlen > os.fstat(f.fileno()).st_size - len(start) or hlen > MAX_MANIFEST_BYTES:
        raise ArtifactError(
            f"{path} is truncated or corrupt (manifest length {hlen} beyond the file or the limit)"
        )
    raw = f.read(hlen)
    if len(raw) != hlen:
        raise ArtifactError(f"{path} is truncated")
    try:
        manifest = json.loads(raw)
    except ValueError as exc:
        raise ArtifactError(f"{path}: corrupt manifest") from exc
    if not isinstance(manifest, dict):
        raise ArtifactError(f"{path}: corrupt manifest (not an object)")
    if manifest.get("format") != FORMAT or manifest.get("format_version") != FORMAT_VERSION:
        raise ArtifactError(
            f"{path}: unsupported map format {manifest.get('format')!r} "
            f"version {manifest.get('format_version')!r} (this program reads version {FORMAT_VERSION})"
        )
    found = _DIGEST_RE.findall(raw)
    if len(found) != 1:
        raise ArtifactError(
            f"{path}: the manifest has no checksum (corrupt, or written by an older version: "
            "prepare the map again)"
        )
    digest = found[0].decode()
    zeroed = raw.replace(_digest_field(digest), _digest_field(_ZERO_DIGEST), 1)
    if hashlib.sha256(start + zeroed).hexdigest() != digest:
        raise ArtifactError(f"{path}: manifest checksum mismatch (file corrupt)")
    return manifest, len(MAGIC) + 8 + hlen


def _is_count(v: Any) -> TypeGuard[int]:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def _checked_table(
    manifest: dict[str, Any], path: Path, data_start: int, size: int
) -> dict[str, dict[str, Any]]:
    """The manifest's array table, every entry validated against the file's size (before
    anything is allocated), and the file's length checked to end with the last array."""
    table = manifest.get("arrays")
    if not isinstance(table, dict):
        raise ArtifactError(f"{path}: corrupt manifest (no array table)")
    # maps written before way pieces get one piece per edge (RoadGraph fills them in)
    missing = [k for k in ARRAY_FIELDS if k not in table and k not in PIECE_FIELDS]
    if missing:
        raise ArtifactError(f"{path}: map file lacks arrays {', '.join(missing)}")
    end = data_start
    for name, t in table.items():
        bad = f"{path}: corrupt manifest entry for array {name!r}"
        if not isinstance(t, dict):
            raise ArtifactError(bad)
        shape, offset, nbytes = t.get("shape"), t.get("offset", -1), t.get("nbytes", -1)
        if not (isinstance(shape, list) and all(_is_count(d) for d in shape) and _is_count(offset)):
            raise ArtifactError(f"{bad} (shape or offset)")
        if not (_is_count(nbytes) and isinstance(t.get("sha256"), str) and isinstance(t.get("dtype"), str)):
            raise ArtifactError(f"{bad} (nbytes, sha256 or dtype)")
        try:
            dtype = np.dtype(t["dtype"])
        except (TypeError, ValueError):
            raise ArtifactError(f"{bad} (dtype {t['dtype']!r})") from None
        if dtype.hasobject or math.prod(shape) * dtype.itemsize != nbytes:
            raise ArtifactError(f"{bad} (dtype, shape and size disagree)")
        if data_start + offset + nbytes > size:
            raise ArtifactError(
                f"{path} is truncated or corrupt (array {name} ends past the end of the file)"
            )
        end = max(end, data_start + offset + nbytes + _pad(nbytes))
    if size != end:
        raise ArtifactError(f"{path} is corrupt ({size} bytes, the manifest describes {end})")
    return table


def _check_fields(manifest: dict[str, Any], path: Path) -> None:
    """The manifest's descriptive fields have the types the loader relies on; the CRS parses."""
    crs = manifest.get("crs")
    if not isinstance(crs, str) or not crs:
        raise ArtifactError(f"{path}: corrupt manifest (crs)")
    if not _UTM_CRS.fullmatch(crs):  # a UTM zone (what builds write) is valid by its form
        from pyproj import CRS  # importing pyproj alone costs 0.2-0.6 s of a load
        from pyproj.exceptions import CRSError

        try:
            CRS.from_user_input(crs)
        except CRSError:
            raise ArtifactError(f"{path}: the manifest's CRS {crs[:40]!r} is not a valid CRS") from None
    for key in ("names", "highways"):
        v = manifest.get(key, [])
        if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
            raise ArtifactError(f"{path}: corrupt manifest ({key} must be a list of strings)")
    if not isinstance(manifest.get("meta", {}), dict):
        raise ArtifactError(f"{path}: corrupt manifest (meta)")


def read_manifest(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The manifest of a map file, without reading its arrays."""
    p = Path(path)
    try:
        with open(p, "rb") as f:
            return _read_head(f, p)[0]
    except FileNotFoundError as exc:
        raise ArtifactError(f"no such map file: {p}") from exc
    except IsADirectoryError as exc:
        raise ArtifactError(f"{p} is a directory, not a map file") from exc
    except OSError as exc:
        raise ArtifactError(f"cannot read map file {p}: {exc.strerror}") from exc


class _FdReader:
    """``read`` and ``fileno`` over a descriptor with ``pread`` (the descriptor's offset,
    which others may share, is left alone)."""

    def __init__(self, fd: int) -> None:
        self.fd, self.pos = fd, 0

    def fileno(self) -> int:
        return self.fd

    def read(self, n: int) -> bytes:
        parts: list[bytes] = []
        while n > 0:
            chunk = os.pread(self.fd, min(n, 1 << 24), self.pos)
            if not chunk:
                break
            parts.append(chunk)
            self.pos += len(chunk)
            n -= len(chunk)
        return b"".join(parts)


def load_map(path: str | os.PathLike[str], *, verify: bool = True) -> RoadGraph:
    """Load a map file written by :func:`save_map`: the file is opened once and
    :func:`load_map_fd` maps that descriptor.

    Raises
    ------
    ArtifactError
        Missing file, wrong format or version, truncated file, or a checksum mismatch.
    """
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_CLOEXEC | os.O_NONBLOCK)
    except FileNotFoundError as exc:
        raise ArtifactError(f"no such map file: {p}") from exc
    except OSError as exc:
        raise ArtifactError(f"cannot read map file {p}: {exc.strerror}") from exc
    try:
        return load_map_fd(fd, name=str(p), verify=verify)
    finally:
        os.close(fd)


def load_map_fd(fd: int, *, name: str, verify: bool = True) -> RoadGraph:
    """Load a map file from an open descriptor, never by name.

    The descriptor is checked with ``fstat`` (a regular file; its size bounds every offset),
    the manifest is read with ``pread``, and the arrays are read-only views of one memory map
    of the descriptor: a file later replaced under the same name (a map prepared again over
    it) does not change the map. The caller may close ``fd`` afterwards (the mapping stays).
    Every array's SHA-256 is checked unless ``verify`` is False. ``name`` names the file in
    messages.

    Raises
    ------
    ArtifactError
        Not a regular file, wrong format or version, truncated file, or a checksum mismatch.
    """
    p = Path(name)
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise ArtifactError(f"{p} is a directory, not a map file")
        if not stat.S_ISREG(st.st_mode):
            raise ArtifactError(f"{p} is not a regular file")
        size = st.st_size
        manifest, data_start = _read_head(_FdReader(fd), p)
    except OSError as exc:
        raise ArtifactError(f"cannot read map file {p}: {exc.strerror}") from exc
    table = _checked_table(manifest, p, data_start, size)
    _check_fields(manifest, p)
    try:
        # a plain ndarray over the mapping: indexing a np.memmap subclass costs microseconds per scalar
        buf: NDArray[np.uint8] = (
            np.frombuffer(mmap.mmap(fd, size, access=mmap.ACCESS_READ), dtype=np.uint8)
            if size
            else np.empty(0, np.uint8)
        )
    except (OSError, ValueError) as exc:
        raise ArtifactError(f"cannot map map file {p}: {exc}") from exc
    for name_, t in table.items():  # the padding after each array is zeros
        lo = data_start + t["offset"] + t["nbytes"]
        gap = buf[lo : lo + _pad(t["nbytes"])]
        if gap.any():
            raise ArtifactError(f"{p}: corrupt padding after array {name_} (file corrupt)")
    arrays: dict[str, NDArray[Any]] = {}
    for key in (k for k in ARRAY_FIELDS if k in table):
        t = table[key]
        lo = data_start + int(t["offset"])
        raw = buf[lo : lo + int(t["nbytes"])]
        if verify and hashlib.sha256(raw.data).hexdigest() != t["sha256"]:
            raise ArtifactError(f"{p}: checksum mismatch in {key} (file corrupt)")
        try:
            arrays[key] = raw.view(np.dtype(t["dtype"])).reshape(t["shape"])
        except (TypeError, ValueError) as exc:
            raise ArtifactError(f"{p}: bad array {key}: {exc}") from exc
    meta = manifest.get("meta", {})
    meta = {**meta, "artifact": {"path": str(p), "bytes": size}}
    try:
        return RoadGraph(
            crs=str(manifest["crs"]),
            names=list(manifest.get("names", [])),
            highways=list(manifest.get("highways", [])),
            meta=meta,
            **arrays,
        )
    except (TypeError, ValueError, KeyError) as exc:  # arrays that disagree with each other
        raise ArtifactError(f"{p}: corrupt map ({type(exc).__name__}: {str(exc)[:200]})") from None


def file_sha256(path: str | os.PathLike[str], *, chunk: int = 1 << 22) -> str:
    """SHA-256 of a file's bytes (the source checksum in the manifest)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def open_map(path: str | os.PathLike[str]) -> RoadGraph:
    """A prepared map file (fast, memory-mapped), or else an OSM/GIS source built on the fly.

    The source case imports the builder (osmnx) only when it is needed.
    """
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_CLOEXEC | os.O_NONBLOCK)
    except FileNotFoundError:
        raise ArtifactError(f"no such map file: {p}") from None
    except OSError as exc:
        raise ArtifactError(f"cannot read map file {p}: {exc.strerror}") from exc
    try:
        mode = os.fstat(fd).st_mode
        if stat.S_ISDIR(mode):
            raise ArtifactError(f"cannot read map file {p}: Is a directory")
        head = os.pread(fd, len(MAGIC), 0) if stat.S_ISREG(mode) else b""
        if head[:-1] == MAGIC[:-1]:  # any format version: load_map_fd reports a mismatch
            return load_map_fd(fd, name=str(p))  # the file that was checked, opened once
    except OSError as exc:
        raise ArtifactError(f"cannot read map file {p}: {exc.strerror}") from exc
    finally:
        os.close(fd)
    from graph.build import build_map

    return build_map(p)
