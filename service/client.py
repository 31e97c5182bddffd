"""A small client for the service: the streaming client behind ``mapmatch send``.

Example::

    with MapMatchClient("127.0.0.1:50051") as client:
        for vehicle_id, fix, result, error in client.stream(fixes):
            ...
"""

from __future__ import annotations

import queue
import threading
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
            if resp.HasField("error"):
                e = resp.error
                err = StreamError(_CODES.get(e.code, grpc.StatusCode.UNKNOWN), e.field, e.message)
                yield Answer(vid, fix, None, err)
            else:
                yield Answer(vid, fix, convert.snap_result_from_proto(resp.result), None)

    def snap(
        self, vehicle_id: str, fix: Fix, *, map_id: str = "", timeout: float | None = 10.0
    ) -> SnapResult:
        """One fix by unary call (raises ``grpc.RpcError`` on a rejected fix)."""
        req = pb.FixRequest(map_id=map_id, vehicle_id=vehicle_id, fix=convert.fix_to_proto(fix))
        resp = self.stub.SnapFix(req, timeout=timeout, metadata=self.metadata)
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


def interleave_by_time(by_vehicle: dict[str, list[Fix]]) -> list[tuple[str, Fix]]:
    """All vehicles' fixes merged by time (stable per vehicle), as a fusion node would send them."""
    rows = [(f.time, i, vid, f) for vid, fixes in by_vehicle.items() for i, f in enumerate(fixes)]
    rows.sort(key=lambda r: (r[0], r[1]))
    return [(vid, f) for _, _, vid, f in rows]


class ServerMatcher:
    """A :data:`MatchFn` over one stream to a running server: each fix waits for its answer.

    Use as a context manager; ``grpc.RpcError`` propagates (the caller maps it to exit code 3).
    """

    def __init__(self, target: str, *, vehicle_id: str, map_id: str = "", timeout: float | None = None):
        self._client = MapMatchClient(target)
        self._queue: queue.Queue[Fix | None] = queue.Queue()
        self._vehicle_id = vehicle_id
        self._answers = self._client.stream(self._fixes(), map_id=map_id, timeout=timeout)
        self._lock = threading.Lock()

    def _fixes(self) -> Iterator[tuple[str, Fix]]:
        while True:
            f = self._queue.get()
            if f is None:
                return
            yield self._vehicle_id, f

    def __call__(self, fix: Fix) -> SnapResult | None:
        with self._lock:
            self._queue.put(fix)
            return next(self._answers).result

    def close(self) -> None:
        self._queue.put(None)
        for _ in self._answers:  # drain: the server ends the stream
            pass
        self._client.close()

    def __enter__(self) -> ServerMatcher:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:  # end the request stream too, then drop the channel
            self._queue.put(None)
            self._client.close()
