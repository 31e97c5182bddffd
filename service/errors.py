"""Every error the service raises, and the one table mapping errors to gRPC statuses.

Domain errors (:mod:`mapmatch.errors`, :mod:`graph.errors`) and the service's own errors below
become precise statuses in :func:`status_for`; the offending field, or the limit, is named
in the message, in the trailing metadata key ``mapmatch-field`` and in a ``google.rpc.Status``
(trailer ``grpc-status-details-bin``, read by ``grpc_status.rpc_status.from_call``, grpcurl
and generated clients) with the details :func:`error_trailers` describes. Anything else is
INTERNAL, logged with its traceback, and never reaches the client.
"""

from __future__ import annotations

import logging
from typing import Any

import grpc
from google.protobuf import any_pb2
from google.rpc import error_details_pb2, status_pb2

from graph.errors import GraphError
from mapmatch.errors import ConfigError, MatchError, ValidationError

errlog = logging.getLogger("mapmatch.service")

FIELD_METADATA_KEY = "mapmatch-field"
STATUS_DETAILS_KEY = "grpc-status-details-bin"
ERROR_DOMAIN = "mapmatch"

__all__ = [
    "ERROR_DOMAIN",
    "FIELD_METADATA_KEY",
    "STATUS_DETAILS_KEY",
    "BatchWorkerError",
    "LimitError",
    "MapLoadError",
    "MapNotFoundError",
    "MapPathError",
    "ServiceError",
    "SessionExistsError",
    "SessionLimitError",
    "SessionNotFoundError",
    "StatusError",
    "error_trailers",
    "log_internal",
    "status_for",
]


class ServiceError(MatchError):
    """Base of the service's own errors."""

    field = ""


class MapNotFoundError(ServiceError, LookupError):
    """A request named a map this server has not loaded (NOT_FOUND)."""

    field = "map_id"

    def __init__(self, map_id: str, known: list[str]) -> None:
        have = ", ".join(known) if known else "none"
        msg = f"map_id: unknown map {map_id!r} (loaded: {have})" if map_id else "map_id: no map is loaded"
        super().__init__(msg)
        self.map_id = map_id


class MapPathError(ServiceError):
    """``LoadMap`` named a path the server will not read (PERMISSION_DENIED).

    One message for every reason (outside ``--map-dir``, missing, not a regular file, no
    ``--map-dir`` at all), so the answer tells nothing about the server's disk.
    """

    field = "path"

    def __init__(self) -> None:
        super().__init__(
            "path: not a map file this server may load (LoadMap reads only regular files inside "
            "the server's --map-dir)"
        )


class MapLoadError(ServiceError):
    """A map file was read but cannot be served: corrupt, no roads, failed warm-up, or over
    the time/memory limits of a load (INVALID_ARGUMENT). A map it would replace stays."""

    field = "path"


class LimitError(ServiceError):
    """A request exceeds a configured limit (RESOURCE_EXHAUSTED); ``field`` names the limit."""

    def __init__(self, limit: str, message: str) -> None:
        super().__init__(f"{limit}: {message}")
        self.field = limit


class SessionLimitError(LimitError):
    """The server holds its maximum number of sessions (RESOURCE_EXHAUSTED)."""

    def __init__(self, message: str) -> None:
        super().__init__("max_sessions", message)


class SessionExistsError(ServiceError):
    """An imported session would replace a live one (ALREADY_EXISTS)."""

    field = "vehicle_id"


class SessionNotFoundError(ServiceError, LookupError):
    """No live session for that vehicle (NOT_FOUND)."""

    field = "vehicle_id"


class StatusError(ServiceError):
    """An error that already carries its status: a batch worker process's answer."""

    def __init__(self, code: grpc.StatusCode, field: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.field = field


class BatchWorkerError(StatusError):
    """A batch worker process ended during a call, or the server is stopping (UNAVAILABLE)."""

    def __init__(self, message: str) -> None:
        super().__init__(grpc.StatusCode.UNAVAILABLE, "", message)


_CODES: tuple[tuple[type[BaseException], grpc.StatusCode], ...] = (
    (ValidationError, grpc.StatusCode.INVALID_ARGUMENT),
    (MapNotFoundError, grpc.StatusCode.NOT_FOUND),
    (SessionNotFoundError, grpc.StatusCode.NOT_FOUND),
    (LimitError, grpc.StatusCode.RESOURCE_EXHAUSTED),
    (SessionExistsError, grpc.StatusCode.ALREADY_EXISTS),
    (MapPathError, grpc.StatusCode.PERMISSION_DENIED),
    (MapLoadError, grpc.StatusCode.INVALID_ARGUMENT),
)


def status_for(exc: BaseException) -> tuple[grpc.StatusCode, str, str]:
    """``(status, field, message)`` for an exception raised while serving a request."""
    if isinstance(exc, StatusError):
        return exc.code, exc.field, str(exc)
    for kind, code in _CODES:
        if isinstance(exc, kind):
            return code, str(getattr(exc, "field", "")), str(exc)
    if isinstance(exc, GraphError):
        return grpc.StatusCode.INVALID_ARGUMENT, "path", f"path: {exc}"
    if isinstance(exc, ConfigError | MatchError):
        return grpc.StatusCode.INVALID_ARGUMENT, "", str(exc)
    if isinstance(exc, ModuleNotFoundError | NotImplementedError):
        return grpc.StatusCode.UNIMPLEMENTED, "", "this server lacks that matcher"
    return grpc.StatusCode.INTERNAL, "", "internal error"


def log_internal(exc: BaseException, where: str) -> None:
    """Log an unexpected exception with its traceback (the client sees only INTERNAL)."""
    errlog.error("unexpected error in %s: %r", where, exc, exc_info=exc)


def error_trailers(code: grpc.StatusCode, field: str, message: str) -> tuple[tuple[str, str | bytes], ...]:
    """The trailing metadata of an error: ``mapmatch-field`` (when a field is named) and a
    ``google.rpc.Status`` of ``code`` and ``message`` whose details name the field.

    The details: ``BadRequest.FieldViolation`` for INVALID_ARGUMENT, ``QuotaFailure`` (the
    limit as subject) for RESOURCE_EXHAUSTED, ``PreconditionFailure`` for
    FAILED_PRECONDITION, and for every error with a field an ``ErrorInfo`` (reason the
    status name, domain ``mapmatch``, metadata ``field``).
    """
    status = status_pb2.Status(code=code.value[0], message=message)
    details: list[Any] = []
    ed = error_details_pb2
    if field:
        if code is grpc.StatusCode.INVALID_ARGUMENT:
            violation = ed.BadRequest.FieldViolation(field=field, description=message)
            details.append(ed.BadRequest(field_violations=[violation]))
        elif code is grpc.StatusCode.RESOURCE_EXHAUSTED:
            quota = ed.QuotaFailure.Violation(subject=field, description=message)
            details.append(ed.QuotaFailure(violations=[quota]))
        elif code is grpc.StatusCode.FAILED_PRECONDITION:
            failed = ed.PreconditionFailure.Violation(type=code.name, subject=field, description=message)
            details.append(ed.PreconditionFailure(violations=[failed]))
        details.append(ed.ErrorInfo(reason=code.name, domain=ERROR_DOMAIN, metadata={"field": field}))
    for d in details:
        packed = any_pb2.Any()
        packed.Pack(d)
        status.details.append(packed)
    out: list[tuple[str, str | bytes]] = [(FIELD_METADATA_KEY, field)] if field else []
    out.append((STATUS_DETAILS_KEY, status.SerializeToString()))
    return tuple(out)
