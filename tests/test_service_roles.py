"""Identities and roles on a real server on a loopback port: vehicles act only for their own
vehicles, only the operator manages maps and imports sessions, quotas per identity, health
``Watch`` capped, the identities file reloaded, and identities from client certificates."""

from __future__ import annotations

import json
import os
import re
import threading
import time
from pathlib import Path

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from online_helpers import drive
from service_util import city, local_config, running

from mapmatch.errors import ConfigError
from service import convert
from service.auth import METHOD_RULES, Identity, Role, hash_token, read_identities, rule_for
from service.gen import mapmatch_pb2 as pb
from service.gen import mapmatch_pb2_grpc as pb_grpc
from service.server import create_server

AMAP = city()
ROOT = Path(__file__).resolve().parents[1]
FIXES = drive(AMAP, "abc")
DENIED = grpc.StatusCode.PERMISSION_DENIED
TOKENS = {"a": "token-of-car-a", "b": "token-of-car-b", "node": "token-of-node-7", "op": "operator-token"}


def _identities(path: Path, **extra: dict) -> Path:
    ids = [
        {"name": "car-a", "role": "vehicle", "token_sha256": hash_token(TOKENS["a"]), "vehicles": ["car-a"]},
        {"name": "car-b", "role": "vehicle", "token_sha256": hash_token(TOKENS["b"]), "vehicles": ["car-b"]},
        {
            "name": "node-7",
            "role": "vehicle",
            "token_sha256": hash_token(TOKENS["node"]),
            "vehicle_prefixes": ["node7/"],
        },
        {"name": "ops", "role": "operator", "token_sha256": hash_token(TOKENS["op"])},
    ]
    for e in ids:
        e.update(extra.get(e["name"].replace("-", "_"), {}))
    path.write_text(json.dumps({"identity": ids}))
    return path


def md(who: str) -> tuple[tuple[str, str], ...]:
    return (("authorization", f"Bearer {TOKENS.get(who, who)}"),)


def fix(vehicle: str, i: int = 0, map_id: str = "city") -> pb.FixRequest:
    return pb.FixRequest(map_id=map_id, vehicle_id=vehicle, seq=i, fix=convert.fix_to_proto(FIXES[i]))


def refused(call, *args, **kw) -> grpc.RpcError:
    with pytest.raises(grpc.RpcError) as ei:
        call(*args, timeout=10, **kw)
    return ei.value


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    d = tmp_path_factory.mktemp("roles")
    (d / "maps").mkdir()
    cfg = local_config(identities=_identities(d / "ids.json"), map_dir=d / "maps", batch_processes=0)
    with running(cfg, {"city": AMAP.graph, "spare": AMAP.graph}) as (srv, port):
        ch = grpc.insecure_channel(f"127.0.0.1:{port}")
        yield srv, port, pb_grpc.MapMatchStub(ch)
        ch.close()


def test_every_rpc_has_a_rule():
    proto = (ROOT / "proto" / "mapmatch" / "v1" / "mapmatch.proto").read_text(encoding="utf-8")
    rpcs = re.findall(r"^\s*rpc (\w+)\(", proto, re.M)
    assert len(rpcs) >= 12
    assert [r for r in rpcs if f"/mapmatch.v1.MapMatch/{r}" not in METHOD_RULES] == []
    for m in ("Check", "Watch"):
        assert rule_for(f"/grpc.health.v1.Health/{m}").open
    assert not rule_for("/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo").open
    for m in ("LoadMap", "UnloadMap", "ImportSession"):
        assert rule_for(f"/mapmatch.v1.MapMatch/{m}").operator_only
    assert rule_for("/mapmatch.v1.MapMatch/NotAMethod").operator_only  # unlisted: operator only


def test_vehicle_cannot_touch_another_vehicles_session(server):
    _, _, api = server
    assert api.SnapFix(fix("car-b"), timeout=10, metadata=md("b")).result.time == 0.0
    # A cannot export (with remove), end, snap for or overwrite B's session ...
    req = pb.ExportSessionRequest(map_id="city", vehicle_id="car-b", remove=True)
    e1 = refused(api.ExportSession, req, metadata=md("a"))
    ghost = pb.ExportSessionRequest(map_id="city", vehicle_id="car-ghost", remove=True)
    e2 = refused(api.ExportSession, ghost, metadata=md("a"))
    # ... and the refusal is the same whether the session exists or not
    assert e1.code() == e2.code() == DENIED
    assert e1.details() == e2.details() == "vehicle_id: this credential may not act for that vehicle"
    e = refused(api.EndSession, pb.EndSessionRequest(map_id="city", vehicle_id="car-b"), metadata=md("a"))
    assert e.code() == DENIED
    assert refused(api.SnapFix, fix("car-b", 1), metadata=md("a")).code() == DENIED
    blob = api.ExportSession(
        pb.ExportSessionRequest(map_id="city", vehicle_id="car-b"), timeout=10, metadata=md("b")
    )
    e = refused(api.ImportSession, pb.ImportSessionRequest(session=blob, replace=True), metadata=md("a"))
    assert (e.code(), e.details()) == (DENIED, "ImportSession needs the operator role")
    # B's session is still there and still B's
    assert api.ExportSession(
        pb.ExportSessionRequest(map_id="city", vehicle_id="car-b"), timeout=10, metadata=md("b")
    ).state
    assert api.EndSession(
        pb.EndSessionRequest(map_id="city", vehicle_id="car-b"), timeout=10, metadata=md("b")
    ).existed


def test_only_the_operator_manages_maps_and_imports(server):
    _, _, api = server
    for who in ("a", "node"):
        e = refused(api.UnloadMap, pb.UnloadMapRequest(map_id="spare"), metadata=md(who))
        assert (e.code(), e.details()) == (DENIED, "UnloadMap needs the operator role")
        e = refused(api.LoadMap, pb.LoadMapRequest(map_id="x", path="x.map"), metadata=md(who))
        assert (e.code(), e.details()) == (DENIED, "LoadMap needs the operator role")
    # the operator passes the role check (and meets the map folder's own refusal)
    e = refused(api.LoadMap, pb.LoadMapRequest(map_id="x", path="x.map"), metadata=md("op"))
    assert e.code() == DENIED and e.details().startswith("path:")
    # vehicles may read the maps and match tracks
    assert {m.map_id for m in api.ListMaps(pb.ListMapsRequest(), timeout=10, metadata=md("a")).maps} >= {
        "city",
        "spare",
    }
    assert api.GetMapInfo(pb.GetMapInfoRequest(map_id="city"), timeout=10, metadata=md("a")).map_id == "city"
    # the operator acts for any vehicle: export, import (replace) and end A's session
    api.SnapFix(fix("car-a"), timeout=10, metadata=md("a"))
    blob = api.ExportSession(
        pb.ExportSessionRequest(map_id="city", vehicle_id="car-a", remove=True), timeout=10, metadata=md("op")
    )
    api.ImportSession(pb.ImportSessionRequest(session=blob), timeout=10, metadata=md("op"))
    assert api.ExportSession(
        pb.ExportSessionRequest(map_id="city", vehicle_id="car-a"), timeout=10, metadata=md("a")
    ).state
    assert api.EndSession(
        pb.EndSessionRequest(map_id="city", vehicle_id="car-a"), timeout=10, metadata=md("op")
    ).existed
    assert api.UnloadMap(pb.UnloadMapRequest(map_id="spare"), timeout=10, metadata=md("op")) is not None


def test_only_the_operator_lists_sessions(server):
    _, _, api = server
    for vid in ("node7/list-1", "node7/list-2", "node7/list-3"):
        api.SnapFix(fix(vid), timeout=10, metadata=md("node"))
    req = pb.ListSessionsRequest(map_id="city", vehicle_prefix="node7/list-", limit=2)
    for who in ("node", "a"):
        e = refused(api.ListSessions, req, metadata=md(who))
        assert (e.code(), e.details()) == (DENIED, "ListSessions needs the operator role")
    got = api.ListSessions(req, timeout=10, metadata=md("op"))
    assert got.total == 3
    assert [s.vehicle_id for s in got.sessions] == ["node7/list-3", "node7/list-2"]  # latest first
    assert all(s.map_id == "city" and s.idle_seconds >= 0 and s.last_time == 0.0 for s in got.sessions)
    assert api.ListSessions(pb.ListSessionsRequest(), timeout=10, metadata=md("op")).total >= 3


def test_streams_check_every_fix_and_go_on(server):
    _, _, api = server
    reqs = [fix("car-a", 0), fix("car-b", 1), fix("car-a", 1)]
    out = list(api.StreamFixes(iter(reqs), timeout=10, metadata=md("a")))
    assert [r.HasField("error") for r in out] == [False, True, False]
    assert out[1].error.code == DENIED.value[0]
    assert out[1].error.message == "vehicle_id: this credential may not act for that vehicle"
    batch = pb.FixBatch(fixes=[fix("car-a", 2), fix("car-b", 2)])
    got = next(api.StreamFixBatches(iter([batch]), timeout=10, metadata=md("a")))
    assert [r.HasField("error") for r in got.responses] == [False, True]
    api.EndSession(pb.EndSessionRequest(map_id="city", vehicle_id="car-a"), timeout=10, metadata=md("a"))


def test_prefix_credentials_act_for_their_prefix_only(server):
    _, _, api = server
    assert api.SnapFix(fix("node7/truck-1"), timeout=10, metadata=md("node")).vehicle_id == "node7/truck-1"
    assert api.SnapFix(fix("node7/truck-2"), timeout=10, metadata=md("node")).result.time == 0.0
    for vid in ("node8/truck-1", "node7", "car-a"):
        assert refused(api.SnapFix, fix(vid), metadata=md("node")).code() == DENIED
    out = list(api.StreamFixes(iter([fix("node7/x"), fix("xnode7/x")]), timeout=10, metadata=md("node")))
    assert [r.HasField("error") for r in out] == [False, True]


def test_unknown_or_missing_credentials_are_unauthenticated_but_check_is_open(server):
    _, port, api = server
    for m in ((), md("not-a-token"), (("authorization", TOKENS["op"]),)):
        e = refused(api.ListMaps, pb.ListMapsRequest(), metadata=m)
        assert e.code() == grpc.StatusCode.UNAUTHENTICATED
        e = refused(lambda **kw: list(api.StreamFixes(iter([fix("car-a")]), **kw)), metadata=m)
        assert e.code() == grpc.StatusCode.UNAUTHENTICATED
    with grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
        st = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(service=""), timeout=10)
        assert st.status == health_pb2.HealthCheckResponse.SERVING


def test_token_flag_is_the_operator_beside_the_identities(tmp_path):
    cfg = local_config(identities=_identities(tmp_path / "ids.json"), token="legacy", batch_processes=0)
    with running(cfg, {"city": AMAP.graph}) as (_, port), grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
        api = pb_grpc.MapMatchStub(ch)
        assert api.SnapFix(fix("anyone"), timeout=10, metadata=md("legacy")).vehicle_id == "anyone"
        api.UnloadMap(pb.UnloadMapRequest(map_id="city"), timeout=10, metadata=md("legacy"))
        assert refused(api.SnapFix, fix("anyone"), metadata=md("a")).code() == DENIED


def test_the_identities_file_is_read_again_when_it_changes(tmp_path):
    path = _identities(tmp_path / "ids.json")
    cfg = local_config(identities=path, batch_processes=0)
    with running(cfg, {"city": AMAP.graph}) as (srv, port), grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
        api = pb_grpc.MapMatchStub(ch)
        assert refused(api.SnapFix, fix("car-c"), metadata=md("a")).code() == DENIED
        _identities(path, car_a={"vehicles": ["car-a", "car-c"]})
        os.utime(path, ns=(time.time_ns(), time.time_ns() + 10**9))  # a surely newer mtime
        time.sleep(1.2)  # the file's mtime is looked at at most once a second
        assert api.SnapFix(fix("car-c"), timeout=10, metadata=md("a")).vehicle_id == "car-c"
        # a file that does not parse keeps the table in force
        path.write_text("{ not json")
        assert not srv.identities.reload()
        assert api.SnapFix(fix("car-c", 1), timeout=10, metadata=md("a")).vehicle_id == "car-c"
        # a token taken out of the file is refused after a reload (as on SIGHUP)
        _identities(path)
        data = json.loads(path.read_text())
        data["identity"] = [i for i in data["identity"] if i["name"] != "car-a"]
        path.write_text(json.dumps(data))
        assert srv.identities.reload()
        e = refused(api.SnapFix, fix("car-a"), metadata=md("a"))
        assert e.code() == grpc.StatusCode.UNAUTHENTICATED


def test_health_watch_is_capped_per_connection_and_in_total():
    cfg = local_config(max_watch_per_connection=2, max_watch_total=3, token="t", batch_processes=0)
    with running(cfg, {"city": AMAP.graph}) as (_, port):
        # a subchannel pool each: three TCP connections (channels alike share one otherwise)
        own = [("grpc.use_local_subchannel_pool", 1)]
        chans = [grpc.insecure_channel(f"127.0.0.1:{port}", options=own) for _ in range(3)]
        try:
            watches = []

            def watch(ch: grpc.Channel):
                call = health_pb2_grpc.HealthStub(ch).Watch(health_pb2.HealthCheckRequest(service=""))
                return call, next(call)  # the first status: the call is open

            for ch in (chans[0], chans[0], chans[1]):
                call, first = watch(ch)
                assert first.status == health_pb2.HealthCheckResponse.SERVING
                watches.append(call)
            for ch, limit in ((chans[0], "max_watch_per_connection"), (chans[2], "max_watch_total")):
                with pytest.raises(grpc.RpcError) as ei:
                    watch(ch)
                assert ei.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
                assert ei.value.details().startswith(limit)
            watches.pop().cancel()
            deadline = time.monotonic() + 10
            while True:  # the freed place is given back once the server sees the cancel
                try:
                    watches.append(watch(chans[2])[0])
                    break
                except grpc.RpcError:
                    assert time.monotonic() < deadline
                    time.sleep(0.05)
        finally:
            for c in watches:
                c.cancel()
            for ch in chans:
                ch.close()


def test_quotas_per_identity_on_streams_and_sessions(tmp_path):
    path = _identities(tmp_path / "ids.json", car_a={"max_streams": 1}, node_7={"max_sessions": 2})
    cfg = local_config(identities=path, batch_processes=0)
    with running(cfg, {"city": AMAP.graph}) as (_, port), grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
        api = pb_grpc.MapMatchStub(ch)
        gate = threading.Event()

        def slow():
            yield fix("car-a", 0)
            gate.wait(10)

        first = api.StreamFixes(slow(), timeout=20, metadata=md("a"))
        assert not next(first).HasField("error")  # the stream is open
        e = refused(lambda **kw: list(api.StreamFixes(iter([fix("car-a", 1)]), **kw)), metadata=md("a"))
        assert e.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert e.details().startswith("max_identity_streams")
        # another identity is not held back by A's quota
        assert list(api.StreamFixes(iter([fix("car-b")]), timeout=10, metadata=md("b")))
        gate.set()
        list(first)
        assert list(api.StreamFixes(iter([fix("car-a", 1)]), timeout=10, metadata=md("a")))
        # sessions: two for node-7, the third refused until one ends
        for vid in ("node7/1", "node7/2"):
            api.SnapFix(fix(vid), timeout=10, metadata=md("node"))
        e = refused(api.SnapFix, fix("node7/3"), metadata=md("node"))
        assert e.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert e.details().startswith("max_identity_sessions")
        api.SnapFix(fix("node7/1", 1), timeout=10, metadata=md("node"))  # its own go on
        api.EndSession(
            pb.EndSessionRequest(map_id="city", vehicle_id="node7/1"), timeout=10, metadata=md("node")
        )
        assert api.SnapFix(fix("node7/3"), timeout=10, metadata=md("node")).vehicle_id == "node7/3"


def test_bad_identities_files_are_refused_with_a_clear_line(tmp_path):
    cases = {
        "missing.json": None,
        "syntax.toml": "[[identity]\nname=",
        "role.json": json.dumps([{"name": "x", "role": "admin", "vehicles": ["v"]}]),
        "hash.json": json.dumps([{"name": "x", "role": "operator", "token_sha256": "secret"}]),
        "novehicles.json": json.dumps([{"name": "x", "role": "vehicle"}]),
        "twice.json": json.dumps([{"name": "x", "role": "operator"}, {"name": "x", "role": "operator"}]),
        "key.json": json.dumps([{"name": "x", "role": "operator", "token": "plain"}]),
    }
    for name, text in cases.items():
        p = tmp_path / name
        if text is not None:
            p.write_text(text)
        with pytest.raises(ConfigError, match="identities file"):
            create_server(local_config(identities=p), {"city": AMAP.graph})
    toml = tmp_path / "ok.toml"
    toml.write_text(
        '[[identity]]\nname = "n"\nrole = "vehicle"\nvehicle_prefixes = ["n/"]\n'
        f'token_sha256 = "{hash_token("x")}"\nmax_streams = 3\n'
    )
    (ident,) = read_identities(toml)
    assert ident == Identity(
        name="n", role=Role.VEHICLE, vehicle_prefixes=("n/",), token_sha256=hash_token("x"), max_streams=3
    )


# ---------------------------------------------------------------------------------- mutual TLS
def _pki(d: Path) -> dict[str, Path]:
    from cryptography import x509
    from tls_util import local_names, new_cert, new_key, write_pem

    out: dict[str, Path] = {}
    ca_key = new_key()
    ca = new_cert("roles test CA", ca_key)
    out["ca_crt"], out["ca_key"] = write_pem(d / "ca", ca, ca_key)
    for stem, cn, san in (
        ("server", "localhost", local_names()),
        ("node", "fleet node", [x509.DNSName("node-7.fleet")]),  # named by its SAN
        ("car", "car-a", None),  # named by its CN
        ("stranger", "stranger", None),
    ):
        k = new_key()
        out[stem + "_crt"], out[stem + "_key"] = write_pem(d / stem, new_cert(cn, k, ca, ca_key, san=san), k)
    return out


def test_mutual_tls_client_certificate_names_the_identity(tmp_path):
    pytest.importorskip("cryptography")
    pki = _pki(tmp_path)
    ids = tmp_path / "ids.toml"
    ids.write_text(
        '[[identity]]\nname = "node-7.fleet"\nrole = "vehicle"\nvehicle_prefixes = ["node7/"]\n'
        '[[identity]]\nname = "car-a"\nrole = "vehicle"\nvehicles = ["car-a"]\n'
        f'[[identity]]\nname = "ops"\nrole = "operator"\ntoken_sha256 = "{hash_token(TOKENS["op"])}"\n'
    )
    cfg = local_config(
        tls_cert=pki["server_crt"],
        tls_key=pki["server_key"],
        client_ca=pki["ca_crt"],
        identities=ids,
        batch_processes=0,
    )

    def channel(stem: str) -> grpc.Channel:
        creds = grpc.ssl_channel_credentials(
            root_certificates=pki["ca_crt"].read_bytes(),
            private_key=pki[stem + "_key"].read_bytes(),
            certificate_chain=pki[stem + "_crt"].read_bytes(),
        )
        return grpc.secure_channel(f"localhost:{port}", creds)

    with running(cfg, {"city": AMAP.graph}) as (_, port):
        with channel("node") as ch:
            api = pb_grpc.MapMatchStub(ch)
            assert api.SnapFix(fix("node7/1"), timeout=10).vehicle_id == "node7/1"
            assert refused(api.SnapFix, fix("car-a")).code() == DENIED
            assert refused(api.UnloadMap, pb.UnloadMapRequest(map_id="city")).code() == DENIED
        with channel("car") as ch:
            api = pb_grpc.MapMatchStub(ch)
            assert api.SnapFix(fix("car-a"), timeout=10).vehicle_id == "car-a"
            assert refused(api.SnapFix, fix("node7/1")).code() == DENIED
        with channel("stranger") as ch:
            api = pb_grpc.MapMatchStub(ch)
            assert refused(api.ListMaps, pb.ListMapsRequest()).code() == grpc.StatusCode.UNAUTHENTICATED
            # a token wins over the certificate: the operator's token on a stranger's connection
            assert api.ListMaps(pb.ListMapsRequest(), timeout=10, metadata=md("op")).maps


def test_a_refused_fix_does_not_move_another_vehicles_session_with_the_store(tmp_path):
    pytest.importorskip("redis")
    from failover_util import redis_server

    path = _identities(tmp_path / "ids.json")
    with redis_server(tmp_path / "redis") as rport:
        cfg = local_config(
            identities=path,
            batch_processes=0,
            session_store=f"redis://127.0.0.1:{rport}/0",
            checkpoint_interval=0.1,
        )
        with (
            running(cfg, {"city": AMAP.graph}) as (srv, port),
            grpc.insecure_channel(f"127.0.0.1:{port}") as ch,
        ):
            api = pb_grpc.MapMatchStub(ch)
            assert api.SnapFix(fix("car-b"), timeout=10, metadata=md("b")).vehicle_id == "car-b"
            # A's stream names B's vehicle: refused, and B's session stays where it is (a
            # stream's own vehicles are handed over to the store and dropped when it ends)
            out = list(api.StreamFixes(iter([fix("car-a"), fix("car-b", 1)]), timeout=10, metadata=md("a")))
            assert [r.HasField("error") for r in out] == [False, True]
            deadline = time.monotonic() + 10
            while srv.sessions.live(("city", "car-a")) is not None:  # A's own: handed over
                assert time.monotonic() < deadline
                time.sleep(0.05)
            assert srv.sessions.live(("city", "car-b")) is not None


@pytest.mark.slow  # a serve process reloading its identities
def test_sighup_reads_the_identities_file_again(tmp_path):
    import signal
    import subprocess
    import sys

    from graph.artifact import save_map

    save_map(AMAP.graph, tmp_path / "city.map")
    path = _identities(tmp_path / "ids.json")
    cmd = [sys.executable, "-m", "mapmatch", "serve", "--map", f"city={tmp_path / 'city.map'}",
           "--address", "127.0.0.1:0", "--identities", str(path), "--batch-processes", "0"]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env, cwd=ROOT
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "listening on" in line, line
        port = int(line.split("listening on ")[1].split()[0].rsplit(":", 1)[1])
        with grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
            api = pb_grpc.MapMatchStub(ch)
            assert refused(api.SnapFix, fix("car-c"), metadata=md("a")).code() == DENIED
            before = path.stat()
            _identities(path, car_a={"vehicles": ["car-a", "car-c"]})
            os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns))  # only the signal tells
            time.sleep(1.2)
            assert refused(api.SnapFix, fix("car-c"), metadata=md("a")).code() == DENIED
            proc.send_signal(signal.SIGHUP)
            deadline = time.monotonic() + 10
            while True:
                try:
                    assert api.SnapFix(fix("car-c"), timeout=10, metadata=md("a")).vehicle_id == "car-c"
                    break
                except grpc.RpcError as exc:
                    assert exc.code() == DENIED and time.monotonic() < deadline
                    time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_the_operator_has_no_quota_unless_its_own(tmp_path):
    path = _identities(tmp_path / "ids.json", car_a={"max_sessions": 1})
    cfg = local_config(identities=path, token="fleet", max_identity_sessions=1, batch_processes=0)
    with running(cfg, {"city": AMAP.graph}) as (_, port), grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
        api = pb_grpc.MapMatchStub(ch)
        for i in range(3):  # the --token operator (a whole fleet, maybe): no default quota
            assert api.SnapFix(fix(f"fleet-{i}"), timeout=10, metadata=md("fleet")).vehicle_id == f"fleet-{i}"
        api.SnapFix(fix("node7/1"), timeout=10, metadata=md("node"))  # a vehicle: the default, 1
        e = refused(api.SnapFix, fix("node7/2"), metadata=md("node"))
        assert e.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        # an empty vehicle id is named by the request's validation, not taken for another vehicle
        e = refused(api.SnapFix, fix(""), metadata=md("node"))
        assert (e.code(), e.details()) == (grpc.StatusCode.INVALID_ARGUMENT, "vehicle_id: is required")
