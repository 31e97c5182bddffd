"""A small client for the service: the streaming client behind ``mapmatch send``.

Example::

    with MapMatchClient("127.0.0.1:50051") as client:
        for vehicle_id, fix, result, error in client.stream(fixes):
            ...

Behind a load balancer that hashes on the vehicle (``deploy/nginx``), each vehicle sends on a
stream of its own, :meth:`MapMatchClient.vehicle`, which carries ``x-vehicle-id`` metadata and
sends a fix again on a new stream when its stream breaks before the answer::

    with MapMatchClient("lb:50051") as client, client.vehicle("bus-17") as bus:
        answer = bus.send(fix)
"""

from __future__ import annotations

import collections
import queue
import threading
import time
import urllib.parse
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import grpc

from service import convert
from service.gen import mapmatch_pb2 as pb
from service.gen import mapmatch_pb2_grpc as pb_grpc


@dataclass(frozen=True, slots=True)
class StreamError:
    """The server's answer to a rejected fix."""

    code: grpc.StatusCode
    field: str
    message: str


@dataclass(frozen=True, slots=True)
class Answer:
    """One fix and the server's answer: ``result`` or ``error``."""

    vehicle_id: str
    fix: Fix
    result: SnapResult | None
    error: StreamError | None


_CODES = {c.value[0]: c for c in grpc.StatusCode}
VEHICLE_HEADER = "x-vehicle-id"  # the metadata key a load balancer hashes on
# a stream that ends with one of these before a fix is answered is opened again, the fix resent
RETRY_CODES = frozenset(
    {
        grpc.StatusCode.UNAVAILABLE,
        grpc.StatusCode.INTERNAL,
        grpc.StatusCode.UNKNOWN,
        grpc.StatusCode.CANCELLED,
    }
)


def vehicle_header(vehicle_id: str) -> str:
    """The ``x-vehicle-id`` value of a vehicle id: itself when it is printable ASCII, else
    percent-encoded UTF-8 (metadata values are ASCII)."""
    if vehicle_id.isascii() and vehicle_id.isprintable():
        return vehicle_id
    return urllib.parse.quote(vehicle_id, safe="")


class StreamEnded(grpc.RpcError):
    """The server ended a stream without answering the fix sent on it."""

    def code(self) -> grpc.StatusCode:
        return grpc.StatusCode.UNAVAILABLE

    def details(self) -> str:
        return "the stream ended before the fix was answered"


def _answer(vehicle_id: str, fix: Fix, resp: pb.SnapResponse) -> Answer:
    if resp.HasField("error"):
        e = resp.error
        err = StreamError(_CODES.get(e.code, grpc.StatusCode.UNKNOWN), e.field, e.message)
        return Answer(vehicle_id, fix, None, err)
    return Answer(vehicle_id, fix, convert.snap_result_from_proto(resp.result), None)


if TYPE_CHECKING:  # conversions go through service.convert; the types are for annotations
    from mapmatch.types import Fix, SnapResult, Track


class MapMatchClient:
    """A channel to a map-matching server.

    Parameters
    ----------
    target
        ``HOST:PORT``.
    tls_ca
        PEM CA to verify the server; enables TLS.
    client_cert, client_key
        PEM client certificate and key for mutual TLS.
    token
        Bearer token sent with every call.
    server_name
        Overrides the TLS host name checked against the server certificate.
    """

    def __init__(
        self,
        target: str,
        *,
        tls_ca: Path | None = None,
        client_cert: Path | None = None,
        client_key: Path | None = None,
        token: str | None = None,
        server_name: str | None = None,
        options: list[tuple[str, Any]] | None = None,
    ) -> None:
        opts = list(options or [])
        if server_name:
            opts.append(("grpc.ssl_target_name_override", server_name))
        if tls_ca is not None or client_cert is not None:
            creds = grpc.ssl_channel_credentials(
                root_certificates=Path(tls_ca).read_bytes() if tls_ca else None,
                private_key=Path(client_key).read_bytes() if client_key else None,
                certificate_chain=Path(client_cert).read_bytes() if client_cert else None,
            )
            self.channel = grpc.secure_channel(target, creds, options=opts)
        else:
            self.channel = grpc.insecure_channel(target, options=opts)
        self.stub = pb_grpc.MapMatchStub(self.channel)
        self.metadata: tuple[tuple[str, str], ...] = (("authorization", f"Bearer {token}"),) if token else ()

    def __enter__(self) -> MapMatchClient:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        self.channel.close()

    def wait_ready(self, timeout: float = 10.0) -> None:
        """Block until the channel is connected (raises ``grpc.FutureTimeoutError``)."""
        grpc.channel_ready_future(self.channel).result(timeout=timeout)

    # ------------------------------------------------------------------ online
    def stream(
        self,
        fixes: Iterable[tuple[str, Fix]],
        *,
        map_id: str = "",
        timeout: float | None = None,
    ) -> Iterator[Answer]:
        """Send ``(vehicle_id, fix)`` pairs on one stream; yield one answer per fix, in order."""
        sent: dict[int, tuple[str, Fix]] = {}
        lock = threading.Lock()

        def reqs() -> Iterator[pb.FixRequest]:
            for seq, (vid, fix) in enumerate(fixes):
                with lock:
                    sent[seq] = (vid, fix)
                yield pb.FixRequest(map_id=map_id, vehicle_id=vid, seq=seq, fix=convert.fix_to_proto(fix))

        for resp in self.stub.StreamFixes(reqs(), timeout=timeout, metadata=self.metadata):
            with lock:
                vid, fix = sent.pop(resp.seq)
            yield _answer(vid, fix, resp)

    def vehicle(
        self,
        vehicle_id: str,
        *,
        map_id: str = "",
        retries: int = 8,
        backoff: float = 0.05,
        replay: float = 3.0,
    ) -> VehicleStream:
        """A :class:`VehicleStream`: one vehicle's fixes, routed by ``x-vehicle-id``, resent
        (with the last ``replay`` seconds of fixes) after a broken stream."""
        return VehicleStream(self, vehicle_id, map_id=map_id, retries=retries, backoff=backoff, replay=replay)

    def snap(
        self, vehicle_id: str, fix: Fix, *, map_id: str = "", timeout: float | None = 10.0
    ) -> SnapResult:
        """One fix by unary call (raises ``grpc.RpcError`` on a rejected fix)."""
        req = pb.FixRequest(map_id=map_id, vehicle_id=vehicle_id, fix=convert.fix_to_proto(fix))
        md = (*self.metadata, (VEHICLE_HEADER, vehicle_header(vehicle_id)))
        resp = self.stub.SnapFix(req, timeout=timeout, metadata=md)
        return convert.snap_result_from_proto(resp.result)

    # ------------------------------------------------------------------ batch and maps
    def match_track(self, track: Track, *, map_id: str = "", timeout: float | None = 60.0) -> pb.TrackResult:
        req = pb.MatchTrackRequest(map_id=map_id, track=convert.track_to_proto(track))
        result: pb.TrackResult = self.stub.MatchTrack(req, timeout=timeout, metadata=self.metadata)
        return result

    def list_maps(self, *, timeout: float | None = 10.0) -> pb.ListMapsResponse:
        result: pb.ListMapsResponse = self.stub.ListMaps(
            pb.ListMapsRequest(), timeout=timeout, metadata=self.metadata
        )
        return result


class VehicleStream:
    """One vehicle's fixes on a stream of its own; each fix is answered before the next goes.

    The stream carries ``x-vehicle-id`` metadata, so a load balancer hashing on it keeps the
    vehicle on one server. When the stream breaks before a fix is answered (its server died
    or is shutting down, the balancer reset it: a status in :data:`RETRY_CODES`), a new stream
    is opened and the fix sent again, at most ``retries`` times for one fix, after ``backoff``
    s and twice as long before each next try.

    Before the fix, the new stream replays the fixes answered in the last ``replay`` seconds
    (their new answers are dropped): a server that died lost what its vehicles did since its
    last checkpoint (at most its ``--checkpoint-interval``, 1 s by default), and the server
    that resumes the session from the store catches up on them, so the session is as if
    nothing had happened (replayed fixes it already holds are refused as not newer, and
    change nothing). A server answers a resend of the fix it last applied with that fix's
    answer. So each fix gets exactly one answer: a result, or an error for a rejected fix.
    Past the retries the last ``grpc.RpcError`` is raised.

    ``timeout`` is each stream's deadline (None: none). Use as a context manager, or call
    :meth:`close`. Not thread-safe: one sender per vehicle.
    """

    def __init__(
        self,
        client: MapMatchClient,
        vehicle_id: str,
        *,
        map_id: str = "",
        retries: int = 8,
        backoff: float = 0.05,
        replay: float = 3.0,
        timeout: float | None = None,
    ) -> None:
        self.client = client
        self.timeout = timeout
        self.replay = replay
        self.vehicle_id = vehicle_id
        self.map_id = map_id
        self.retries = retries
        self.backoff = backoff
        self.reconnects = 0  # streams opened again after a failure
        self.resent = 0  # fixes sent again (replayed ones included)
        self._history: collections.deque[tuple[float, pb.FixRequest]] = collections.deque()
        self._metadata = (*client.metadata, (VEHICLE_HEADER, vehicle_header(vehicle_id)))
        self._call: Any = None
        self._queue: queue.SimpleQueue[pb.FixRequest | None] | None = None
        self._seq = 0

    def _open(self) -> None:
        q: queue.SimpleQueue[pb.FixRequest | None] = queue.SimpleQueue()

        def reqs() -> Iterator[pb.FixRequest]:
            while (r := q.get()) is not None:
                yield r

        self._queue = q
        self._call = self.client.stub.StreamFixes(reqs(), metadata=self._metadata, timeout=self.timeout)

    def _drop(self) -> None:
        if self._queue is not None:
            self._queue.put(None)
        if self._call is not None:
            self._call.cancel()
        self._call = self._queue = None

    def send(self, fix: Fix) -> Answer:
        """Send one fix and wait for its answer (resending it after a broken stream)."""
        req = pb.FixRequest(
            map_id=self.map_id, vehicle_id=self.vehicle_id, seq=self._seq, fix=convert.fix_to_proto(fix)
        )
        self._seq += 1
        for attempt in range(self.retries + 1):
            replay: list[pb.FixRequest] = []
            if self._call is None:
                self._open()
                if attempt:
                    replay = [r for _, r in self._history]
            assert self._queue is not None
            for r in replay:
                self._queue.put(r)
            self._queue.put(req)
            try:
                for _ in replay:  # their answers were given before
                    next(self._call)
                answer = _answer(self.vehicle_id, fix, next(self._call))
            except (grpc.RpcError, StopIteration) as exc:
                self._drop()
                err = exc if isinstance(exc, grpc.RpcError) else StreamEnded()
                if err.code() not in RETRY_CODES or attempt == self.retries:
                    raise err from None
            else:
                self._remember(req)
                return answer
            time.sleep(self.backoff * 2**attempt)
            self.reconnects += 1
            self.resent += 1 + len(self._history)
        raise AssertionError("unreachable")

    def _remember(self, req: pb.FixRequest) -> None:
        now = time.monotonic()
        h = self._history
        h.append((now, req))
        while h and h[0][0] < now - self.replay:
            h.popleft()

    def close(self) -> None:
        """End the stream (the server hands the vehicle's session over, when it has a store)."""
        call = self._call
        if self._queue is not None:
            self._queue.put(None)
        if call is not None:
            try:
                for _ in call:  # the server ends its side once ours has ended
                    pass
            except grpc.RpcError:
                pass
        self._call = self._queue = None

    def __enter__(self) -> VehicleStream:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self._drop()


def interleave_by_time(by_vehicle: dict[str, list[Fix]]) -> list[tuple[str, Fix]]:
    """All vehicles' fixes merged by time (stable per vehicle), as a fusion node would send them."""
    rows = [(f.time, i, vid, f) for vid, fixes in by_vehicle.items() for i, f in enumerate(fixes)]
    rows.sort(key=lambda r: (r[0], r[1]))
    return [(vid, f) for _, _, vid, f in rows]


class ServerMatcher:
    """A :data:`MatchFn` over one stream to a running server: each fix waits for its answer
    (a :class:`VehicleStream`, so a broken stream is opened again and the fix resent).

    Use as a context manager; ``grpc.RpcError`` propagates (the caller maps it to exit code 3).
    """

    def __init__(self, target: str, *, vehicle_id: str, map_id: str = "", timeout: float | None = None):
        self._client = MapMatchClient(target)
        # a few resends: a server restarting behind a balancer; none that is down stays long
        self._stream = VehicleStream(self._client, vehicle_id, map_id=map_id, retries=3, timeout=timeout)
        self._lock = threading.Lock()

    def __call__(self, fix: Fix) -> SnapResult | None:
        with self._lock:
            return self._stream.send(fix).result

    def close(self) -> None:
        self._stream.close()
        self._client.close()

    def __enter__(self) -> ServerMatcher:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:  # end the stream too, then drop the channel
            self._stream._drop()
            self._client.close()
