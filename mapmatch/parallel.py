"""Running batch matching over many tracks: local process pool or a Dask cluster, resumable.

Tracks are grouped into partitions. Each partition is matched by one worker (which loads the
map once per process) and written as one file in the parts folder, atomically: JSON lines
``part-NNNNN.json`` for a file output, GeoParquet ``part-NNNNN.parquet`` (the ``tables``
extra) for a folder output; a restarted run skips the partitions already written, so nothing is done
twice and no row is lost or duplicated. The final output (GeoJSON, CSV or GeoParquet file) is
assembled from the parts; when the output is a folder, the parts are the output (partitioned
Parquet, what a Dask run on a cluster writes).

Input partitions: each Parquet file of an input folder is a partition that the worker reads
itself (so a cluster reads partitioned Parquet in parallel); other inputs are read here and cut
into partitions of ``partition_size`` tracks.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from graph.files import atomic_path
from mapmatch.config import BATCH_CONFIG, UBODT_MAX_BYTES, MatchConfig
from mapmatch.errors import MatchError
from mapmatch.extras import require, require_installed
from mapmatch.io import (
    DEFAULT_COLUMNS,
    TABLES,
    Columns,
    ResultRows,
    read_rows_json,
    read_tracks,
    result_rows,
    write_geoparquet,
    write_results,
    write_rows_json,
)
from mapmatch.types import Track

MANIFEST = "_run.json"
ROUTE_TABLE_PREFIX = "_route_table-"
PARQUET_SUFFIXES = (".parquet", ".geoparquet", ".pq")
PART_SUFFIXES = (".json", ".parquet")
"""A partition file's suffix: JSON lines (:func:`mapmatch.io.write_rows_json`) for a file output,
joined at the end; GeoParquet for a folder output, whose parts are the result."""


class RunError(MatchError):
    """A batch run cannot start or finish (bad output path, parts from another run...)."""


@dataclass(frozen=True)
class Partition:
    """One unit of work: either a Parquet file the worker reads, or tracks shipped to it."""

    index: int
    source: str | None = None
    tracks: tuple[Track, ...] = ()
    n_points: int = 0


@dataclass
class RunSummary:
    """What a run did; ``track_summaries`` has one row per track (resumed partitions' too), in
    the order the partitions finished."""

    partitions: int = 0
    skipped: int = 0
    tracks: int = 0
    points: int = 0
    seconds: float = 0.0
    output: str = ""
    parts_dir: str = ""
    failed: list[str] = field(default_factory=list)
    track_summaries: list[TrackSummary] = field(default_factory=list)


@dataclass(frozen=True, slots=True)
class TrackSummary:
    """One matched track: its id, its points and how many of them are unmatched."""

    track_id: str
    points: int
    unmatched: int


@dataclass(frozen=True, slots=True)
class RouteTableSpec:
    """The route table a run's matchers use: none without ``delta``; built with ``delta`` (a
    bound in metres) and ``max_bytes`` (about; ``None``: no limit), or mapped from ``path`` when
    the run built it once for every worker."""

    delta: float | None = None
    max_bytes: int | None = UBODT_MAX_BYTES
    path: str | None = None


@dataclass(frozen=True, slots=True)
class RunOptions:
    """How a run is spread and what it precomputes.

    Attributes
    ----------
    workers : int or None
        Local processes (default: the machine's cores; 1 runs in this process).
    scheduler : str, distributed.Client or None
        ``tcp://host:port`` of a dask.distributed scheduler, or a ``distributed.Client``.
    partition_size : int
        Tracks per partition for non-Parquet inputs.
    ubodt_delta : float or None
        When given, a route table (:class:`mapmatch.route_table.Ubodt`) of this bound in metres
        is precomputed: faster matching for more memory and start-up time. With worker
        processes or Dask, the run builds it once into the parts folder and every worker maps
        that file (one table's memory on a machine, however many workers); in process, it is
        built there.
    ubodt_max_bytes : int or None
        The table's memory budget (about; ``None``: no limit). Where the bound's table would
        not fit, a shorter bound is used; the matches are the same.
    """

    workers: int | None = None
    scheduler: str | Any | None = None
    partition_size: int = 64
    ubodt_delta: float | None = None
    ubodt_max_bytes: int | None = UBODT_MAX_BYTES


# ---------------------------------------------------------------------- worker side
_GRAPHS: dict[tuple[str, int, int], Any] = {}
_MATCHERS: dict[tuple[str, int, int, float, RouteTableSpec], Any] = {}


def _file_key(map_path: str) -> tuple[str, int, int]:
    st = os.stat(map_path)
    return os.path.abspath(map_path), st.st_mtime_ns, st.st_size


def load_run_map(map_path: str) -> Any:
    """The process's road graph for a map file, loaded once (the run's check of the map and
    its in-process matcher share it)."""
    from graph.artifact import load_map

    key = _file_key(map_path)
    g = _GRAPHS.get(key)
    if g is None:
        _GRAPHS.clear()
        g = _GRAPHS[key] = load_map(map_path)
    return g


def _matcher(map_path: str, table: RouteTableSpec, turn_cost: float) -> Any:
    """The process's matcher for a map file and route table (its routes costing ``turn_cost``
    per turn back), made once."""
    from mapmatch.batch import BatchMatcher
    from mapmatch.route_table import Ubodt

    key = (*_file_key(map_path), float(turn_cost), table)
    m = _MATCHERS.get(key)
    if m is None:
        _MATCHERS.clear()
        graph = load_run_map(map_path)
        ubodt = None
        if table.path:
            ubodt = Ubodt.load(table.path)
        elif table.delta:
            ubodt = Ubodt.build(graph, table.delta, turn_cost=turn_cost, max_bytes=table.max_bytes)
        m = _MATCHERS[key] = BatchMatcher(graph, ubodt=ubodt)
    return m


def match_partition(
    map_path: str,
    part: Partition,
    out_file: str,
    config: MatchConfig | None = None,
    columns: Columns = DEFAULT_COLUMNS,
    table: RouteTableSpec = RouteTableSpec(delta=None),
) -> list[TrackSummary]:
    """Match one partition and write its results file atomically; one summary per track."""
    turn_cost = (config or BATCH_CONFIG).batch.route.turn_cost
    matcher = _matcher(map_path, table, turn_cost)
    tracks = list(part.tracks) if part.source is None else read_tracks(part.source, columns=columns)
    results = [matcher.match(t, config) for t in tracks]
    rows = result_rows(results, matcher.graph)
    if out_file.endswith(".json"):
        write_rows_json(out_file, rows)
    else:
        write_geoparquet(out_file, rows)
    return [
        TrackSummary(str(r.track_id), len(r.points), sum(1 for q in r.points if str(q.status) == "unmatched"))
        for r in results
    ]


def part_summaries(part_file: Path) -> list[TrackSummary]:
    """The track summaries of a partition file written by an earlier run (a resumed run)."""
    if part_file.suffix == ".json":
        rows: ResultRows = read_rows_json(part_file)
    else:
        pq = require("pyarrow.parquet", extra=TABLES, needed_for="Parquet parts")
        rows = pq.read_table(part_file, columns=["track_id", "n_points", "n_unmatched"]).to_pylist()
    return [TrackSummary(str(r["track_id"]), int(r["n_points"]), int(r["n_unmatched"])) for r in rows]


# ---------------------------------------------------------------------- planning
def plan_partitions(
    inputs: Sequence[str | os.PathLike[str]], *, columns: Columns = DEFAULT_COLUMNS, partition_size: int = 64
) -> list[Partition]:
    """Partitions of the inputs, in a stable order (the same inputs give the same plan)."""
    parts: list[Partition] = []
    loose: list[Track] = []
    for inp in inputs:
        p = Path(inp)
        if p.is_dir():
            files = sorted(q for q in p.iterdir() if q.name.lower().endswith(PARQUET_SUFFIXES))
            if not files:
                raise RunError(f"{p}: no Parquet files in the folder")
            for q in files:
                parts.append(Partition(index=0, source=str(q), n_points=_parquet_rows(q)))
        else:
            loose.extend(read_tracks(p, columns=columns))
    size = max(int(partition_size), 1)
    for i in range(0, len(loose), size):
        chunk = tuple(loose[i : i + size])
        parts.append(Partition(index=0, tracks=chunk, n_points=sum(len(t) for t in chunk)))
    return [Partition(i, p.source, p.tracks, p.n_points) for i, p in enumerate(parts)]


def _parquet_rows(path: Path) -> int:
    pq = require("pyarrow.parquet", extra=TABLES, needed_for="reading Parquet folders")

    return int(pq.ParquetFile(path).metadata.num_rows)


def _fingerprint(
    inputs: Sequence[str | os.PathLike[str]],
    map_path: str,
    config: MatchConfig | None,
    columns: Columns,
    size: int,
) -> str:
    h = hashlib.sha256()
    for p in [*inputs, map_path]:
        q = Path(p)
        files = sorted(q.iterdir()) if q.is_dir() else [q]
        for f in files:
            st = f.stat()
            h.update(f"{f.resolve()}:{st.st_size}:{st.st_mtime_ns}\n".encode())
    h.update(
        json.dumps([config.to_dict() if config else None, asdict(columns), size], sort_keys=True).encode()
    )
    return h.hexdigest()


def parts_dir_for(out: Path) -> Path:
    """Where the partition files of an output go: the folder itself, or ``OUT.parts/``."""
    return out if _is_dir_output(out) else out.with_name(out.name + ".parts")


def _is_dir_output(out: Path) -> bool:
    return out.is_dir() or not out.suffix


# ---------------------------------------------------------------------- the run
def run_batch(
    inputs: Sequence[str | os.PathLike[str]],
    map_path: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    config: MatchConfig | None = None,
    columns: Columns = DEFAULT_COLUMNS,
    options: RunOptions = RunOptions(),
    progress: Callable[[int, int], None] | None = None,
    on_total: Callable[[int], None] | None = None,
) -> RunSummary:
    """Match every track of ``inputs`` against the map file and write ``out``.

    Parameters
    ----------
    inputs
        Track files (CSV, GPX, Parquet) and folders of Parquet parts.
    map_path
        A map file written by ``mapmatch prep`` (read by every worker; on a cluster it must be
        at the same path on every machine). It is checked before anything is written.
    out
        ``.geojson``, ``.csv``, ``.parquet``/``.geoparquet`` file, or a folder for
        partitioned GeoParquet output.
    options
        Workers, Dask scheduler, partition size and route table (:class:`RunOptions`).
    progress
        Called with ``(points, tracks)`` as partitions finish (after resumed ones).
    on_total
        Called once with the total number of points to match.

    Returns
    -------
    RunSummary
        Counts, and a summary per track (points, unmatched points).
    """
    t0 = time.perf_counter()
    outp = Path(out)
    map_s = str(map_path)
    _check_run(map_s, outp)
    parts = plan_partitions(inputs, columns=columns, partition_size=options.partition_size)
    pdir = parts_dir_for(outp)
    _prepare_parts_dir(pdir, _fingerprint(inputs, map_s, config, columns, options.partition_size), len(parts))
    suffix = PART_SUFFIXES[_is_dir_output(outp)]
    files = [pdir / f"part-{p.index:05d}{suffix}" for p in parts]
    todo = [p for p, f in zip(parts, files, strict=True) if not f.exists()]
    summary = RunSummary(partitions=len(parts), skipped=len(parts) - len(todo), parts_dir=str(pdir))
    for f in files:
        if f.exists():
            summary.track_summaries.extend(part_summaries(f))
    if on_total:
        on_total(sum(p.n_points for p in todo))
    in_process = options.scheduler is None and (options.workers == 1 or len(todo) <= 1)
    table = RouteTableSpec(options.ubodt_delta, options.ubodt_max_bytes)
    if options.ubodt_delta and todo and not in_process:  # built once, mapped by every worker
        turn_cost = (config or BATCH_CONFIG).batch.route.turn_cost
        shared = _shared_route_table(pdir, map_s, table, turn_cost)
        table = RouteTableSpec(table.delta, table.max_bytes, str(shared))
    job = _Job(map_s, config, columns, table)
    done: Iterable[list[TrackSummary]]
    if options.scheduler is not None:
        done = _run_dask(options.scheduler, job, todo, files)
    elif in_process:
        done = (match_partition(map_s, p, str(files[p.index]), config, columns, table) for p in todo)
    else:
        done = _run_pool(options.workers, job, todo, files)
    for rows in done:
        summary.track_summaries.extend(rows)
        summary.tracks += len(rows)
        npts = sum(r.points for r in rows)
        summary.points += npts
        if progress:
            progress(npts, len(rows))
    if table.path is not None:
        shutil.rmtree(table.path, ignore_errors=True)
    if not _is_dir_output(outp):
        _join_parts(outp, files, pdir)
    summary.output = str(outp)
    summary.seconds = time.perf_counter() - t0
    return summary


def _check_run(map_s: str, outp: Path) -> None:
    """Refuse a run before anything is written: the map must load (its CRS too), the output
    must have a known format."""
    from pyproj import CRS

    if not Path(map_s).is_file():
        raise RunError(f"no such map file: {map_s}")
    if not _is_dir_output(outp) and not outp.name.lower().endswith(
        (".geojson", ".json", ".csv", ".parquet", ".geoparquet")
    ):
        raise RunError(f"{outp}: unknown output format (use .geojson, .csv, .parquet or a folder)")
    if _is_dir_output(outp) or outp.name.lower().endswith((".parquet", ".geoparquet")):
        require_installed("pandas", "pyarrow", extra=TABLES, needed_for="GeoParquet output")
    try:
        CRS.from_user_input(load_run_map(map_s).crs)
    except Exception as exc:  # corrupt manifest or arrays, bad CRS, not a map file: one line
        raise RunError(f"map {map_s}: {type(exc).__name__}: {exc}") from None


def _join_parts(outp: Path, files: list[Path], pdir: Path) -> None:
    """The partition files joined into the one output file; the parts folder goes."""
    write_results(outp, [r for f in files for r in read_rows_json(f)])
    shutil.rmtree(pdir, ignore_errors=True)


@dataclass(frozen=True, slots=True)
class _Job:
    """What every partition of a run is matched with."""

    map_path: str
    config: MatchConfig | None
    columns: Columns
    table: RouteTableSpec

    def matching(self) -> tuple[MatchConfig | None, Columns, RouteTableSpec]:
        """:func:`match_partition`'s arguments after the partition's."""
        return self.config, self.columns, self.table


def _shared_route_table(pdir: Path, map_s: str, table: RouteTableSpec, turn_cost: float) -> Path:
    """The run's route table in the parts folder, built once for every worker (each maps the
    same file, so N workers hold one table's memory, not N); kept for a resumed run."""
    from mapmatch.route_table import TABLE_FILE_VERSION, Ubodt

    st = os.stat(map_s)
    key = json.dumps(
        [
            os.path.abspath(map_s),
            st.st_mtime_ns,
            st.st_size,
            table.delta,
            table.max_bytes,
            turn_cost,
            TABLE_FILE_VERSION,
        ]
    )
    folder = pdir / f"{ROUTE_TABLE_PREFIX}{hashlib.sha256(key.encode()).hexdigest()[:16]}"
    for old in pdir.glob(ROUTE_TABLE_PREFIX + "*"):
        if old != folder:
            shutil.rmtree(old, ignore_errors=True)
    if not (folder / "table.json").exists():
        assert table.delta is not None
        Ubodt.build(load_run_map(map_s), table.delta, turn_cost=turn_cost, max_bytes=table.max_bytes).save(
            folder
        )
    return folder


def _prepare_parts_dir(pdir: Path, fingerprint: str, n: int) -> None:
    """Create the parts folder, or check that its parts belong to this same run (else start over)."""
    man = pdir / MANIFEST
    if pdir.is_dir() and man.exists():
        try:
            old = json.loads(man.read_text())
        except (OSError, ValueError):
            old = {}
        if old.get("fingerprint") == fingerprint and old.get("partitions") == n:
            return
        for f in _part_files(pdir):
            f.unlink()
    elif pdir.is_dir() and _part_files(pdir):
        raise RunError(f"{pdir} holds parts of an unknown run; remove them or choose another output")
    pdir.mkdir(parents=True, exist_ok=True)
    with atomic_path(man) as tmp:
        tmp.write_text(json.dumps({"fingerprint": fingerprint, "partitions": n}))


def _part_files(pdir: Path) -> list[Path]:
    return [f for f in pdir.glob("part-*") if f.suffix in PART_SUFFIXES]


def _run_pool(
    workers: int | None, job: _Job, todo: list[Partition], files: list[Path]
) -> Iterable[list[TrackSummary]]:
    import multiprocessing as mp

    n = workers or os.cpu_count() or 1
    ctx = mp.get_context("spawn")  # no fork of a process holding threads
    with ProcessPoolExecutor(max_workers=min(n, len(todo)), mp_context=ctx) as ex:
        futs: list[Future[list[TrackSummary]]] = [
            ex.submit(
                match_partition, job.map_path, p, str(files[p.index]), job.config, job.columns, job.table
            )
            for p in todo
        ]
        for f in as_completed(futs):
            yield f.result()


def _run_dask(
    scheduler: str | Any, job: _Job, todo: list[Partition], files: list[Path]
) -> Iterable[list[TrackSummary]]:
    from distributed import Client
    from distributed import as_completed as dask_completed

    own = isinstance(scheduler, str)
    client: Any = Client(scheduler) if own else scheduler
    try:
        futs = [
            client.submit(
                match_partition,
                job.map_path,
                p,
                str(files[p.index]),
                *job.matching(),
                key=f"mapmatch-part-{p.index}-{id(p)}",
            )
            for p in todo
        ]
        for f in dask_completed(futs):
            yield f.result()
    finally:
        if own:
            client.close()
