"""The ``mapmatch.v1.MapMatch`` servicer: validate, convert, call ``mapmatch``, convert back.

No matching logic lives here. Online updates are fast and run on the server's event loop, so
each stream is served in order and a vehicle's fixes never race; batch matching and map
loading run on a thread pool so they never stall the live streams. Exceptions propagate to
:class:`service.interceptors.ServiceInterceptor`, which maps them to statuses; in the live
stream a bad fix is answered with an ``error`` for that fix and the stream goes on.
"""

from __future__ import annotations

import asyncio
import functools
import math
import os
import socket
from collections.abc import AsyncIterator, Callable
from concurrent.futures import Executor
from pathlib import Path
from typing import Any, TypeVar

import grpc
from grpc import aio

from mapmatch.errors import ValidationError
from service import convert
from service.gen.mapmatch.v1 import mapmatch_pb2 as pb
from service.gen.mapmatch.v1 import mapmatch_pb2_grpc as pb_grpc
from service.interceptors import log_internal, status_for
from service.maps import MapEntry, MapRegistry
from service.sessions import SessionStore

T = TypeVar("T")
SERVICE_NAME = pb.DESCRIPTOR.services_by_name["MapMatch"].full_name


def _prefixed(exc: ValidationError, prefix: str) -> ValidationError:
    return ValidationError(f"{prefix}.{exc.field}", exc.reason)


class MapMatchServicer(pb_grpc.MapMatchServicer):
    """Serves the API over a map registry and a session store.

    Parameters
    ----------
    maps
        Loaded maps.
    sessions
        Per-vehicle sessions.
    executor
        Thread pool for batch matching and map loads.
    on_maps_changed
        Called (on the event loop) after a map is loaded or unloaded; the server updates health.
    """

    def __init__(
        self,
        *,
        maps: MapRegistry,
        sessions: SessionStore,
        executor: Executor,
        on_maps_changed: Callable[[], Any] | None = None,
    ) -> None:
        self.maps = maps
        self.sessions = sessions
        self.executor = executor
        self.on_maps_changed = on_maps_changed
        self.server_id = f"{socket.gethostname()}:{os.getpid()}"

    async def _offload(self, context: aio.ServicerContext | None, fn: Callable[[], T]) -> T:
        if context is not None:
            left = context.time_remaining()
            if left is not None and left <= 0:
                await context.abort(grpc.StatusCode.DEADLINE_EXCEEDED, "deadline passed before work started")
        return await asyncio.get_running_loop().run_in_executor(self.executor, fn)

    # ------------------------------------------------------------------ online
    def snap(self, req: pb.FixRequest) -> pb.SnapResponse:
        """One fix through the vehicle's session (raises domain errors)."""
        entry = self.maps.get(req.map_id)
        if not req.vehicle_id:
            raise ValidationError("vehicle_id", "is required")
        if not req.HasField("fix"):
            raise ValidationError("fix", "is required")
        fix = convert.fix_from_proto(req.fix)
        try:
            fix.validate()
        except ValidationError as exc:
            raise _prefixed(exc, "fix") from None
        with self.sessions.use(entry.map_id, req.vehicle_id, entry.online.new_session) as s:
            try:
                result = entry.online.update(s.state, fix)
            except ValidationError as exc:
                raise _prefixed(exc, "fix") from None
            except Exception:
                # state may be half-updated: start this vehicle afresh, keep the others
                s.state = entry.online.new_session()
                raise
        return pb.SnapResponse(
            map_id=entry.map_id,
            vehicle_id=req.vehicle_id,
            seq=req.seq,
            result=convert.snap_result_to_proto(result),
        )

    def answer(self, req: pb.FixRequest) -> pb.SnapResponse:
        """Like :meth:`snap`, but a rejected fix becomes a response carrying its error."""
        try:
            return self.snap(req)
        except Exception as exc:
            code, fld, msg = status_for(exc)
            if code is grpc.StatusCode.INTERNAL:
                log_internal(exc, "StreamFixes")
            return pb.SnapResponse(
                map_id=req.map_id,
                vehicle_id=req.vehicle_id,
                seq=req.seq,
                error=convert.error_to_proto(code.value[0], fld, msg),
            )

    async def StreamFixes(
        self, request_iterator: AsyncIterator[pb.FixRequest], context: aio.ServicerContext
    ) -> AsyncIterator[pb.SnapResponse]:
        async for req in request_iterator:
            yield self.answer(req)

    async def StreamFixBatches(
        self, request_iterator: AsyncIterator[pb.FixBatch], context: aio.ServicerContext
    ) -> AsyncIterator[pb.SnapBatch]:
        async for batch in request_iterator:
            yield pb.SnapBatch(responses=[self.answer(r) for r in batch.fixes])

    async def SnapFix(self, request: pb.FixRequest, context: aio.ServicerContext) -> pb.SnapResponse:
        return self.snap(request)

    # ------------------------------------------------------------------ batch
    def _match(self, entry: MapEntry, msg: pb.Track, prefix: str) -> pb.TrackResult:
        track = convert.track_from_proto(msg, prefix=prefix)
        try:
            m = entry.batch.match(track)
        except ValidationError as exc:
            raise _prefixed(exc, prefix) from None
        return convert.track_match_to_proto(m, entry.graph)

    async def MatchTrack(self, request: pb.MatchTrackRequest, context: aio.ServicerContext) -> pb.TrackResult:
        entry = self.maps.get(request.map_id)
        if not request.HasField("track"):
            raise ValidationError("track", "is required")
        return await self._offload(context, lambda: self._match(entry, request.track, "track"))

    async def MatchTracks(
        self, request: pb.MatchTracksRequest, context: aio.ServicerContext
    ) -> AsyncIterator[pb.TrackResult]:
        entry = self.maps.get(request.map_id)
        for i, t in enumerate(request.tracks):
            if context.cancelled() or context.done():
                return
            try:
                yield await self._offload(context, functools.partial(self._match, entry, t, f"tracks[{i}]"))
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
        path = Path(request.path)

        def load() -> MapEntry:
            entry = self.maps.load(request.map_id, path)
            try:
                warm_up(entry, self)
            except Exception:
                self.maps.unload(request.map_id)
                raise
            return entry

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
        if not request.vehicle_id:
            raise ValidationError("vehicle_id", "is required")
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
        if not blob.vehicle_id:
            raise ValidationError("session.vehicle_id", "is required")
        entry = self.maps.get(blob.map_id)
        if blob.map_checksum and blob.map_checksum != entry.checksum:
            raise ValidationError(
                "session.map_checksum",
                f"session was made on another version of map {entry.map_id!r} "
                f"({blob.map_checksum}, this server has {entry.checksum})",
            )
        from mapmatch.online import SessionState

        try:
            state = SessionState.from_bytes(blob.state)
        except Exception as exc:
            raise ValidationError("session.state", f"not a valid session state ({exc})") from None
        self.sessions.put(entry.map_id, blob.vehicle_id, state, replace=request.replace)
        return pb.ImportSessionResponse()

    async def EndSession(
        self, request: pb.EndSessionRequest, context: aio.ServicerContext
    ) -> pb.EndSessionResponse:
        entry = self.maps.get(request.map_id)
        if not request.vehicle_id:
            raise ValidationError("vehicle_id", "is required")
        return pb.EndSessionResponse(existed=self.sessions.drop(entry.map_id, request.vehicle_id))


async def _maybe_await(x: Any) -> None:
    if asyncio.iscoroutine(x):
        await x


def warm_up(entry: MapEntry, servicer: MapMatchServicer, *, batch: bool = True) -> None:
    """One online query (and one batch match when available and ``batch``) on a map, through the
    same code path as requests; raises when the map cannot serve. Leaves no session behind."""
    g = entry.graph
    if g.n_edges == 0:
        raise ValidationError("path", f"map {entry.map_id!r} has no roads")
    e = int(g.edge_len.argmax())
    u, v = int(g.edge_u[e]), int(g.edge_v[e])
    lon0, lat0 = g.node_lonlat[u]
    lon1, lat1 = g.node_lonlat[v]
    lat, lon = (lat0 + lat1) / 2.0, (lon0 + lon1) / 2.0
    vid = f"__warmup__{os.getpid()}"
    bearing = float(g.edge_bearing_start[e])
    req = pb.FixRequest(
        map_id=entry.map_id,
        vehicle_id=vid,
        fix=pb.Fix(time=0.0, lat=float(lat), lon=float(lon), heading=bearing, pos_sigma=5.0, speed=5.0),
    )
    try:
        resp = servicer.snap(req)
    finally:
        servicer.sessions.drop(entry.map_id, vid)
    if not math.isfinite(resp.result.time):
        raise RuntimeError(f"warm-up query on map {entry.map_id!r} failed")
    if not batch:
        return
    try:
        import mapmatch.batch  # noqa: F401
    except ModuleNotFoundError:
        return
    track = pb.Track(
        track_id="warmup", time=[0.0, 1.0], lat=[float(lat0), float(lat)], lon=[float(lon0), float(lon)]
    )
    servicer._match(entry, track, "track")
