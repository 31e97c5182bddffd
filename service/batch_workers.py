"""Batch matching in child processes, off the online process's GIL.

A long ``MatchTrack`` (a 1M-point track takes minutes) would hold the GIL for long stretches
and raise every online stream's latency. :class:`BatchWorkers` runs batch matches in
``processes`` child processes started with the server: each child memory-maps the same map
files read-only (the page cache is shared), builds its batch matchers and warms them up
before the first request. The server passes the request bytes through and gets the answer
bytes back (serialised in the child), so the online process neither parses the answer nor
builds it.

* Map files: the server opened each map file once and keeps its descriptor; every child
  gets that descriptor (passed over its pipe, ``SCM_RIGHTS``), never the file's name, so
  a file replaced on disk (a map prepared again over it) changes nothing: a restarted child
  maps the version the server loaded.
* Map replacement: every job names the map's id and checksum and carries its descriptor; a
  child loads a map it does not hold (or holds in another version), and
  :meth:`BatchWorkers.set_maps` tells idle children to load new maps and drop unloaded
  ones. A child that cannot load a map (its file changed in place) reports it: the map is
  in :attr:`BatchWorkers.failed` and ``on_failed`` is called (the server's health then says
  NOT_SERVING for that map), and MatchTrack on it answers FAILED_PRECONDITION.
* A child that dies (killed, out of memory) fails its call with UNAVAILABLE naming the
  cause, and a new child starts. A call the client abandons (cancelled, deadline passed)
  stops its child, which restarts: no work goes on for nobody.
* The children run in a lower CPU class: ``SCHED_IDLE`` by default (``sched="idle"``), so
  they get a core only when no other task of the server's wants it, and a waking online
  thread takes the core from them at once; ``"idle-session"`` also keeps their CPU time out
  of the server's share of a host busy with other work (see :func:`lower_cpu_class`); with
  ``"normal"`` (or where ``SCHED_IDLE`` is missing) they are time-shared at a higher
  ``nice``. They are also the kernel's first choice when memory runs out
  (``oom_score_adj`` 1000), not the server.
* :meth:`BatchWorkers.stop` ends the children (SIGTERM, then SIGKILL); queued calls get
  UNAVAILABLE. A child also ends when the server process is gone, however it ended (the
  kernel's parent-death signal, :func:`service.children.die_with_parent`).

Maps without a file (built in memory, or from an OSM/GIS source) are matched on the
server's batch threads as before.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import queue
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from multiprocessing.connection import Connection
from multiprocessing.reduction import recv_handle, send_handle
from typing import Any, NamedTuple

import grpc

from graph.files import ReadOnlyFile
from mapmatch.config import BATCH_CONFIG, MatchConfig
from mapmatch.errors import ValidationError
from service.children import die_with_parent
from service.errors import BatchWorkerError, LimitError, StatusError, log_internal, status_for
from service.gen import mapmatch_pb2 as pb

log = logging.getLogger("mapmatch.service")

__all__ = [
    "POINT_ANSWER_BYTES",
    "BatchWorkers",
    "MapFile",
    "RequestPeek",
    "TrackLimits",
    "check_answer_bytes",
    "check_point_count",
    "check_points",
    "match_track",
    "peek_track_request",
]


@dataclass(frozen=True)
class MapFile:
    """A loaded map as a child process finds it: id, file name (for messages), checksum,
    and the open descriptor it is read from (None: the one :meth:`BatchWorkers.set_maps`
    gave for that id and checksum)."""

    map_id: str
    path: str
    checksum: str
    file: ReadOnlyFile | None = field(default=None, compare=False, repr=False)

    def wire(self) -> MapFile:
        """This record as it is pickled to a child (the descriptor goes beside it)."""
        return replace(self, file=None)


@dataclass(frozen=True)
class TrackLimits:
    """The per-track limits a batch match obeys (points in, bytes out)."""

    max_track_points: int
    max_answer_bytes: int


# ---------------------------------------------------------------------------------- matching
class RequestPeek(NamedTuple):
    """What the server needs of a serialised ``MatchTrackRequest`` before handing it on."""

    map_id: str
    has_track: bool
    points: int | None  # None: not counted here (the worker checks the limit)


PEEK_FIELDS = 64  # wire fields a peek reads at most (per message level) before giving up


def _varint(data: bytes, i: int, end: int) -> tuple[int, int]:
    out = shift = 0
    while i < end and shift < 64:
        b = data[i]
        i += 1
        out |= (b & 0x7F) << shift
        if b < 0x80:
            return out, i
        shift += 7
    raise ValueError("bad varint")


def _fields(data: bytes, start: int, end: int) -> list[tuple[int, int, int, int]] | None:
    """``(field, wire type, value start, value end)`` of one message level, its values
    skipped unread; None past :data:`PEEK_FIELDS` fields or on a wire type a peek leaves
    to the full parser (groups, bad bytes)."""
    out: list[tuple[int, int, int, int]] = []
    i = start
    while i < end:
        if len(out) >= PEEK_FIELDS:
            return None
        key, i = _varint(data, i, end)
        field, wire = key >> 3, key & 7
        if wire == 0:
            _, j = _varint(data, i, end)
        elif wire == 1:
            j = i + 8
        elif wire == 2:
            n, i = _varint(data, i, end)
            j = i + n
        elif wire == 5:
            j = i + 4
        else:
            return None
        if field == 0 or j > end:
            return None
        out.append((field, wire, i, j))
        i = j
    return out


def peek_track_request(data: bytes) -> RequestPeek | None:
    """The map id, the presence of the track and its point count of a serialised
    ``MatchTrackRequest``, read from the wire format without parsing the track's arrays:
    O(1) work on the event loop for a request of any size.

    None when the bytes are anything but the plain encoding (then the full parser decides,
    with its own error for bad bytes); ``points`` None when the track's fields are not all
    packed (the worker's parse then checks the limit).
    """
    try:
        top = _fields(data, 0, len(data))
        if top is None:
            return None
        map_id, tracks = b"", []
        for field, wire, a, b in top:
            if field == 1 and wire == 2:
                map_id = data[a:b]  # a repeated scalar: the last one counts
            elif field == 2 and wire == 2:
                tracks.append((a, b))  # repeated message fields merge
            elif field in (1, 2):
                return None
        name = map_id.decode("utf-8")
        counts = [0] * 9
        for a, b in tracks:
            inner = _fields(data, a, b)
            if inner is None:
                return RequestPeek(name, True, None)
            for field, wire, x, y in inner:
                if 2 <= field <= 8 and wire == 2:  # packed doubles
                    if (y - x) % 8:
                        return None
                    counts[field] += (y - x) // 8
                elif 2 <= field <= 8 and wire == 1:
                    counts[field] += 1
                elif field == 1 and wire == 2:
                    data[x:y].decode("utf-8")
                elif field <= 8:
                    return None
        # as check_points counts: the longest of time, lat and lon
        return RequestPeek(name, bool(tracks), max(counts[2], counts[3], counts[4]))
    except (ValueError, UnicodeDecodeError):
        return None


def _point_answer_bytes() -> int:
    """The most bytes one point adds to a ``TrackResult`` (its ``MatchedPoint`` at the widest
    values, with the repeated field's tag and length)."""
    widest = pb.MatchedPoint(
        index=2**31 - 1, status=pb.POINT_STATUS_UNMATCHED, edge=-1, offset=1.0, lat=1.0, lon=1.0, dist=1.0
    )
    return widest.ByteSize() + 2


# a fact of the wire format, not a setting: an answer holds at least this many bytes a point
POINT_ANSWER_BYTES = _point_answer_bytes()


def check_points(msg: pb.Track, limits: TrackLimits) -> None:
    """:func:`check_point_count` for a track message."""
    check_point_count(max(len(msg.lat), len(msg.lon), len(msg.time)), limits)


def check_point_count(n: int, limits: TrackLimits) -> None:
    """Before any work: :class:`LimitError` naming ``max_track_points`` when ``n`` points are
    over it, or ``max_answer_bytes`` when their points alone (:data:`POINT_ANSWER_BYTES` each)
    cannot fit in an answer."""
    if n > limits.max_track_points:
        most = limits.max_track_points
        raise LimitError("max_track_points", f"a track has {n} points, over the server's limit of {most}")
    if n * POINT_ANSWER_BYTES > limits.max_answer_bytes:
        most = limits.max_answer_bytes // POINT_ANSWER_BYTES
        raise LimitError(
            "max_answer_bytes",
            f"the answer to a track of {n} points would be at least {n * POINT_ANSWER_BYTES} bytes, "
            f"over the server's limit of {limits.max_answer_bytes}; send at most {most} points a track",
        )


def check_answer_bytes(n: int, limit: int) -> None:
    """:class:`LimitError` naming ``max_answer_bytes`` when an ``n``-byte answer is over ``limit``."""
    if n > limit:
        raise LimitError(
            "max_answer_bytes",
            f"the answer would be {n} bytes, over the server's limit of {limit}; "
            "send fewer fixes or points per message",
        )


def match_track(entry: Any, msg: pb.Track, *, prefix: str, limits: TrackLimits) -> pb.TrackResult:
    """One track through a map entry's batch matcher, as a ``TrackResult`` (limits checked)."""
    from service import convert

    check_points(msg, limits)
    track = convert.track_from_proto(msg, prefix=prefix)
    try:
        m = entry.batch.match(track)
    except ValidationError as exc:
        raise ValidationError(f"{prefix}.{exc.field}", exc.reason) from None
    out = convert.track_match_to_proto(m, entry.graph)
    check_answer_bytes(out.ByteSize(), limits.max_answer_bytes)
    return out


# ---------------------------------------------------------------------------------- server side
@dataclass
class _Job:
    loop: asyncio.AbstractEventLoop
    fut: asyncio.Future[bytes]
    header: tuple[Any, ...]
    data: bytes
    deadline: float = math.inf
    """``time.monotonic()`` by which the call must be answered (inf: no deadline)."""


PREPARING = (
    "the batch worker is still preparing its maps (on a machine's first run it compiles the batch "
    "kernels, once, about a minute); retry"
)
PREPARING_MARGIN = 0.5
"""Seconds before a call's deadline at which a call still waiting for a preparing child is
answered UNAVAILABLE (so the answer arrives before the deadline)."""


class _Stop(NamedTuple):
    """A call ended before its answer: ``result`` is what to deliver (None: nothing)."""

    result: BaseException | None


class _Slot:
    """One child process and the thread that feeds it."""

    def __init__(self, index: int) -> None:
        self.index = index
        self.proc: Any = None
        self.conn: Connection | None = None
        self.generation = -1
        self.thread: threading.Thread | None = None
        self.loading = 0  # map loads the child has not yet said "ready" for


class BatchWorkers:
    """``processes`` child processes matching tracks; see the module docstring.

    Parameters
    ----------
    processes
        Child processes (each matches one track at a time).
    limits
        Points per track and bytes per answer.
    nice
        Added to the children's nice value (lower CPU priority than the online process).
    sched
        The children's CPU class: ``"idle"``, ``"idle-session"`` or ``"normal"``
        (:func:`lower_cpu_class`).
    """

    def __init__(
        self,
        *,
        processes: int,
        limits: TrackLimits,
        nice: int = 10,
        sched: str = "idle",
        match_config: MatchConfig = BATCH_CONFIG,
    ) -> None:
        import multiprocessing as mp

        self.limits = limits
        self.match_config = match_config
        self.nice = nice
        self.sched = sched
        self._ctx = mp.get_context("spawn")
        self._q: queue.SimpleQueue[_Job | None] = queue.SimpleQueue()
        self._slots = [_Slot(i) for i in range(processes)]
        self._files: tuple[MapFile, ...] = ()
        self._handles: dict[tuple[str, str], ReadOnlyFile] = {}  # this and the last set_maps
        self._last: set[tuple[str, str]] = set()
        self._generation = 0
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._warm = threading.Event()  # a child has loaded and warmed its maps
        self._started = False
        self.restarts = 0
        self.failed: dict[str, str] = {}  # maps a child could not load: id -> why
        self.on_failed: Callable[[dict[str, str]], None] = lambda failed: None
        self.on_warm: Callable[[], None] = lambda: None  # the first child is warm

    # ------------------------------------------------------------------ control
    def set_maps(self, files: list[MapFile]) -> None:
        """The maps now served, each with its open descriptor (children load new ones and
        drop others when idle)."""
        with self._lock:
            self._files = tuple(f for f in files if f.file is not None)
            now = {(f.map_id, f.checksum): f.file for f in self._files if f.file is not None}
            last = {k: v for k, v in self._handles.items() if k in self._last}
            self._last = set(now)
            self._handles = {**last, **now}  # a call that named the last version still finds it
            self._generation += 1
            gone = [k for k in self.failed if k not in {f.map_id for f in self._files}]
            for k in gone:
                del self.failed[k]

    def _file_of(self, mf: MapFile) -> ReadOnlyFile | None:
        if mf.file is not None:
            return mf.file
        with self._lock:
            return self._handles.get((mf.map_id, mf.checksum))

    def _note(self, loaded: list[str], failed: dict[str, str]) -> None:
        """A child's report of its map loads: :attr:`failed` and ``on_failed`` follow."""
        with self._lock:
            was = dict(self.failed)
            for map_id in loaded:
                self.failed.pop(map_id, None)
            self.failed.update(failed)
            now = dict(self.failed)
        if now != was:
            for map_id, why in failed.items():
                log.error("batch worker cannot load map %s: %s", map_id, why)
            self.on_failed(now)

    def start(self) -> None:
        """Start the children (once); each loads and warms the maps of :meth:`set_maps`."""
        with self._lock:
            if self._started or self._stopping.is_set():
                return
            self._started = True
        for slot in self._slots:
            slot.thread = threading.Thread(
                target=self._run, args=(slot,), name=f"mapmatch-batch-feed-{slot.index}", daemon=True
            )
            slot.thread.start()

    def _set_warm(self) -> None:
        if not self._warm.is_set():
            self._warm.set()
            self.on_warm()

    @property
    def started(self) -> bool:
        """Whether the children have been started (by the first map with a file)."""
        return self._started

    @property
    def warm(self) -> bool:
        """Whether a child has loaded and warmed up its maps (a call is answered at once)."""
        return self._warm.is_set()

    def wait_warm(self, timeout: float) -> bool:
        """Block until a child has loaded and warmed up the maps of :meth:`set_maps` (so a
        call can be answered without waiting for a start-up); False after ``timeout`` s."""
        return self._warm.wait(timeout)

    def pids(self) -> list[int]:
        """The children's process ids (those running)."""
        return [s.proc.pid for s in self._slots if s.proc is not None and s.proc.is_alive()]

    def stop(self, timeout: float = 5.0) -> None:
        """End the children; queued and running calls get UNAVAILABLE."""
        self._stopping.set()
        for _ in self._slots:
            self._q.put(None)
        for slot in self._slots:
            self._end_child(slot)
        for slot in self._slots:
            if slot.thread is not None:
                slot.thread.join(timeout)
        while True:  # calls still queued
            try:
                job = self._q.get_nowait()
            except queue.Empty:
                break
            if job is not None:
                _deliver(job, BatchWorkerError("the server is shutting down; retry on another server"))

    # ------------------------------------------------------------------ calls
    async def match(
        self, map_file: MapFile, data: bytes, *, kind: str, prefix: str, time_left: float | None = None
    ) -> bytes:
        """Match in a child: ``data`` is a serialised ``MatchTrackRequest`` (``kind`` "request")
        or ``Track`` (``kind`` "track"); returns a serialised ``TrackResult``. With
        ``time_left`` (the call's seconds to its deadline), a call that would wait past it for a
        child still preparing its maps (on a machine's first run, compiling the batch kernels) is
        answered UNAVAILABLE just before it, not left to expire.

        Raises
        ------
        StatusError
            The child's answer was an error (its status, field and message), or the child
            ended (UNAVAILABLE).
        """
        if self._stopping.is_set():
            raise BatchWorkerError("the server is shutting down; retry on another server")
        if not self._started:
            self.start()
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[bytes] = loop.create_future()
        deadline = math.inf if time_left is None else time.monotonic() + time_left - PREPARING_MARGIN
        self._q.put(_Job(loop, fut, ("match", kind, map_file, prefix), data, deadline))
        return await fut  # cancelled with the call: the feeding thread then stops the child

    # ------------------------------------------------------------------ feeding threads
    def _run(self, slot: _Slot) -> None:
        while not self._stopping.is_set():
            try:
                self._ensure_child(slot)
            except Exception as exc:  # cannot start a process: wait, try again
                log.error("cannot start a batch worker process: %s", exc)
                time.sleep(1.0)
                continue
            if slot.loading and not self._take_ready(slot):
                continue  # still loading: no job yet (another child may be ready for it)
            try:
                job = self._q.get(timeout=0.5)
            except queue.Empty:
                self._drain_ready(slot)  # map loads reported while idle: health knows at once
                continue
            if job is None:
                return
            if job.fut.cancelled():
                continue
            try:
                self._ensure_child(slot)
                result = self._call(slot, job)
            except Exception as exc:
                result = exc
            if result is not None:
                _deliver(job, result)

    def _drain_ready(self, slot: _Slot) -> None:
        """Read the child's map-load reports that have arrived (it is idle: nothing else comes)."""
        conn = slot.conn
        if conn is None:
            return
        with contextlib.suppress(EOFError, OSError):
            while slot.loading and conn.poll(0):
                msg = conn.recv()
                if msg[0] == "ready":
                    slot.loading -= 1
                    self._note(msg[1], msg[2])

    def _ensure_child(self, slot: _Slot) -> None:
        if slot.proc is not None and not slot.proc.is_alive():
            self._end_child(slot)
        with self._lock:
            files, generation = self._files, self._generation
        if slot.proc is None:
            if self._stopping.is_set():
                raise BatchWorkerError("the server is shutting down; retry on another server")
            parent, child = self._ctx.Pipe(duplex=True)
            proc = self._ctx.Process(
                target=worker_main,
                args=(child, self.limits, os.getpid(), self.nice, self.sched, self.match_config),
                name=f"mapmatch-batch-{slot.index}",
                daemon=True,
            )
            proc.start()
            child.close()
            slot.proc, slot.conn, slot.generation, slot.loading = proc, parent, -1, 1
            log.info("batch worker %d started (pid %d, %d map(s))", slot.index, proc.pid, len(files))
        if slot.generation != generation:
            assert slot.conn is not None and slot.proc is not None
            slot.generation = generation
            slot.loading += 1
            _send_maps(slot.conn, files, slot.proc.pid)

    def _take_ready(self, slot: _Slot) -> bool:
        """Read a loading child's "ready" when it has come (waiting up to 0.2 s); True when
        the child has loaded everything it was told to."""
        conn = slot.conn
        if conn is None:
            return False
        with contextlib.suppress(EOFError, OSError):  # a child that died: restarted next round
            if conn.poll(0.2):
                msg = conn.recv()
                if msg[0] == "ready":
                    slot.loading -= 1
                    self._note(msg[1], msg[2])
        if not slot.loading:
            self._set_warm()
        return not slot.loading

    def _call(self, slot: _Slot, job: _Job) -> bytes | BaseException | None:
        conn, proc = slot.conn, slot.proc
        assert conn is not None and proc is not None
        try:
            # a child loading (and warming) its maps reads nothing: a track sent now would block
            # this thread, deaf to the call being abandoned, until the load ends
            while slot.loading:
                stop = self._wait(slot, job, working=False)
                if stop is not None:
                    return stop.result
                msg = conn.recv()
                if msg[0] == "ready":
                    slot.loading -= 1
                    self._note(msg[1], msg[2])
            self._set_warm()
            _, kind, mf, prefix = job.header
            file = self._file_of(mf)
            if file is None or file.closed:
                return BatchWorkerError(f"map {mf.map_id!r} was replaced during this call; retry")
            conn.send(("match", kind, mf.wire(), prefix))
            send_handle(conn, file.fileno(), proc.pid)
            conn.send_bytes(job.data)
            stop = self._wait(slot, job, working=True)
            if stop is not None:
                return stop.result
            status, info = conn.recv()
            if status == "ok":
                return recv_raw(conn, info)
            code, fld, text = info
            if code == "FAILED_PRECONDITION" and fld == "map_id":  # the child cannot load the map
                self._note([], {mf.map_id: text})
            return StatusError(grpc.StatusCode[code], fld, text)
        except (EOFError, OSError):
            if self._stopping.is_set():
                self._end_child(slot)
                return BatchWorkerError("the server is shutting down; retry on another server")
            proc.join(2.0)
            why = _exit_reason(proc.exitcode)
            self._end_child(slot)
            self.restarts += 1
            log.error("batch worker %d ended during a match (%s); starting another", slot.index, why)
            return BatchWorkerError(
                f"the batch worker process ended during this match ({why}); a new one is starting, "
                "retry (a track this large may need more memory than the server has)"
            )

    def _wait(self, slot: _Slot, job: _Job, *, working: bool) -> _Stop | None:
        """Wait for the child's next message; a :class:`_Stop` when the call was abandoned (a
        child ``working`` on it is restarted; one still loading its maps goes on) or the server
        is stopping."""
        conn, proc = slot.conn, slot.proc
        assert conn is not None and proc is not None
        while not conn.poll(0.2):
            if not working and time.monotonic() >= job.deadline:
                return _Stop(StatusError(grpc.StatusCode.UNAVAILABLE, "", PREPARING))
            if job.fut.cancelled():  # the client gave up
                if working:  # stop the work
                    log.info("batch worker %d: call abandoned, restarting the worker", slot.index)
                    self._end_child(slot)
                return _Stop(None)
            if self._stopping.is_set():
                self._end_child(slot)
                return _Stop(BatchWorkerError("the server is shutting down; retry on another server"))
            if not proc.is_alive():
                raise EOFError
        return None

    def _end_child(self, slot: _Slot) -> None:
        proc, conn = slot.proc, slot.conn
        slot.proc, slot.conn = None, None
        if conn is not None:
            with contextlib.suppress(OSError):
                conn.close()
        if proc is None:
            return
        if proc.is_alive():
            proc.terminate()
            proc.join(2.0)
            if proc.is_alive():
                proc.kill()
        proc.join(2.0)


def _send_maps(conn: Connection, files: tuple[MapFile, ...], pid: int) -> None:
    """Tell a child the maps now served: their records, then one descriptor each."""
    conn.send(("maps", tuple(f.wire() for f in files)))
    for f in files:
        assert f.file is not None
        send_handle(conn, f.file.fileno(), pid)


def send_raw(conn: Connection, data: bytes) -> None:
    """Write ``data`` on the connection's descriptor as it is (no message frame): the reader
    knows its length from the message before it (:func:`recv_raw`)."""
    try:
        sock = socket.socket(fileno=os.dup(conn.fileno()))
    except OSError:  # not a socket: plain writes
        view = memoryview(data)
        while view:
            view = view[os.write(conn.fileno(), view) :]
        return
    with sock:
        sock.sendall(data)


def _read_exactly(fd: int, n: int) -> bytes:
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    while got < n:
        k = os.readv(fd, [view[got:]])
        if k == 0:
            raise EOFError
        got += k
    return bytes(buf)


def recv_raw(conn: Connection, n: int) -> bytes:
    """The ``n`` bytes :func:`send_raw` wrote. On a socket (a duplex pipe on Unix) one
    ``recv(MSG_WAITALL)`` fills a new bytes object with the GIL released; multiprocessing's
    ``recv_bytes`` read a 50 MB answer in pipe-sized pieces, each into a fresh ``n``-byte
    buffer, then copied them twice, holding the GIL (the event loop) for tens of ms."""
    parts: list[bytes] = []
    got = 0
    try:
        sock = socket.socket(fileno=os.dup(conn.fileno()))
    except OSError:  # not a socket: plain reads
        return _read_exactly(conn.fileno(), n)
    with sock:
        while got < n:
            chunk = sock.recv(n - got, socket.MSG_WAITALL)
            if not chunk:
                raise EOFError
            parts.append(chunk)
            got += len(chunk)
    return parts[0] if len(parts) == 1 else b"".join(parts)


def _deliver(job: _Job, result: bytes | BaseException) -> None:
    def done() -> None:
        if job.fut.cancelled():
            return
        if isinstance(result, BaseException):
            job.fut.set_exception(result)
        else:
            job.fut.set_result(result)

    with contextlib.suppress(RuntimeError):  # the loop has closed
        job.loop.call_soon_threadsafe(done)


def _exit_reason(code: int | None) -> str:
    if code is None:
        return "it stopped answering"
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        return f"killed by {name}" + (", perhaps out of memory" if -code == signal.SIGKILL else "")
    return f"exit status {code}"


# ---------------------------------------------------------------------------------- child side
def _load(mf: MapFile, fd: int, config: MatchConfig) -> Any:
    """A map entry (graph, index, batch matcher warmed up) from the map's open descriptor,
    checksum checked."""
    from graph.artifact import load_map_fd
    from graph.index import EdgeIndex
    from service.maps import MapEntry, graph_checksum, warm_batch

    try:
        graph = load_map_fd(fd, name=os.path.basename(mf.path))
    except Exception:
        graph = None
    if graph is None or graph_checksum(graph) != mf.checksum:
        raise StatusError(
            grpc.StatusCode.FAILED_PRECONDITION,
            "map_id",
            f"map_id: the file of map {mf.map_id!r} was changed in place since the server loaded it; "
            "load it again",
        )
    entry = MapEntry(
        map_id=mf.map_id,
        graph=graph,
        source="",
        checksum=mf.checksum,
        index=EdgeIndex(graph),
        online=None,
        batch_config=config,
    )
    warm_batch(entry, compile=True)  # a child compiles the kernels before it says "ready"
    return entry


def _refresh(
    held: dict[str, Any], files: tuple[MapFile, ...], fds: list[int], config: MatchConfig
) -> tuple[list[str], dict[str, str]]:
    """Hold the maps of ``files`` (read from ``fds``, closed here); returns the ids loaded
    and the failures (id -> why)."""
    keep = {(f.map_id, f.checksum) for f in files}
    for map_id in [k for k, e in held.items() if (k, e.checksum) not in keep]:
        del held[map_id]
    loaded: list[str] = []
    failed: dict[str, str] = {}
    for f, fd in zip(files, fds, strict=True):
        try:
            if f.map_id not in held:
                held[f.map_id] = _load(f, fd, config)
            loaded.append(f.map_id)
        except Exception as exc:  # reported to the server (health) and by calls that need it
            failed[f.map_id] = str(exc)
        finally:
            os.close(fd)
    return loaded, failed


def _run_job(
    held: dict[str, Any],
    header: tuple[Any, ...],
    fd: int,
    data: bytes,
    limits: TrackLimits,
    config: MatchConfig,
) -> bytes:
    _, kind, mf, prefix = header
    entry = held.get(mf.map_id)
    try:
        if entry is None or entry.checksum != mf.checksum:
            entry = held[mf.map_id] = _load(mf, fd, config)
    finally:
        os.close(fd)
    try:
        parse = pb.MatchTrackRequest.FromString if kind == "request" else pb.Track.FromString
        msg = parse(data)
        if isinstance(msg, pb.MatchTrackRequest):
            msg = msg.track
    except Exception as exc:
        raise ValidationError(
            "request", f"the message does not decode as the method's request type ({type(exc).__name__})"
        ) from None
    out = match_track(entry, msg, prefix=prefix, limits=limits).SerializeToString()
    return out


def _watch_parent(parent: int) -> None:  # where the kernel has no parent-death signal
    while True:
        time.sleep(1.0)
        if os.getppid() != parent:
            os._exit(0)


def lower_cpu_class(*, nice: int, sched: str) -> None:
    """Put the calling process in the batch workers' CPU class (see :class:`BatchWorkers`).

    ``"idle"``: ``SCHED_IDLE``: a waking thread of the server takes the core at once.
    ``"idle-session"``: also a session of its own, which Linux's autogroup scheduling (on in
    many kernels, for processes outside a cgroup of their own) puts in a group of its own,
    at ``nice``: an idle-class process in the server's group still counts against that
    group's share of a host busy with other sessions (a waking online thread then waited
    for the next tick, about 6 ms per wake-up, measured), while in a group of its own the
    batch work gets only what the other groups leave. Steps the host does not allow are
    skipped (``nice`` still applies).
    """
    if nice:
        with contextlib.suppress(OSError):
            os.nice(nice)
    if sched == "idle-session":
        with contextlib.suppress(OSError):
            os.setsid()
        with contextlib.suppress(OSError), open("/proc/self/autogroup", "w") as f:
            f.write(str(nice))
    if sched in ("idle", "idle-session") and hasattr(os, "SCHED_IDLE"):
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))


def worker_main(
    conn: Connection,
    limits: TrackLimits,
    parent: int,
    nice: int = 0,
    sched: str = "normal",
    config: MatchConfig = BATCH_CONFIG,
) -> None:
    """A child process: load the maps it is sent (each with its descriptor), then answer
    jobs until the pipe closes; it dies with the server process ``parent``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the server's to handle
    die_with_parent(parent)
    lower_cpu_class(nice=nice, sched=sched)
    # when memory runs out, the kernel ends this process (its call fails UNAVAILABLE, a new
    # worker starts), not the server
    with contextlib.suppress(OSError), open("/proc/self/oom_score_adj", "w") as f:
        f.write("1000")
    logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()
    held: dict[str, Any] = {}
    with contextlib.suppress(EOFError, OSError):
        conn.send(("ready", [], {}))
    while True:
        try:
            header = conn.recv()
            if header[0] == "maps":
                fds = [recv_handle(conn) for _ in header[1]]
                loaded, failed = _refresh(held, header[1], fds, config)
                conn.send(("ready", loaded, failed))
                continue
            fd = recv_handle(conn)
            data = conn.recv_bytes()
        except (EOFError, OSError):
            return
        try:
            out = _run_job(held, header, fd, data, limits, config)
        except Exception as exc:
            code, fld, msg = status_for(exc)
            if code is grpc.StatusCode.INTERNAL:
                log_internal(exc, "batch worker")
            reply: tuple[Any, ...] = ("error", (code.name, fld, msg))
        else:
            reply = ("ok", len(out))
        del data
        try:
            conn.send(reply)
            if reply[0] == "ok":
                send_raw(conn, out)
        except (EOFError, OSError):
            return
