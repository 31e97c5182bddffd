"""TLS, mutual TLS and the bearer token, with a throwaway CA made in the test (``cryptography``)."""

from __future__ import annotations

from pathlib import Path

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from online_helpers import drive
from service_util import city, local_config, running
from tls_util import local_names, new_cert, new_key, write_pem

from mapmatch.errors import ConfigError
from service.client import MapMatchClient
from service.gen import mapmatch_pb2 as pb
from service.gen import mapmatch_pb2_grpc as pb_grpc

AMAP = city()


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("pki")
    ca_key = new_key()
    ca = new_cert("test CA", ca_key)
    other_key = new_key()
    other_ca = new_cert("other CA", other_key)
    out: dict[str, Path] = {}
    out["ca"], _ = write_pem(d / "ca", ca, ca_key)
    out["other_ca"], _ = write_pem(d / "other_ca", other_ca, other_key)
    sk, ck, rk = new_key(), new_key(), new_key()
    local = local_names()
    out["server_crt"], out["server_key"] = write_pem(
        d / "server", new_cert("localhost", sk, ca, ca_key, san=local), sk
    )
    out["client_crt"], out["client_key"] = write_pem(
        d / "client", new_cert("vehicle-node-1", ck, ca, ca_key, san=local), ck
    )
    out["rogue_crt"], out["rogue_key"] = write_pem(
        d / "rogue", new_cert("rogue", rk, other_ca, other_key, san=local), rk
    )
    return out


def _fix_req() -> pb.FixRequest:
    from service import convert

    return pb.FixRequest(vehicle_id="v", fix=convert.fix_to_proto(drive(AMAP, "ab")[0]))


def test_tls_serves_verified_clients_and_refuses_plain_ones(pki):
    cfg = local_config(tls_cert=pki["server_crt"], tls_key=pki["server_key"])
    with running(cfg, {"city": AMAP.graph}) as (_, port):
        with MapMatchClient(f"localhost:{port}", tls_ca=pki["ca"]) as client:
            assert client.list_maps(timeout=10).maps[0].map_id == "city"
            assert client.snap("v", drive(AMAP, "ab")[0]).time == 0.0
        # a plain-text client cannot talk to a TLS server
        ch = grpc.insecure_channel(f"127.0.0.1:{port}")
        with pytest.raises(grpc.RpcError) as ei:
            pb_grpc.MapMatchStub(ch).ListMaps(pb.ListMapsRequest(), timeout=3)
        assert ei.value.code() == grpc.StatusCode.UNAVAILABLE
        ch.close()
        # a client trusting another CA refuses the server
        with (
            MapMatchClient(f"localhost:{port}", tls_ca=pki["other_ca"]) as client,
            pytest.raises(grpc.RpcError),
        ):
            client.list_maps(timeout=3)


def test_mutual_tls_needs_a_client_certificate_from_the_ca(pki):
    cfg = local_config(tls_cert=pki["server_crt"], tls_key=pki["server_key"], client_ca=pki["ca"])
    with running(cfg, {"city": AMAP.graph}) as (_, port):
        with MapMatchClient(
            f"localhost:{port}", tls_ca=pki["ca"], client_cert=pki["client_crt"], client_key=pki["client_key"]
        ) as client:
            assert client.list_maps(timeout=10).maps
        with (
            MapMatchClient(f"localhost:{port}", tls_ca=pki["ca"]) as client,
            pytest.raises(grpc.RpcError) as ei,
        ):
            client.list_maps(timeout=3)
        assert ei.value.code() == grpc.StatusCode.UNAVAILABLE
        with (
            MapMatchClient(
                f"localhost:{port}",
                tls_ca=pki["ca"],
                client_cert=pki["rogue_crt"],
                client_key=pki["rogue_key"],
            ) as client,
            pytest.raises(grpc.RpcError) as ei,
        ):
            client.list_maps(timeout=3)
        assert ei.value.code() == grpc.StatusCode.UNAVAILABLE


def test_bearer_token_is_checked_on_every_call_but_health(pki):
    with running(local_config(token="s3cret"), {"city": AMAP.graph}) as (_, port):
        ch = grpc.insecure_channel(f"127.0.0.1:{port}")
        api = pb_grpc.MapMatchStub(ch)
        for md in [(), (("authorization", "Bearer wrong"),), (("authorization", "s3cret"),)]:
            with pytest.raises(grpc.RpcError) as ei:
                api.SnapFix(_fix_req(), timeout=5, metadata=md)
            assert ei.value.code() == grpc.StatusCode.UNAUTHENTICATED
            with pytest.raises(grpc.RpcError) as ei:
                list(api.StreamFixes(iter([_fix_req()]), timeout=5, metadata=md))
            assert ei.value.code() == grpc.StatusCode.UNAUTHENTICATED
            with pytest.raises(grpc.RpcError) as ei:
                list(api.MatchTracks(pb.MatchTracksRequest(), timeout=5, metadata=md))
            assert ei.value.code() == grpc.StatusCode.UNAUTHENTICATED
        good = (("authorization", "Bearer s3cret"),)
        assert api.SnapFix(_fix_req(), timeout=5, metadata=good).result.time == 0.0
        assert next(api.StreamFixes(iter([_fix_req()]), timeout=5, metadata=good)).result
        # probes need no token
        health = health_pb2_grpc.HealthStub(ch)
        st = health.Check(health_pb2.HealthCheckRequest(service=""), timeout=5).status
        assert st == health_pb2.HealthCheckResponse.SERVING
        ch.close()
        with MapMatchClient(f"127.0.0.1:{port}", token="s3cret") as client:
            assert client.list_maps().maps


def test_tls_config_must_be_complete_and_readable(tmp_path, pki):
    with pytest.raises(ConfigError):
        local_config(tls_cert=pki["server_crt"])
    with pytest.raises(ConfigError):
        local_config(client_ca=pki["ca"])
    with (
        pytest.raises(ConfigError, match="cannot read TLS file"),
        running(
            local_config(tls_cert=tmp_path / "nope.crt", tls_key=pki["server_key"]), {"city": AMAP.graph}
        ),
    ):
        pass
