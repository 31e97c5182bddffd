"""gRPC conventions: server reflection v1 beside v1alpha, and errors that carry a
``google.rpc.Status`` naming the field, on a real server on a loopback port."""

from __future__ import annotations

import grpc
import pytest
from google.protobuf import descriptor_pb2
from google.rpc import error_details_pb2
from grpc_reflection.v1alpha import reflection_pb2 as alpha
from grpc_status import rpc_status
from service_util import city, local_config, running, stub

from service.gen import mapmatch_pb2 as pb
from service.reflection import v1_messages

AMAP = city()


def _reflect(port: int, method: str, request, response_type) -> list:
    with grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
        call = ch.stream_stream(
            method, request_serializer=type(request).SerializeToString,
            response_deserializer=response_type.FromString,
        )  # fmt: skip
        return list(call(iter([request]), timeout=10))


def test_reflection_v1_and_v1alpha_list_and_describe_the_service():
    req_v1, resp_v1 = v1_messages()
    with running(local_config(), {"city": AMAP.graph}) as (_, port):
        for method, req, resp in (
            ("/grpc.reflection.v1.ServerReflection/ServerReflectionInfo", req_v1, resp_v1),
            ("/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
             alpha.ServerReflectionRequest, alpha.ServerReflectionResponse),
        ):  # fmt: skip
            (listed,) = _reflect(port, method, req(list_services=""), resp)
            names = {s.name for s in listed.list_services_response.service}
            assert {"mapmatch.v1.MapMatch", "grpc.health.v1.Health"} <= names
            assert {
                "grpc.reflection.v1.ServerReflection",
                "grpc.reflection.v1alpha.ServerReflection",
            } <= names
            (found,) = _reflect(port, method, req(file_containing_symbol="mapmatch.v1.MapMatch"), resp)
            files = [
                descriptor_pb2.FileDescriptorProto.FromString(b)
                for b in found.file_descriptor_response.file_descriptor_proto
            ]
            services = {f"{f.package}.{s.name}" for f in files for s in f.service}
            assert "mapmatch.v1.MapMatch" in services
        (v1file,) = _reflect(
            port,
            "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo",
            req_v1(file_containing_symbol="grpc.reflection.v1.ServerReflection"),
            resp_v1,
        )
        fd = descriptor_pb2.FileDescriptorProto.FromString(
            v1file.file_descriptor_response.file_descriptor_proto[0]
        )
        assert fd.package == "grpc.reflection.v1" and fd.service[0].name == "ServerReflection"


def _status(err: grpc.RpcError):
    status = rpc_status.from_call(err)  # checks code and message agree with the call's
    assert status is not None, "no google.rpc.Status on the error"
    return status


def _unpack(status, kind):
    out = []
    for d in status.details:
        if d.Is(kind.DESCRIPTOR):
            msg = kind()
            d.Unpack(msg)
            out.append(msg)
    return out


def test_errors_carry_a_google_rpc_status_naming_the_field():
    with running(local_config(max_track_points=10), {"city": AMAP.graph}) as (_, port):
        ch, api = stub(port)
        bad = pb.FixRequest(vehicle_id="v", fix=pb.Fix(time=0.0, lat=95.0, lon=24.0, heading=0.0))
        with pytest.raises(grpc.RpcError) as ei:
            api.SnapFix(bad, timeout=10)
        err = ei.value
        assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
        status = _status(err)
        (br,) = _unpack(status, error_details_pb2.BadRequest)
        assert [v.field for v in br.field_violations] == ["fix.lat"]
        assert br.field_violations[0].description == err.details()
        (info,) = _unpack(status, error_details_pb2.ErrorInfo)
        assert info.domain == "mapmatch" and info.metadata["field"] == "fix.lat"
        assert dict(err.trailing_metadata())["mapmatch-field"] == "fix.lat"  # kept beside it
        # a limit: QuotaFailure naming the limit
        track = pb.Track(track_id="t", time=[float(i) for i in range(20)], lat=[60.0] * 20, lon=[24.0] * 20)
        with pytest.raises(grpc.RpcError) as ei:
            api.MatchTrack(pb.MatchTrackRequest(track=track), timeout=30)
        assert ei.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        (quota,) = _unpack(_status(ei.value), error_details_pb2.QuotaFailure)
        assert quota.violations[0].subject == "max_track_points"
        # NOT_FOUND: ErrorInfo with the field
        with pytest.raises(grpc.RpcError) as ei:
            api.GetMapInfo(pb.GetMapInfoRequest(map_id="nowhere"), timeout=10)
        assert ei.value.code() == grpc.StatusCode.NOT_FOUND
        (info,) = _unpack(_status(ei.value), error_details_pb2.ErrorInfo)
        assert info.reason == "NOT_FOUND" and info.metadata["field"] == "map_id"
        ch.close()
