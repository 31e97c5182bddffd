"""The ``mapmatch.v1.MapMatch`` servicer: validate, convert, call ``mapmatch``, convert back.

No matching logic lives here. A single fix (``StreamFixes``, ``SnapFix``) is matched on the
event loop (``inline_fixes``, the default): it is short, bounded work, and a hop to another
thread and back cost more CPU than the fix itself saves, all under one GIL. ``FixBatch``
slices run on the online thread(s) (``online_workers``); batch matching on a map loaded from
a map file runs in batch worker processes (``batch_processes``,
:mod:`service.batch_workers`), off this process's GIL; other batch matching and map
loads on the batch pool (``workers``), so no long work holds the loop. A vehicle's fixes never race (each
session has a lock); a ``FixBatch`` is matched in slices of ``batch_slice`` fixes, so other
streams' fixes are served in between. Every message's work is bounded by the configured
limits (fixes per batch, points per track, bytes per answer), each refused with
RESOURCE_EXHAUSTED naming the limit. Exceptions propagate to
:class:`service.interceptors.StatusInterceptor`, which maps them to statuses; in the live
streams a bad fix, or a message whose bytes do not decode, is answered with an ``error`` and
the stream goes on. ``ImportSession`` decodes its blob off the event loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import math
import os
import queue
import socket
import threading
from collections.abc import AsyncIterator, Callable, Sequence
from concurrent.futures import Executor
from typing import TYPE_CHECKING, Any, TypeVar

import grpc
from grpc import aio

from mapmatch.errors import ValidationError
from mapmatch.types import State
from service import convert
from service.auth import CALLER, Identity, Quotas, check_vehicle
from service.batch_workers import (
    BatchWorkers,
    MapFile,
    TrackLimits,
    check_answer_bytes,
    check_point_count,
    check_points,
    match_track,
    peek_track_request,
)
from service.config import ServerConfig
from service.errors import LimitError, MapPathError, log_internal, status_for
from service.gen import mapmatch_pb2 as pb
from service.gen import mapmatch_pb2_grpc as pb_grpc
from service.interceptors import Undecodable, undecodable_error
from service.maps import LoadLimits, MapEntry, MapRegistry, resolve_map_path
from service.sessions import SessionStore

if TYPE_CHECKING:
    from service.store_checkpoints import Checkpointer

T = TypeVar("T")
SERVICE_NAME = pb.DESCRIPTOR.services_by_name["MapMatch"].full_name


def _prefixed(exc: ValidationError, prefix: str) -> ValidationError:
    return ValidationError(f"{prefix}.{exc.field}", exc.reason)


class OnlineQueue:
    """Online updates on their own thread(s), off the event loop.

    Jobs from every stream go into one FIFO queue, so a stream's slice waits behind the fixes
    other streams sent before it. A worker takes every job waiting (up to ``drain``) at once
    and hands the answers back to the loop in one call, so at high rates the threads wake
    each other once per group of fixes, not once per fix.
    """

    def __init__(self, *, workers: int = 1, drain: int = 256, name: str = "mapmatch-online") -> None:
        self._q: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._drain = drain
        self._threads = [
            threading.Thread(target=self._run, name=f"{name}-{i}", daemon=True) for i in range(workers)
        ]
        self._started = False
        self._lock = threading.Lock()

    def start(self) -> None:
        """Start the worker threads (once)."""
        with self._lock:
            if not self._started:
                self._started = True
                for t in self._threads:
                    t.start()

    def submit(self, fn: Callable[[], T]) -> asyncio.Future[T]:
        """Run ``fn`` on a worker; the future resolves on the calling event loop."""
        if not self._started:
            self.start()
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[T] = loop.create_future()
        self._q.put((loop, fut, fn))
        return fut

    def shutdown(self) -> None:
        if not self._started:
            return
        for _ in self._threads:
            self._q.put(None)

    def _run(self) -> None:
        while True:
            job = self._q.get()
            jobs = [job]
            while job is not None and len(jobs) < self._drain:
                try:
                    job = self._q.get_nowait()
                except queue.Empty:
                    break
                jobs.append(job)
            done: dict[Any, list[tuple[Any, Any, BaseException | None]]] = {}
            stop = False
            for j in jobs:
                if j is None:
                    stop = True
                    continue
                loop, fut, fn = j
                try:
                    done.setdefault(loop, []).append((fut, fn(), None))
                except BaseException as exc:  # handed to the awaiting coroutine
                    done.setdefault(loop, []).append((fut, None, exc))
            for loop, results in done.items():
                with contextlib.suppress(RuntimeError):  # the loop has closed
                    loop.call_soon_threadsafe(_deliver, results)
            if stop:
                return


def _deliver(results: list[tuple[asyncio.Future[Any], Any, BaseException | None]]) -> None:
    for fut, value, exc in results:
        if fut.cancelled():
            continue
        if exc is not None:
            fut.set_exception(exc)
        else:
            fut.set_result(value)


def load_limits(config: ServerConfig) -> LoadLimits:
    """The map-load limits of a server configuration."""
    return LoadLimits(
        max_bytes=config.max_map_bytes, timeout=config.load_timeout, memory_bytes=config.load_memory_bytes
    )


class MapMatchServicer(pb_grpc.MapMatchServicer):
    """Serves the API over a map registry and a session store.

    ``checkpoints`` (set by the server with ``--session-store``) brings unknown vehicles'
    sessions from the store before their fixes and hands a stream's vehicles over when it ends.

    Parameters
    ----------
    maps
        Loaded maps.
    sessions
        Per-vehicle sessions.
    executor
        Thread pool for batch matching and map loads.
    online
        Where online updates run (one thread of their own by default).
    batch_workers
        Child processes for batch matches on maps with a file (None: the ``executor`` threads).
    config
        Limits (``max_*``), ``batch_slice``, ``max_time_jump`` and ``map_dir``.
    on_maps_changed
        Called (on the event loop) after a map is loaded or unloaded; the server updates health.
    """

    def __init__(
        self,
        *,
        maps: MapRegistry,
        sessions: SessionStore,
        executor: Executor,
        online: OnlineQueue | None = None,
        batch_workers: BatchWorkers | None = None,
        config: ServerConfig | None = None,
        on_maps_changed: Callable[[], Any] | None = None,
    ) -> None:
        self.maps = maps
        self.sessions = sessions
        self.executor = executor
        self.online = online or OnlineQueue()
        self.batch_workers = batch_workers
        self.config = config or ServerConfig()
        self.track_limits = TrackLimits(
            max_track_points=self.config.max_track_points, max_answer_bytes=self.config.max_answer_bytes
        )
        self.on_maps_changed = on_maps_changed
        self._short_id = self.config.max_vehicle_id // 4  # ids this long or shorter fit in any case
        self.server_id = f"{socket.gethostname()}:{os.getpid()}"
        self.checkpoints: Checkpointer | None = None
        self.quotas: Quotas | None = None  # per-identity session quotas (set by the server)

    async def _offload(self, context: aio.ServicerContext | None, fn: Callable[[], T]) -> T:
        await self._check_deadline(context)
        return await asyncio.get_running_loop().run_in_executor(self.executor, fn)

    def _answer_size(self, msg: Any) -> Any:
        check_answer_bytes(msg.ByteSize(), self.config.max_answer_bytes)
        return msg

    # ------------------------------------------------------------------ online
    def _check_vehicle(self, vehicle_id: str, field: str = "vehicle_id") -> None:
        if not vehicle_id:
            raise ValidationError(field, "is required")
        n = len(vehicle_id.encode())
        if n > self.config.max_vehicle_id:
            raise ValidationError(field, f"is {n} bytes long, over the limit of {self.config.max_vehicle_id}")

    def snap(self, req: pb.FixRequest, caller: Identity | None = None) -> pb.SnapResponse:
        """One fix through the vehicle's session (raises domain errors; runs off the loop).

        A fix more than ``max_time_jump`` seconds from the session's last accepted fix
        (either way) starts the session afresh and is answered ``reinitialised``; a rejected
        fix leaves the session as it was (no new session, no refreshed idle timer). A resend
        of the last accepted fix (same time and position: a client's retry) gets that fix's
        answer again and changes nothing.
        """
        entry = self.maps.get(req.map_id)
        vehicle_id = req.vehicle_id
        # at most 4 bytes a character: a short id needs no encoding to check its length
        if not 0 < len(vehicle_id) <= self._short_id:
            self._check_vehicle(vehicle_id)
        if not req.HasField("fix"):
            raise ValidationError("fix", "is required")
        fix = convert.fix_from_proto(req.fix)
        try:
            fix.validate()
        except ValidationError as exc:
            raise _prefixed(exc, "fix") from None
        online = entry.online
        sessions = self.sessions
        s = sessions.live((entry.map_id, vehicle_id))
        if s is not None and s.lock.acquire(blocking=False):  # a known vehicle, not busy
            try:
                result, _ = self._update(online, s, fix)
            finally:
                s.lock.release()
            sessions.touch(s)
        else:
            if caller is not None and self.quotas is not None:
                self.quotas.claim_session(caller, (entry.map_id, vehicle_id), sessions.live)
            with sessions.use(entry.map_id, vehicle_id, online.new_session) as s:
                result, _ = self._update(online, s, fix)
        return convert.snap_response(entry.map_id, vehicle_id, req.seq, result)

    def _update(self, online: Any, s: Any, fix: Any) -> tuple[Any, bool]:
        """The update of a locked session: (the result, whether the time jump restarted it)."""
        last = s.state.time
        if fix.time == last and (a := s.answer) is not None and a.raw_lat == fix.lat and a.raw_lon == fix.lon:
            return a, False  # a resend of the fix last answered (a client's retry)
        jumped = math.isfinite(last) and abs(fix.time - last) > self.config.max_time_jump
        state = online.new_session() if jumped else s.state
        s.version += 1  # odd: a checkpoint that reads the session meanwhile drops what it read
        try:
            result = self._apply(online, s, state, fix)
            if jumped:
                result = dataclasses.replace(result, state=State.REINITIALISED)
            s.answer = result
        finally:
            s.version += 1
        return result, jumped

    @staticmethod
    def _apply(online: Any, s: Any, state: Any, fix: Any) -> Any:
        """``online.update(state, fix)``, then ``state`` becomes the session's."""
        try:
            result = online.update(state, fix)
        except ValidationError as exc:
            raise _prefixed(exc, "fix") from None
        except Exception:
            # state may be half-updated: start this vehicle afresh, keep the others
            s.state = online.new_session()
            raise
        s.state = state
        return result

    def answer(self, req: pb.FixRequest | Undecodable, caller: Identity | None = None) -> pb.SnapResponse:
        """Like :meth:`snap`, but a rejected fix (or a message whose bytes did not decode)
        becomes a response carrying its error; a fix for a vehicle ``caller`` may not act for is
        answered PERMISSION_DENIED."""
        if isinstance(req, Undecodable):
            return pb.SnapResponse(error=_error_of(undecodable_error(req)))
        try:
            if caller is not None:
                check_vehicle(caller, req.vehicle_id)
            return self.snap(req, caller)
        except Exception as exc:
            return pb.SnapResponse(
                map_id=req.map_id,
                vehicle_id=req.vehicle_id[: self.config.max_vehicle_id],
                seq=req.seq,
                error=_error_of(exc, "StreamFixes"),
            )

    def answer_all(
        self, reqs: Sequence[pb.FixRequest | Undecodable], caller: Identity | None = None
    ) -> list[pb.SnapResponse]:
        return [self.answer(r, caller) for r in reqs]

    async def StreamFixes(
        self, request_iterator: AsyncIterator[pb.FixRequest], context: aio.ServicerContext
    ) -> None:
        """Reader/writer style (``context.read`` / ``context.write``): per fix, no async
        generator of gRPC's, ours or the interceptors' between the wire and :meth:`answer`."""
        caller = CALLER.get()
        answer = self.answer if caller is None else functools.partial(self.answer, caller=caller)
        submit = None if self.config.inline_fixes else self.online.submit
        if self.checkpoints is not None:  # sessions in the store: look-ups first, hand-over at the end
            allowed = None if caller is None else caller.may_act_for
            await self.checkpoints.serve(context, answer, submit, allowed)
            return
        read, write, eof = context.read, context.write, aio.EOF
        if submit is None:  # no thread hop: one fix is a bounded, short piece of work
            while (req := await read()) is not eof:
                await write(answer(req))
        else:
            while (req := await read()) is not eof:
                await write(await submit(functools.partial(answer, req)))

    async def StreamFixBatches(
        self, request_iterator: AsyncIterator[pb.FixBatch], context: aio.ServicerContext
    ) -> AsyncIterator[pb.SnapBatch]:
        cap, step = self.config.max_batch_fixes, self.config.batch_slice
        caller = CALLER.get()
        async for batch in request_iterator:
            if isinstance(batch, Undecodable):  # answered, and the stream goes on
                yield pb.SnapBatch(error=_error_of(undecodable_error(batch)))
                continue
            fixes = batch.fixes
            if len(fixes) > cap:
                raise LimitError(
                    "max_batch_fixes", f"a FixBatch has {len(fixes)} fixes, over the server's limit of {cap}"
                )
            if self.checkpoints is not None:  # only the caller's own vehicles are looked up
                mine = fixes if caller is None else [f for f in fixes if caller.may_act_for(f.vehicle_id)]
                await self.checkpoints.before_batch(mine)
            out: list[pb.SnapResponse] = []
            for i in range(0, len(fixes), step):  # a slice at a time: other streams go in between
                out += await self.online.submit(
                    functools.partial(self.answer_all, fixes[i : i + step], caller)
                )
            yield self._answer_size(pb.SnapBatch(responses=out))

    async def SnapFix(self, request: pb.FixRequest, context: aio.ServicerContext) -> pb.SnapResponse:
        left = context.time_remaining()
        if left is not None and left <= 0:
            await context.abort(grpc.StatusCode.DEADLINE_EXCEEDED, "deadline passed before work started")
        if self.checkpoints is not None:
            await self.checkpoints.before(request)
        caller = CALLER.get()  # its right to this vehicle is checked by the interceptor
        if self.config.inline_fixes:
            return self.snap(request, caller)
        return await self.online.submit(functools.partial(self.snap, request, caller))

    # ------------------------------------------------------------------ batch
    def _worker_map(self, entry: MapEntry) -> MapFile | None:
        """The map's file when a batch worker process can match on it."""
        if self.batch_workers is None or entry.path is None:
            return None
        return MapFile(map_id=entry.map_id, path=str(entry.path), checksum=entry.checksum)

    async def MatchTrack(
        self, request: pb.MatchTrackRequest | bytes, context: aio.ServicerContext
    ) -> pb.TrackResult | bytes:
        """Registered with ``request`` as bytes (:func:`service.server.add_servicer`):
        on a map with a file they go to a batch worker process as they are, and its answer
        comes back as bytes. The server reads only the map id, the track's presence and its
        point count from the wire format (:func:`peek_track_request`): no work on the event
        loop grows with the track."""
        data = request if isinstance(request, bytes) else b""
        peek = peek_track_request(data) if data else None
        if peek is not None:
            entry = self.maps.get(peek.map_id)
            mf = self._worker_map(entry)
            if mf is not None and self.batch_workers is not None:
                if not peek.has_track:
                    raise ValidationError("track", "is required")
                if peek.points is not None:
                    check_point_count(peek.points, self.track_limits)
                await self._check_deadline(context)
                return await self.batch_workers.match(
                    mf, data, kind="request", prefix="track", time_left=_time_left(context)
                )
        if isinstance(request, bytes):
            try:
                request = pb.MatchTrackRequest.FromString(data)
            except Exception as exc:  # protobuf DecodeError and friends
                raise ValidationError(
                    "request",
                    f"the message does not decode as the method's request type ({type(exc).__name__})",
                ) from None
        entry = self.maps.get(request.map_id)
        if not request.HasField("track"):
            raise ValidationError("track", "is required")
        check_points(request.track, self.track_limits)
        mf = self._worker_map(entry)
        if mf is not None and self.batch_workers is not None:
            await self._check_deadline(context)
            return await self.batch_workers.match(
                mf,
                data or request.SerializeToString(),
                kind="request",
                prefix="track",
                time_left=_time_left(context),
            )
        track = request.track
        return await self._offload(
            context, lambda: match_track(entry, track, prefix="track", limits=self.track_limits)
        )

    async def _check_deadline(self, context: aio.ServicerContext | None) -> None:
        if context is not None:
            left = context.time_remaining()
            if left is not None and left <= 0:
                await context.abort(grpc.StatusCode.DEADLINE_EXCEEDED, "deadline passed before work started")

    async def MatchTracks(
        self, request: pb.MatchTracksRequest, context: aio.ServicerContext
    ) -> AsyncIterator[pb.TrackResult | bytes]:
        entry = self.maps.get(request.map_id)
        mf = self._worker_map(entry)
        for i, t in enumerate(request.tracks):
            if context.cancelled() or context.done():
                return
            prefix = f"tracks[{i}]"
            try:
                if mf is not None and self.batch_workers is not None:
                    check_points(t, self.track_limits)
                    await self._check_deadline(context)
                    yield await self.batch_workers.match(
                        mf, t.SerializeToString(), kind="track", prefix=prefix, time_left=_time_left(context)
                    )
                else:
                    fn = functools.partial(match_track, entry, t, prefix=prefix, limits=self.track_limits)
                    yield await self._offload(context, fn)
            except (asyncio.CancelledError, aio.AbortError):
                raise
            except Exception as exc:
                code, fld, msg = status_for(exc)
                if code is grpc.StatusCode.INTERNAL:
                    log_internal(exc, "MatchTracks")
                yield pb.TrackResult(
                    track_id=t.track_id, error=convert.error_to_proto(code.value[0], fld, msg)
                )

    # ------------------------------------------------------------------ maps
    def _info(self, entry: MapEntry) -> pb.MapInfo:
        return convert.map_info_to_proto(entry, session_count=self.sessions.count(entry.map_id))

    async def ListMaps(
        self, request: pb.ListMapsRequest, context: aio.ServicerContext
    ) -> pb.ListMapsResponse:
        return pb.ListMapsResponse(
            maps=[self._info(e) for e in self.maps.entries()],
            default_map_id=self.maps.default_id,
            server_id=self.server_id,
        )

    async def GetMapInfo(self, request: pb.GetMapInfoRequest, context: aio.ServicerContext) -> pb.MapInfo:
        return self._info(self.maps.get(request.map_id))

    async def LoadMap(self, request: pb.LoadMapRequest, context: aio.ServicerContext) -> pb.MapInfo:
        if not request.map_id or "/" in request.map_id:
            raise ValidationError("map_id", "is required (a name without '/')")
        if not request.path:
            raise ValidationError("path", "is required")
        map_dir = self.config.map_dir
        limits = load_limits(self.config)

        def load() -> MapEntry:
            path = resolve_map_path(map_dir, request.path)  # MapPathError for everything else
            assert map_dir is not None
            shown = os.path.relpath(path, os.path.realpath(map_dir))
            # loaded and warmed up before it replaces a map of the same id
            return self.maps.load(request.map_id, path, limits=limits, source=shown)

        if map_dir is None:
            raise MapPathError()
        entry = await self._offload(context, load)
        if self.on_maps_changed is not None:
            await _maybe_await(self.on_maps_changed())
        return self._info(entry)

    async def UnloadMap(
        self, request: pb.UnloadMapRequest, context: aio.ServicerContext
    ) -> pb.UnloadMapResponse:
        if not request.map_id:
            raise ValidationError("map_id", "is required")
        dropped = self.maps.unload(request.map_id)
        if self.on_maps_changed is not None:
            await _maybe_await(self.on_maps_changed())
        return pb.UnloadMapResponse(sessions_dropped=dropped)

    # ------------------------------------------------------------------ sessions
    async def ExportSession(
        self, request: pb.ExportSessionRequest, context: aio.ServicerContext
    ) -> pb.SessionBlob:
        entry = self.maps.get(request.map_id)
        self._check_vehicle(request.vehicle_id)
        state = self.sessions.export(entry.map_id, request.vehicle_id, remove=request.remove)
        return pb.SessionBlob(
            map_id=entry.map_id, vehicle_id=request.vehicle_id, map_checksum=entry.checksum, state=state
        )

    async def ImportSession(
        self, request: pb.ImportSessionRequest, context: aio.ServicerContext
    ) -> pb.ImportSessionResponse:
        blob = request.session
        if not request.HasField("session"):
            raise ValidationError("session", "is required")
        self._check_vehicle(blob.vehicle_id, "session.vehicle_id")
        entry = self.maps.get(blob.map_id)
        if not blob.map_checksum:
            raise ValidationError(
                "session.map_checksum", "is required (the checksum of the map the session was made on)"
            )
        if blob.map_checksum != entry.checksum:
            raise ValidationError(
                "session.map_checksum",
                f"session was made on another version of map {entry.map_id!r} "
                f"({blob.map_checksum}, this server has {entry.checksum})",
            )
        from mapmatch.online.codec import StateCaps, from_bytes

        decode = functools.partial(
            from_bytes, blob.state, n_edges=entry.graph.n_edges, caps=StateCaps.of(entry.online.config)
        )
        try:
            # off the event loop: other streams are answered while a blob of up to
            # ``max_message_bytes`` parses (its lists are bounded by the matcher's caps)
            state = await asyncio.to_thread(decode)
        except ValidationError as exc:
            fld = f"session.{exc.field}" if exc.field.startswith("state") else f"session.state.{exc.field}"
            raise ValidationError(fld, exc.reason) from None
        except Exception as exc:
            raise ValidationError(
                "session.state", f"not a valid session state ({type(exc).__name__})"
            ) from None
        self.sessions.put(entry.map_id, blob.vehicle_id, state, replace=request.replace)
        return pb.ImportSessionResponse()

    async def EndSession(
        self, request: pb.EndSessionRequest, context: aio.ServicerContext
    ) -> pb.EndSessionResponse:
        entry = self.maps.get(request.map_id)
        self._check_vehicle(request.vehicle_id)
        if self.checkpoints is not None:
            self.checkpoints.forget(entry.map_id, request.vehicle_id)
        return pb.EndSessionResponse(existed=self.sessions.drop(entry.map_id, request.vehicle_id))

    async def ListSessions(
        self, request: pb.ListSessionsRequest, context: aio.ServicerContext
    ) -> pb.ListSessionsResponse:
        """The live sessions, most recently used first (built off the event loop; the answer
        is bounded by ``max_answer_bytes``)."""
        map_id = self.maps.get(request.map_id).map_id if request.map_id else ""
        return await self._offload(context, functools.partial(self._list_sessions, request, map_id))

    def _list_sessions(self, request: pb.ListSessionsRequest, map_id: str) -> pb.ListSessionsResponse:
        now = self.sessions.now()
        ttl, prefix, limit = self.sessions.ttl, request.vehicle_prefix, request.limit
        out = pb.ListSessionsResponse()
        total = 0
        for s in self.sessions.used_since(now - ttl):  # live ones, most recently used first
            m, vid = s.key
            if (map_id and m != map_id) or not vid.startswith(prefix):
                continue
            total += 1
            if not limit or len(out.sessions) < limit:
                t = getattr(s.state, "time", math.nan)
                out.sessions.add(map_id=m, vehicle_id=vid, idle_seconds=now - s.last_used, last_time=t)
        out.total = total
        return self._answer_size(out)


def _time_left(context: aio.ServicerContext | None) -> float | None:
    """Seconds to the call's deadline (None: no deadline)."""
    return None if context is None else context.time_remaining()


def _error_of(exc: Exception, method: str = "") -> pb.Error:
    """The ``Error`` message of an exception (an unexpected one logged as INTERNAL)."""
    code, fld, msg = status_for(exc)
    if code is grpc.StatusCode.INTERNAL:
        log_internal(exc, method)
    return convert.error_to_proto(code.value[0], fld, msg)


async def _maybe_await(x: Any) -> None:
    if asyncio.iscoroutine(x):
        await x
