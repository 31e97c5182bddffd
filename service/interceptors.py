"""Server interceptors: bearer-token auth, error mapping and structured access logs.

* Auth: when a token is configured, every call but health checks needs the metadata
  ``authorization: Bearer <token>``; otherwise UNAUTHENTICATED.
* Errors: exceptions from the ``mapmatch``/``graph`` hierarchies become precise statuses
  (:func:`status_for`); the offending field is named in the details and in the trailing
  metadata key ``mapmatch-field``. Anything else is INTERNAL, logged with its traceback,
  and never reaches the client.
* Access log: one structured line per call on logger ``mapmatch.access`` with method, peer,
  status, duration, message counts, the method's running call count and, for bidirectional
  streams, per-message latency (p50/max).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import inspect
import json
import logging
import threading
import time
from collections import Counter, defaultdict, deque
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import grpc
from grpc import aio

from graph.errors import GraphError
from mapmatch.errors import ConfigError, MatchError, ValidationError
from service.maps import MapNotFoundError
from service.sessions import SessionExistsError, SessionLimitError, SessionNotFoundError

log = logging.getLogger("mapmatch.access")
errlog = logging.getLogger("mapmatch.service")

FIELD_METADATA_KEY = "mapmatch-field"
HEALTH_PREFIX = "/grpc.health.v1.Health/"


def status_for(exc: BaseException) -> tuple[grpc.StatusCode, str, str]:
    """``(status, field, message)`` for an exception raised while serving a request."""
    if isinstance(exc, ValidationError):
        return grpc.StatusCode.INVALID_ARGUMENT, exc.field, str(exc)
    if isinstance(exc, MapNotFoundError):
        return grpc.StatusCode.NOT_FOUND, "map_id", str(exc)
    if isinstance(exc, SessionNotFoundError):
        return grpc.StatusCode.NOT_FOUND, exc.field, str(exc)
    if isinstance(exc, SessionLimitError):
        return grpc.StatusCode.RESOURCE_EXHAUSTED, "", str(exc)
    if isinstance(exc, SessionExistsError):
        return grpc.StatusCode.ALREADY_EXISTS, "vehicle_id", str(exc)
    if isinstance(exc, FileNotFoundError):
        return grpc.StatusCode.NOT_FOUND, "path", f"path: no such file: {exc.filename}"
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


class Metrics:
    """Running call counts per method and status, and per-method latency totals (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.calls: Counter[str] = Counter()
        self.codes: Counter[tuple[str, str]] = Counter()
        self.seconds: defaultdict[str, float] = defaultdict(float)
        self.messages: Counter[str] = Counter()

    def record(self, method: str, code: str, seconds: float, messages: int) -> int:
        with self._lock:
            self.calls[method] += 1
            self.codes[(method, code)] += 1
            self.seconds[method] += seconds
            self.messages[method] += messages
            return self.calls[method]

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            return {
                m: {
                    "calls": self.calls[m],
                    "messages": self.messages[m],
                    "mean_ms": 1000.0 * self.seconds[m] / max(self.calls[m], 1),
                    "codes": {c: n for (mm, c), n in self.codes.items() if mm == m},
                }
                for m in sorted(self.calls)
            }


class _CallLog:
    """Collects what one call's access-log line reports."""

    __slots__ = ("code", "lat", "method", "n_in", "n_out", "pending", "t0")

    def __init__(self, method: str) -> None:
        self.method = method
        self.t0 = time.perf_counter()
        self.code = "OK"
        self.n_in = 0
        self.n_out = 0
        self.pending: deque[float] = deque()
        self.lat: deque[float] = deque(maxlen=4096)  # recent per-message latencies, bounded


class ServiceInterceptor(aio.ServerInterceptor):
    """Auth, error mapping and access logging for every RPC of the aio server.

    Parameters
    ----------
    token
        Required bearer token, or None for no auth.
    metrics
        Where call counts and latencies accumulate.
    log_format
        ``"json"`` or ``"text"``.
    """

    def __init__(self, *, token: str | None, metrics: Metrics, log_format: str = "json") -> None:
        self._expected = f"Bearer {token}".encode() if token else None
        self.metrics = metrics
        self.log_format = log_format

    # ------------------------------------------------------------------ auth
    def _authorised(self, details: grpc.HandlerCallDetails) -> bool:
        if self._expected is None or details.method.startswith(HEALTH_PREFIX):
            return True
        for key, value in details.invocation_metadata or ():
            if key == "authorization":
                v = value.encode() if isinstance(value, str) else value
                return hmac.compare_digest(v, self._expected)
        return False

    # ------------------------------------------------------------------ logging
    def _finish(self, call: _CallLog, context: aio.ServicerContext) -> None:
        dt = time.perf_counter() - call.t0
        n = self.metrics.record(call.method, call.code, dt, call.n_in + call.n_out)
        if not log.isEnabledFor(logging.INFO):
            return
        rec: dict[str, Any] = {
            "event": "rpc",
            "method": call.method,
            "peer": context.peer(),
            "code": call.code,
            "ms": round(dt * 1000.0, 3),
            "in": call.n_in,
            "out": call.n_out,
            "calls": n,
        }
        if call.lat:
            s = sorted(call.lat)
            rec["msg_p50_ms"] = round(1000.0 * s[len(s) // 2], 3)
            rec["msg_max_ms"] = round(1000.0 * s[-1], 3)
        if self.log_format == "json":
            log.info(json.dumps(rec))
        else:
            log.info(" ".join(f"{k}={v}" for k, v in rec.items()))

    async def _fail(self, call: _CallLog, context: aio.ServicerContext, exc: BaseException) -> None:
        code, fld, msg = status_for(exc)
        if code is grpc.StatusCode.INTERNAL:
            log_internal(exc, call.method)
        call.code = code.name
        if fld:
            context.set_trailing_metadata(((FIELD_METADATA_KEY, fld),))
        await context.abort(code, msg)

    @contextlib.asynccontextmanager
    async def _guard(self, call: _CallLog, context: aio.ServicerContext) -> AsyncIterator[None]:
        """Around a handler: map its exception to a status (:meth:`_fail`), note the status
        of an abort or cancellation, and always write the access-log line."""
        try:
            yield
        except asyncio.CancelledError:
            call.code = grpc.StatusCode.CANCELLED.name
            raise
        except aio.AbortError:
            if call.code == "OK":
                call.code = _code_name(context)
            raise
        except Exception as exc:
            await self._fail(call, context, exc)
        finally:
            self._finish(call, context)

    # ------------------------------------------------------------------ wrapping
    async def intercept_service(
        self,
        continuation: Callable[[grpc.HandlerCallDetails], Awaitable[grpc.RpcMethodHandler]],
        handler_call_details: grpc.HandlerCallDetails,
    ) -> grpc.RpcMethodHandler:
        handler = await continuation(handler_call_details)
        if handler is None:
            return handler
        method = handler_call_details.method
        authorised = self._authorised(handler_call_details)
        if handler.request_streaming and handler.response_streaming:
            inner = handler.stream_stream
            factory = grpc.stream_stream_rpc_method_handler
            wrapped = self._wrap_stream_stream(method, inner, authorised)
        elif handler.request_streaming:
            inner = handler.stream_unary
            factory = grpc.stream_unary_rpc_method_handler
            wrapped = self._wrap_unary(method, inner, authorised, streaming_in=True)
        elif handler.response_streaming:
            inner = handler.unary_stream
            factory = grpc.unary_stream_rpc_method_handler
            wrapped = self._wrap_unary_stream(method, inner, authorised)
        else:
            inner = handler.unary_unary
            factory = grpc.unary_unary_rpc_method_handler
            wrapped = self._wrap_unary(method, inner, authorised, streaming_in=False)
        return factory(
            wrapped,
            request_deserializer=handler.request_deserializer,
            response_serializer=handler.response_serializer,
        )

    async def _deny(self, call: _CallLog, context: aio.ServicerContext) -> None:
        call.code = grpc.StatusCode.UNAUTHENTICATED.name
        await context.abort(grpc.StatusCode.UNAUTHENTICATED, "missing or invalid bearer token")

    def _count_in(self, call: _CallLog, it: AsyncIterator[Any], *, timed: bool) -> AsyncIterator[Any]:
        async def gen() -> AsyncIterator[Any]:
            async for m in it:
                call.n_in += 1
                if timed:
                    call.pending.append(time.perf_counter())
                yield m

        return gen()

    def _wrap_unary(self, method: str, inner: Any, authorised: bool, *, streaming_in: bool) -> Any:
        async def behaviour(request: Any, context: aio.ServicerContext) -> Any:
            call = _CallLog(method)
            async with self._guard(call, context):
                if not authorised:
                    await self._deny(call, context)
                if streaming_in:
                    request = self._count_in(call, request, timed=False)
                else:
                    call.n_in = 1
                result = inner(request, context)
                if asyncio.iscoroutine(result):
                    result = await result
                call.n_out = 1
                return result
            return None  # the guard handled an error (the call was aborted)

        return behaviour

    def _wrap_unary_stream(self, method: str, inner: Any, authorised: bool) -> Any:
        if not inspect.isasyncgenfunction(inner):  # reader/writer style (e.g. health Watch)
            return self._wrap_unary(method, inner, authorised, streaming_in=False)

        async def behaviour(request: Any, context: aio.ServicerContext) -> AsyncIterator[Any]:
            call = _CallLog(method)
            call.n_in = 1
            async with self._guard(call, context):
                if not authorised:
                    await self._deny(call, context)
                async for resp in inner(request, context):
                    call.n_out += 1
                    yield resp

        return behaviour

    def _wrap_stream_stream(self, method: str, inner: Any, authorised: bool) -> Any:
        if not inspect.isasyncgenfunction(inner):  # reader/writer style (e.g. reflection)
            return self._wrap_unary(method, inner, authorised, streaming_in=True)

        async def behaviour(request_iterator: Any, context: aio.ServicerContext) -> AsyncIterator[Any]:
            call = _CallLog(method)
            async with self._guard(call, context):
                if not authorised:
                    await self._deny(call, context)
                async for resp in inner(self._count_in(call, request_iterator, timed=True), context):
                    call.n_out += 1
                    if call.pending:
                        call.lat.append(time.perf_counter() - call.pending.popleft())
                    yield resp

        return behaviour


def _code_name(context: aio.ServicerContext) -> str:
    try:
        code = context.code()
    except Exception:  # older grpc: no code() on aio contexts
        return "ABORTED_BY_HANDLER"
    if isinstance(code, grpc.StatusCode):
        return code.name
    return str(code) if code is not None else "UNKNOWN"
