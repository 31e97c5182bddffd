"""Server reflection, both versions clients ask for: ``grpc.reflection.v1`` (grpcurl and
current tools) and ``grpc.reflection.v1alpha`` (older ones).

grpcio-reflection implements v1alpha. The v1 protocol has the same messages, field for
field, in the package ``grpc.reflection.v1``: :func:`enable_reflection` registers the v1
descriptors (the v1alpha file under the v1 names) and serves the v1 method with the same
servicer, the bytes on the wire being identical.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import grpc
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from grpc import aio
from grpc_reflection.v1alpha import reflection, reflection_pb2
from grpc_reflection.v1alpha._async import ReflectionServicer

__all__ = ["V1_FILE", "V1_SERVICE", "enable_reflection", "v1_messages"]

V1_PACKAGE = "grpc.reflection.v1"
V1_FILE = "grpc/reflection/v1/reflection.proto"
V1_SERVICE = f"{V1_PACKAGE}.ServerReflection"
_ALPHA = f".{reflection_pb2.DESCRIPTOR.package}."


def _v1_file() -> descriptor_pb2.FileDescriptorProto:
    """The v1 reflection file: v1alpha's messages and service under the v1 package."""
    fdp = descriptor_pb2.FileDescriptorProto()
    reflection_pb2.DESCRIPTOR.CopyToProto(fdp)
    fdp.name, fdp.package = V1_FILE, V1_PACKAGE
    fdp.ClearField("options")

    def rename(messages: Iterable[descriptor_pb2.DescriptorProto]) -> None:
        for msg in messages:
            for f in msg.field:
                if f.HasField("type_name"):
                    f.type_name = f.type_name.replace(_ALPHA, f".{V1_PACKAGE}.")
            rename(msg.nested_type)

    rename(fdp.message_type)
    for svc in fdp.service:
        for m in svc.method:
            m.input_type = m.input_type.replace(_ALPHA, f".{V1_PACKAGE}.")
            m.output_type = m.output_type.replace(_ALPHA, f".{V1_PACKAGE}.")
    return fdp


def _ensure_v1(pool: Any) -> None:
    """Add the v1 file to ``pool`` unless it is there (another library may have added it)."""
    try:
        pool.FindFileByName(V1_FILE)
    except KeyError:
        pool.AddSerializedFile(_v1_file().SerializeToString())


def v1_messages() -> tuple[type[Any], type[Any]]:
    """The v1 ``ServerReflectionRequest`` and ``ServerReflectionResponse`` classes (for clients)."""
    pool = descriptor_pool.Default()
    _ensure_v1(pool)
    req = pool.FindMessageTypeByName(f"{V1_PACKAGE}.ServerReflectionRequest")
    resp = pool.FindMessageTypeByName(f"{V1_PACKAGE}.ServerReflectionResponse")
    return message_factory.GetMessageClass(req), message_factory.GetMessageClass(resp)


def enable_reflection(service_names: Iterable[str], server: aio.Server) -> None:
    """Serve reflection v1 and v1alpha on ``server``, listing ``service_names`` and both
    reflection services."""
    _ensure_v1(descriptor_pool.Default())
    names = (*service_names, reflection.SERVICE_NAME, V1_SERVICE)
    reflection.enable_server_reflection(names, server)
    servicer = ReflectionServicer(names)
    handler = grpc.stream_stream_rpc_method_handler(
        servicer.ServerReflectionInfo,
        request_deserializer=reflection_pb2.ServerReflectionRequest.FromString,
        response_serializer=reflection_pb2.ServerReflectionResponse.SerializeToString,
    )
    server.add_generic_rpc_handlers(
        (grpc.method_handlers_generic_handler(V1_SERVICE, {"ServerReflectionInfo": handler}),)
    )
