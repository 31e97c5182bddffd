"""Every error the service raises, and the one table mapping errors to gRPC statuses.

Domain errors (:mod:`mapmatch.errors`, :mod:`graph.errors`) and the service's own errors below
become precise statuses in :func:`status_for`; the offending field, or the limit, is named
in the message and in the trailing metadata key ``mapmatch-field``. Anything else is
INTERNAL, logged with its traceback, and never reaches the client.
"""

from __future__ import annotations

import logging

import grpc

from graph.errors import GraphError
from mapmatch.errors import ConfigError, MatchError, ValidationError

errlog = logging.getLogger("mapmatch.service")

__all__ = [
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
