"""Helpers for the gRPC service tests: a small ASCII city, servers on port 0, fixes as requests."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import grpc

from graph.ascii import AsciiMap, parse_ascii_map
from mapmatch.types import Fix
from service import convert
from service.config import ServerConfig
from service.gen import mapmatch_pb2 as pb
from service.gen import mapmatch_pb2_grpc as pb_grpc
from service.server import Server, start_server

CITY = """
    a-----------b-----------c
    |           |           |
    |           |           |
    d-----------e-----------f
    |           |
    |           |
    g-----------h
"""


def city(scale: float = 10.0) -> AsciiMap:
    """A 3x3 grid: 120 m blocks across, 60 m down."""
    return parse_ascii_map(CITY, scale=scale)


def local_config(**kw: Any) -> ServerConfig:
    base: dict[str, Any] = {"address": "127.0.0.1:0", "grace": 2.0, "reuse_port": False}
    base.update(kw)
    return ServerConfig(**base)


@contextlib.contextmanager
def running(config: ServerConfig | None = None, maps: Any = None, **kw: Any) -> Iterator[tuple[Server, int]]:
    server, port = start_server(config or local_config(), maps, **kw)
    try:
        yield server, port
    finally:
        server.stop(0)


def stub(port: int, **kw: Any) -> tuple[grpc.Channel, pb_grpc.MapMatchStub]:
    ch = grpc.insecure_channel(f"127.0.0.1:{port}", **kw)
    return ch, pb_grpc.MapMatchStub(ch)


def requests(fixes: list[Fix], vehicle: str, map_id: str = "", seq0: int = 0) -> list[pb.FixRequest]:
    return [
        pb.FixRequest(map_id=map_id, vehicle_id=vehicle, seq=seq0 + i, fix=convert.fix_to_proto(f))
        for i, f in enumerate(fixes)
    ]


def looped_track(amap: AsciiMap, n: int, track_id: str = "t") -> pb.Track:
    """An ``n``-point track at 1 Hz, driving a loop of the city over and over."""
    from online_helpers import DriveSpec, drive

    fixes = drive(amap, "abcfedghd", DriveSpec(speed=10.0, dt=1.0))
    k = len(fixes)
    return pb.Track(
        track_id=track_id,
        time=[float(i) for i in range(n)],
        lat=[fixes[i % k].lat for i in range(n)],
        lon=[fixes[i % k].lon for i in range(n)],
    )
