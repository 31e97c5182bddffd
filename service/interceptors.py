"""Server interceptors, one concern each (in the order they wrap a call, outermost first).

The concerns run in one :class:`Chain` (the one gRPC interceptor): each keeps its own class
and hooks, but a streamed message passes through one wrapper, not one per concern.

* :class:`AccessLogInterceptor`: one structured line per call on logger ``mapmatch.access``
  with method, peer, status, duration, message counts, the method's running call count and,
  for bidirectional streams, per-message latency (p50/max); ``json`` gives one JSON object
  per line.
* :class:`AuthInterceptor`: the caller's identity (bearer token or client certificate) and
  the method's rule (:mod:`service.auth`): UNAUTHENTICATED or PERMISSION_DENIED; per-identity
  stream quotas; health ``Watch`` calls capped per connection and in all.
* :class:`StatusInterceptor`: exceptions become precise statuses
  (:func:`service.errors.status_for`), the offending field named in the details, in the
  trailing metadata key ``mapmatch-field`` and in a ``google.rpc.Status``
  (:func:`service.errors.error_trailers`); a request whose bytes do not decode gets
  INVALID_ARGUMENT (not UNKNOWN or INTERNAL, and no traceback).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import inspect
import json
import logging
import threading
import time
from array import array
from collections import Counter, defaultdict, deque
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import grpc
from grpc import aio

from mapmatch.errors import ValidationError
from service.auth import CALLER, AccessError, Identity, IdentityTable, Quotas, Rule, check_vehicle, rule_for
from service.errors import FIELD_METADATA_KEY, LimitError, error_trailers, log_internal, status_for

log = logging.getLogger("mapmatch.access")

LATENCY_RING = 512  # per-message latencies a stream's access-log line is drawn from

__all__ = [
    "FIELD_METADATA_KEY",
    "AccessLogInterceptor",
    "AccessSettings",
    "AuthInterceptor",
    "Chain",
    "Metrics",
    "StatusInterceptor",
    "Undecodable",
    "log_internal",
    "status_for",
    "undecodable_error",
]

Around = Callable[[grpc.HandlerCallDetails, aio.ServicerContext], contextlib.AbstractAsyncContextManager[Any]]


class _Wrapping:
    """One concern of the interceptor chain: hooks run around every call and on its messages.

    :meth:`around` is an async context manager per call (its value is the call's state);
    :meth:`request` sees each request message, :meth:`response` each response message, and
    :meth:`deserializer` may wrap the request deserializer. :class:`Chain` runs the concerns,
    outermost first, in one wrapper per call; a streamed message meets their hooks in the
    call's deserializer (requests) and serializer (responses), so it passes through no
    generator of the chain's, however many concerns there are.
    """

    def around(self, details: grpc.HandlerCallDetails, context: aio.ServicerContext) -> Any:
        return contextlib.nullcontext()

    def request(self, state: Any, req: Any) -> Any:
        return req

    def response(self, state: Any, resp: Any) -> None:
        return None

    def deserializer(self, inner: Any) -> Any:
        return inner

    def handler_found(self, details: grpc.HandlerCallDetails, handler: grpc.RpcMethodHandler) -> None:
        """Called once per call with the handler it will run."""


def _overrides(concern: _Wrapping, name: str) -> bool:
    return getattr(type(concern), name) is not getattr(_Wrapping, name)


class Chain(aio.ServerInterceptor):
    """The gRPC interceptor that runs a list of concerns (:class:`_Wrapping`), outermost first."""

    def __init__(self, concerns: list[_Wrapping]) -> None:
        self.concerns = concerns
        self._arounds = concerns
        self._requests = [i for i, c in enumerate(concerns) if _overrides(c, "request")]
        self._responses = [i for i, c in enumerate(concerns) if _overrides(c, "response")]

    async def intercept_service(
        self,
        continuation: Callable[[grpc.HandlerCallDetails], Awaitable[grpc.RpcMethodHandler]],
        handler_call_details: grpc.HandlerCallDetails,
    ) -> grpc.RpcMethodHandler:
        handler = await continuation(handler_call_details)
        if handler is None:
            return handler
        d = handler_call_details
        for c in self.concerns:
            c.handler_found(d, handler)
        call = _Call(d)
        if handler.request_streaming and handler.response_streaming:
            inner, factory = handler.stream_stream, grpc.stream_stream_rpc_method_handler
            wrapped = self._stream_out(call, inner, streaming_in=True)
        elif handler.request_streaming:
            inner, factory = handler.stream_unary, grpc.stream_unary_rpc_method_handler
            wrapped = self._unary_out(call, inner, streaming_in=True)
        elif handler.response_streaming:
            inner, factory = handler.unary_stream, grpc.unary_stream_rpc_method_handler
            wrapped = self._stream_out(call, inner, streaming_in=False)
        else:
            inner, factory = handler.unary_unary, grpc.unary_unary_rpc_method_handler
            wrapped = self._unary_out(call, inner, streaming_in=False)
        deserializer = handler.request_deserializer
        for c in reversed(self.concerns):  # the outermost concern sees the bytes first
            deserializer = c.deserializer(deserializer)
        if handler.request_streaming and self._requests:
            deserializer = call.streamed(deserializer)
        serializer = handler.response_serializer
        if handler.response_streaming and self._responses:
            serializer = call.answered(serializer)
        return factory(wrapped, request_deserializer=deserializer, response_serializer=serializer)

    async def _enter(
        self, stack: contextlib.AsyncExitStack, d: grpc.HandlerCallDetails, context: aio.ServicerContext
    ) -> list[Any]:
        return [await stack.enter_async_context(c.around(d, context)) for c in self._arounds]

    def _hooks(self, states: list[Any]) -> list[tuple[Callable[[Any, Any], Any], Any]]:
        return [(self._arounds[i].request, states[i]) for i in self._requests]

    def _input(self, call: _Call, states: list[Any], request: Any, streaming_in: bool) -> Any:
        """The request (iterator) the handler gets. A streamed request's hooks run in the
        call's deserializer (:meth:`_Call.streamed`), not in another async-generator layer."""
        if streaming_in:
            call.hooks = self._hooks(states)
            return request
        for hook, st in self._hooks(states):
            request = hook(st, request)
        return request

    def _output(self, states: list[Any]) -> list[tuple[Callable[[Any, Any], None], Any]]:
        return [(self._arounds[i].response, states[i]) for i in reversed(self._responses)]

    def _unary_out(self, call: _Call, inner: Any, *, streaming_in: bool, streaming_out: bool = False) -> Any:
        async def behaviour(request: Any, context: aio.ServicerContext) -> Any:
            async with contextlib.AsyncExitStack() as stack:
                states = await self._enter(stack, call.details, context)
                if streaming_out:  # reader/writer style: each written message meets the hooks
                    call.out = self._output(states)  # in the call's serializer
                result = inner(self._input(call, states, request, streaming_in), context)
                if inspect.isawaitable(result):
                    result = await result
                if not streaming_out:
                    for hook, st in self._output(states):
                        hook(st, result)
                return result
            return None  # a concern handled an error (the call was aborted)

        return behaviour

    def _stream_out(self, call: _Call, inner: Any, *, streaming_in: bool) -> Any:
        """A streamed answer's hooks run in the call's serializer (:meth:`_Call.answered`), as
        gRPC sends each message: the wrapper adds no work per message of its own."""
        if not inspect.isasyncgenfunction(inner):  # reader/writer style (StreamFixes, health Watch)
            return self._unary_out(call, inner, streaming_in=streaming_in, streaming_out=True)

        async def behaviour(request: Any, context: aio.ServicerContext) -> AsyncIterator[Any]:
            async with contextlib.AsyncExitStack() as stack:
                states = await self._enter(stack, call.details, context)
                call.out = self._output(states)
                async for resp in inner(self._input(call, states, request, streaming_in), context):
                    yield resp

        return behaviour


class _Call:
    """One call's place for its request and response hooks, bound once the concerns have
    entered."""

    __slots__ = ("details", "hooks", "out")

    def __init__(self, details: grpc.HandlerCallDetails) -> None:
        self.details = details
        self.hooks: list[tuple[Callable[[Any, Any], Any], Any]] = []
        self.out: list[tuple[Callable[[Any, Any], None], Any]] = []

    def answered(self, inner: Any) -> Callable[[Any], Any]:
        """The serializer of a streamed response: run the response hooks, then serialise.
        gRPC calls it as the handler yields or writes each message, whichever the handler's
        style."""
        dump = inner if inner is not None else (lambda m: m)

        def each(m: Any) -> Any:
            for hook, st in self.out:
                hook(st, m)
            return dump(m)

        return each

    def streamed(self, inner: Any) -> Callable[[bytes], Any]:
        """The deserializer of a streamed request: parse, then run the request hooks. gRPC
        calls it as the handler reads each message (the concerns have entered by then), and
        what a hook raises reaches the handler as if the request iterator had raised it."""
        parse = inner if inner is not None else (lambda data: data)

        def each(data: bytes) -> Any:
            m = parse(data)
            for hook, st in self.hooks:
                m = hook(st, m)
            return m

        return each


# ---------------------------------------------------------------------------------- auth
@dataclasses.dataclass(frozen=True, slots=True)
class AccessSettings:
    """What :class:`AuthInterceptor` enforces.

    Attributes
    ----------
    table : IdentityTable
        The credentials accepted (none configured: every call is allowed).
    quotas : Quotas or None
        Per-identity stream and session quotas.
    max_watch_per_connection, max_watch_total : int
        Concurrent health ``Watch`` calls on one connection, and in all.
    """

    table: IdentityTable
    quotas: Quotas | None
    max_watch_per_connection: int = 16
    max_watch_total: int = 1000


class _Access:
    """One call's caller and rule (the state of :class:`AuthInterceptor`)."""

    __slots__ = ("caller", "rule")

    def __init__(self, caller: Identity | None, rule: Rule) -> None:
        self.caller = caller
        self.rule = rule


class AuthInterceptor(_Wrapping):
    """Identities and roles (:mod:`service.auth`), quotas, and the cap on health ``Watch``.

    Each call's identity comes from its bearer token or its client certificate; the method's
    :data:`~service.auth.METHOD_RULES` entry decides. A unary request naming a vehicle is
    checked here; the fixes of a stream are checked by the servicer, which reads the caller
    from :data:`service.auth.CALLER`.
    """

    def __init__(self, settings: AccessSettings) -> None:
        self.settings = settings
        self.table = settings.table
        self.quotas = settings.quotas
        self._watch_lock = threading.Lock()
        self._watch: dict[str, int] = {}
        self._watch_total = 0

    def identify(self, details: grpc.HandlerCallDetails, context: aio.ServicerContext) -> Identity | None:
        """The caller's identity, or None when it has no (known) credential."""
        for key, value in details.invocation_metadata or ():
            if key == "authorization":
                v = value.encode() if isinstance(value, str) else value
                if v[:7].lower() != b"bearer ":
                    return None
                return self.table.by_token(v[7:].strip())
        return self.table.by_names(_cert_names(context))

    @contextlib.asynccontextmanager
    async def around(
        self, details: grpc.HandlerCallDetails, context: aio.ServicerContext
    ) -> AsyncIterator[_Access | None]:
        rule = rule_for(details.method)
        if rule.open:
            async with self._watch_slot(details, context):
                yield None
            return
        if not self.table.enabled:
            yield None
            return
        caller = self.identify(details, context)
        if caller is None:
            await abort(context, grpc.StatusCode.UNAUTHENTICATED, "", str(AccessError.unauthenticated()))
        assert caller is not None
        if rule.operator_only and not caller.operator:
            method = details.method.rsplit("/", 1)[-1]
            await abort(context, grpc.StatusCode.PERMISSION_DENIED, "", str(AccessError.operator(method)))
        counted = rule.stream and self.quotas is not None
        if counted:
            assert self.quotas is not None
            try:
                self.quotas.open_stream(caller)
            except LimitError as exc:
                await abort(context, grpc.StatusCode.RESOURCE_EXHAUSTED, exc.field, str(exc))
        token = CALLER.set(caller)
        try:
            yield _Access(caller, rule)
        finally:
            if counted:
                assert self.quotas is not None
                self.quotas.close_stream(caller)
            with contextlib.suppress(ValueError):  # a generator finalised in another context
                CALLER.reset(token)

    def request(self, state: _Access | None, req: Any) -> Any:
        if state is None or state.rule.vehicle_field is None:
            return req
        vid = getattr(req, state.rule.vehicle_field, None)
        if isinstance(vid, str):
            check_vehicle(state.caller, vid, state.rule.vehicle_field)
        return req

    @contextlib.asynccontextmanager
    async def _watch_slot(
        self, details: grpc.HandlerCallDetails, context: aio.ServicerContext
    ) -> AsyncIterator[None]:
        """Health ``Watch`` calls are capped per connection (peer) and in all."""
        if not details.method.endswith("/Watch"):
            yield
            return
        peer = context.peer()
        s = self.settings
        with self._watch_lock:
            n = self._watch.get(peer, 0)
            full = n >= s.max_watch_per_connection or self._watch_total >= s.max_watch_total
            if not full:
                self._watch[peer] = n + 1
                self._watch_total += 1
        if full:
            limit = "max_watch_total" if n < s.max_watch_per_connection else "max_watch_per_connection"
            await abort(
                context,
                grpc.StatusCode.RESOURCE_EXHAUSTED,
                limit,
                f"{limit}: too many health Watch calls open",
            )
        try:
            yield
        finally:
            with self._watch_lock:
                self._watch_total -= 1
                left = self._watch.get(peer, 1) - 1
                if left > 0:
                    self._watch[peer] = left
                else:
                    self._watch.pop(peer, None)


def _cert_names(context: aio.ServicerContext) -> list[str]:
    """The common name and subject alternative names of the client certificate, if any."""
    try:
        auth = context.auth_context()
    except Exception:  # no transport security
        return []
    out: list[str] = []
    for key in ("x509_common_name", "x509_subject_alternative_name"):
        for v in auth.get(key, ()):
            out.append(v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v))
    return out


# ---------------------------------------------------------------------------------- status mapping
class Undecodable:
    """Stands for a request message whose bytes did not parse."""

    __slots__ = ("reason",)

    def __init__(self, reason: str) -> None:
        self.reason = reason


def undecodable_error(msg: Undecodable) -> ValidationError:
    """The INVALID_ARGUMENT error of a message whose bytes did not parse."""
    return ValidationError(
        "request", f"the message does not decode as the method's request type ({msg.reason})"
    )


async def abort(context: aio.ServicerContext, code: grpc.StatusCode, field: str, message: str) -> None:
    """End the call with ``code`` and ``message``, the field named in its trailers
    (``mapmatch-field`` and a ``google.rpc.Status``: :func:`service.errors.error_trailers`)."""
    context.set_trailing_metadata(error_trailers(code, field, message))
    await context.abort(code, message)


# streams whose servicer answers an undecodable message with an error and goes on
ANSWERS_UNDECODABLE = frozenset(
    {"/mapmatch.v1.MapMatch/StreamFixes", "/mapmatch.v1.MapMatch/StreamFixBatches"}
)


class StatusInterceptor(_Wrapping):
    """Maps exceptions to statuses; undecodable requests to INVALID_ARGUMENT, except in the
    live streams (:data:`ANSWERS_UNDECODABLE`), whose servicer gets the :class:`Undecodable`
    and answers it with an error, the stream going on."""

    def deserializer(self, inner: Any) -> Any:
        if inner is None:
            return None

        def parse(data: bytes) -> Any:
            try:
                return inner(data)
            except Exception as exc:  # protobuf DecodeError and friends
                return Undecodable(type(exc).__name__)

        return parse

    def request(self, state: Any, req: Any) -> Any:
        if isinstance(req, Undecodable) and state not in ANSWERS_UNDECODABLE:
            raise undecodable_error(req)
        return req

    @contextlib.asynccontextmanager
    async def around(
        self, details: grpc.HandlerCallDetails, context: aio.ServicerContext
    ) -> AsyncIterator[str]:
        try:
            yield details.method
        except (asyncio.CancelledError, aio.AbortError):
            raise
        except Exception as exc:
            code, fld, msg = status_for(exc)
            if code is grpc.StatusCode.INTERNAL:
                log_internal(exc, details.method)
            await abort(context, code, fld, msg)


# ---------------------------------------------------------------------------------- access log
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

    __slots__ = ("code", "lat", "lat_max", "method", "n_in", "n_lat", "n_out", "pending", "t0", "timed")

    def __init__(self, method: str, *, timed: bool) -> None:
        self.method = method
        self.t0 = time.perf_counter()
        self.code = "OK"
        self.n_in = 0
        self.n_out = 0
        self.timed = timed
        self.pending: deque[float] = deque()
        # the last LATENCY_RING per-message latencies (a fixed-size ring: a long stream's
        # record does not grow) and the largest of all
        self.lat = array("d", bytes(8 * LATENCY_RING)) if timed else array("d")
        self.lat_max = 0.0
        self.n_lat = 0


class AccessLogInterceptor(_Wrapping):
    """One access-log line per call, and the running :class:`Metrics`.

    Parameters
    ----------
    metrics
        Where call counts and latencies accumulate.
    log_format
        ``"json"`` (a JSON object per line) or ``"text"`` (``key=value`` pairs).
    """

    def __init__(self, *, metrics: Metrics, log_format: str = "json") -> None:
        self.metrics = metrics
        self.log_format = log_format
        self._bidi: dict[str, bool] = {}

    def handler_found(self, details: grpc.HandlerCallDetails, handler: grpc.RpcMethodHandler) -> None:
        self._bidi[details.method] = bool(handler.request_streaming and handler.response_streaming)

    def request(self, state: _CallLog, req: Any) -> Any:
        state.n_in += 1
        if state.timed:
            state.pending.append(time.perf_counter())
        return req

    def response(self, state: _CallLog, resp: Any) -> None:
        state.n_out += 1
        if state.pending:
            dt = time.perf_counter() - state.pending.popleft()
            state.lat[state.n_lat % LATENCY_RING] = dt
            state.n_lat += 1
            if dt > state.lat_max:
                state.lat_max = dt

    @contextlib.asynccontextmanager
    async def around(
        self, details: grpc.HandlerCallDetails, context: aio.ServicerContext
    ) -> AsyncIterator[_CallLog]:
        # per-message latencies only feed the log line: not timed when no line is written
        timed = self._bidi.get(details.method, False) and log.isEnabledFor(logging.INFO)
        call = _CallLog(details.method, timed=timed)
        try:
            yield call
        except asyncio.CancelledError:
            call.code = grpc.StatusCode.CANCELLED.name
            raise
        except aio.AbortError:
            call.code = _code_name(context)
            raise
        except Exception:
            call.code = grpc.StatusCode.UNKNOWN.name
            raise
        finally:
            self._finish(call, context)

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
        if call.n_lat:
            s = sorted(call.lat[: min(call.n_lat, LATENCY_RING)])
            rec["msg_p50_ms"] = round(1000.0 * s[len(s) // 2], 3)
            rec["msg_max_ms"] = round(1000.0 * call.lat_max, 3)
        if self.log_format == "json":
            log.info(json.dumps(rec), extra={"rpc": rec})
        else:
            log.info(" ".join(f"{k}={v}" for k, v in rec.items()))


def _code_name(context: aio.ServicerContext) -> str:
    try:
        code = context.code()
    except Exception:  # older grpc: no code() on aio contexts
        return "ABORTED_BY_HANDLER"
    if isinstance(code, grpc.StatusCode):
        return code.name
    if isinstance(code, int):
        for c in grpc.StatusCode:
            if c.value[0] == code:
                return c.name
    return str(code) if code is not None else "UNKNOWN"


def interceptors(*, access: AccessSettings, metrics: Metrics, log_format: str) -> list[aio.ServerInterceptor]:
    """The server's interceptors: one :class:`Chain` of the concerns, outermost first."""
    concerns: list[_Wrapping] = [
        AccessLogInterceptor(metrics=metrics, log_format=log_format),
        AuthInterceptor(access),
        StatusInterceptor(),
    ]
    return [Chain(concerns)]
