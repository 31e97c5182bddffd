"""The server's event loop: uvloop's when the ``uvloop`` extra is installed, asyncio's without;
the same answers on both (a real server on a loopback port, a stream of a drive's fixes)."""

from __future__ import annotations

import asyncio
import contextlib
import sys

import pytest
from online_helpers import DriveSpec, drive
from service_util import city, local_config, requests, running, stub

from mapmatch.online import OnlineMatcher
from service import convert
from service.server import new_event_loop

AMAP = city()
FIXES = drive(AMAP, "abcfedghd", DriveSpec(speed=10.0, dt=1.0, sigma=3.0))


def reference() -> list[bytes]:
    """The drive's answers from one session in process, as the server serialises them."""
    m = OnlineMatcher(AMAP.graph)
    st = m.new_session()
    return [convert.snap_result_to_proto(m.update(st, f)).SerializeToString() for f in FIXES]


def streamed() -> tuple[type, list[bytes]]:
    """A server's loop class and its answers to the drive on one stream."""
    with running(local_config(), {"city": AMAP.graph}) as (srv, port):
        loop_type = type(srv.loop)
        ch, api = stub(port)
        with contextlib.closing(ch):
            got = list(api.StreamFixes(iter(requests(FIXES, "bus-1", "city")), timeout=30))
    assert [r.HasField("error") for r in got] == [False] * len(FIXES)
    return loop_type, [r.result.SerializeToString() for r in got]


def test_serve_runs_on_uvloop_and_answers_as_in_process() -> None:
    uvloop = pytest.importorskip("uvloop", reason="needs the uvloop extra: pip install 'mapmatch[uvloop]'")
    loop_type, got = streamed()
    assert issubclass(loop_type, uvloop.Loop)
    assert got == reference()


def test_without_uvloop_serve_runs_on_asyncio_with_the_same_answers(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "uvloop", None)  # import uvloop raises ImportError
    loop = new_event_loop()
    try:
        assert type(loop).__module__.startswith("asyncio")
    finally:
        loop.close()
    loop_type, got = streamed()
    assert issubclass(loop_type, asyncio.BaseEventLoop)
    assert got == reference()
