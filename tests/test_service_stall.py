"""No client can stall another, on a real server on a loopback port.

A session blob is bounded by the matcher's own caps (a list over its cap is refused with
INVALID_ARGUMENT naming it) and decoded off the event loop; the largest blob the caps allow
imports, its vehicle's fixes are answered and its lists stay bounded, while another vehicle's
stream is answered throughout. How long that stream waits is measured, not asserted:
``bench/bench_attacks.py`` prints the longest gap at 50 Hz with the machine's load.
"""

from __future__ import annotations

import json
import threading

import grpc
from online_helpers import DriveSpec, drive
from service_util import city, local_config, requests, running, stub
from stall_util import worst_case_blob

from mapmatch.config import DEFAULT_CONFIG
from mapmatch.online import SessionState
from mapmatch.online.codec import StateCaps
from service.gen import mapmatch_pb2 as pb

AMAP = city()
CAPS = StateCaps.of(DEFAULT_CONFIG)


def _field(err: grpc.RpcError) -> str:
    return dict(err.trailing_metadata() or ()).get("mapmatch-field", "")


def _session(api, vehicle: str) -> pb.SessionBlob:
    """A real session of ``vehicle`` on the server (driven into an ambiguous region), exported."""
    fixes = drive(AMAP, "abefc", DriveSpec(speed=10.0, dt=1.0, noise=1.5, seed=7, sigma=3.0))
    out = list(api.StreamFixes(iter(requests(fixes[:14], vehicle)), timeout=30))
    assert all(not r.HasField("error") for r in out)
    return api.ExportSession(pb.ExportSessionRequest(vehicle_id=vehicle), timeout=10)


def _import(api, blob: pb.SessionBlob, state: bytes, vehicle: str) -> None:
    session = pb.SessionBlob(
        map_id=blob.map_id, vehicle_id=vehicle, map_checksum=blob.map_checksum, state=state
    )
    api.ImportSession(pb.ImportSessionRequest(session=session, replace=True), timeout=30)


def test_a_blob_with_200000_headings_is_refused_naming_the_list():
    with running(local_config(), {"city": AMAP.graph}) as (_, port):
        ch, api = stub(port)
        blob = _session(api, "v1")
        d = json.loads(blob.state)
        d["version"] = 2  # version 2 carries the headings as a JSON list
        d.pop("headings_f64")
        d["headings"] = [[float(i), 90.0] for i in range(200_000)]
        state = json.dumps(d).encode()
        assert len(state) > 2_000_000
        try:
            _import(api, blob, state, "v1")
        except grpc.RpcError as err:
            assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
            assert _field(err) == "session.state.headings" and "over the limit of" in err.details()
        else:
            raise AssertionError("the oversize blob was imported")
        # the vehicle's own session is untouched
        again = api.ExportSession(pb.ExportSessionRequest(vehicle_id="v1"), timeout=10)
        assert again.state == blob.state
        ch.close()


def test_every_list_over_its_cap_is_refused_naming_it():
    names = {
        "hyps": "session.state.hyps",
        "edges": "session.state.hyps[0].edges",
        "live": "session.state.live",
        "trail": "session.state.trail",
        "back": "session.state.back",
    }
    with running(local_config(), {"city": AMAP.graph}) as (_, port):
        ch, api = stub(port)
        blob = _session(api, "v1")
        for over, field in names.items():
            state = worst_case_blob(blob.state, CAPS, n_edges=AMAP.graph.n_edges, over=over)
            try:
                _import(api, blob, state, "w")
            except grpc.RpcError as err:
                assert err.code() == grpc.StatusCode.INVALID_ARGUMENT and _field(err) == field, over
            else:
                raise AssertionError(f"{over}: a list over its cap was imported")
        ch.close()


def test_the_worst_allowed_blob_imports_and_every_stream_is_answered():
    """Another vehicle streams while the worst blob the caps allow is imported and its
    vehicle sends fixes: every fix of both is answered, and the imported lists shrink back
    to what the matcher keeps."""
    with running(local_config(), {"city": AMAP.graph}) as (_, port):
        ch, api = stub(port)
        blob = _session(api, "v1")
        worst = worst_case_blob(blob.state, CAPS, n_edges=AMAP.graph.n_edges)
        fixes = drive(AMAP, "abcfed", DriveSpec(speed=10.0, dt=0.02, noise=0.5, seed=3, sigma=3.0))[:400]
        got: list[pb.SnapResponse] = []
        ready = threading.Event()

        def gen():
            for i, r in enumerate(requests(fixes, "other")):
                if i == 20:
                    ready.set()
                yield r

        t = threading.Thread(target=lambda: got.extend(api.StreamFixes(gen(), timeout=120)))
        t.start()
        ready.wait(30)
        _import(api, blob, worst, "big")
        later = drive(AMAP, "abefc", DriveSpec(speed=10.0, dt=1.0, t0=14.0, seed=7, sigma=3.0))[14:20]
        answers = list(api.StreamFixes(iter(requests(later, "big")), timeout=60))
        t.join(120)
        assert len(got) == len(fixes) and not any(r.HasField("error") for r in got)
        assert len(answers) == len(later) and not any(r.HasField("error") for r in answers)
        st = SessionState.from_bytes(
            api.ExportSession(pb.ExportSessionRequest(vehicle_id="big"), timeout=10).state
        )
        o = DEFAULT_CONFIG.online
        assert len(st.headings) <= o.evidence.turn_max_samples and len(st.trail) <= o.corrections.trail_max
        assert len(st.hyps) <= CAPS.hyps and len(st.live) <= o.corrections.max_live
        ch.close()
