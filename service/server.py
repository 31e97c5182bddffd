"""Build, run and stop the gRPC server.

:func:`create_server` only builds: it checks the configuration (TLS files, maps) and returns
a :class:`ServiceRuntime`, which then starts (event-loop thread, bound port), warms up (loads
every map and runs a warm-up query on it; then the batch worker processes start and warm up
their batch matchers, before health says SERVING), sweeps
idle sessions and stops (the batch workers too): health goes
NOT_SERVING, new calls are refused and in-flight calls get ``grace`` seconds to finish.
:func:`start_server` does both; :func:`serve` runs a server until SIGTERM/SIGINT.

Health (``grpc.health.v1``) is NOT_SERVING for ``""`` and ``mapmatch.v1.MapMatch`` until
at least one map is loaded and has passed its warm-up, online and batch (a batch worker
process has loaded it and matched a track on it); each loaded map also has its own
service name, ``mapmatch.v1.MapMatch/<map id>``. With a session store
(``--session-store``), ``mapmatch.v1.SessionStore`` is SERVING while the store answers and
NOT_SERVING while it fails (fixes are answered either way, so ``""`` stays SERVING; see
:mod:`service.store_checkpoints`). Server reflection (v1 and v1alpha) is on. Every start-up step is logged on
``service``, and so is the moment the server is SERVING. Started by :func:`serve` cold (its
online kernels not compiled yet, ``--kernels auto``), the server answers fixes interpreted
while a child process compiles them, then switches to them (:class:`mapmatch.kernels.TieredGroup`);
health ``mapmatch.v1.MapMatch.Compiled`` is SERVING once fixes are answered compiled.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import gc
import json
import logging
import os
import signal
import socket
import ssl
import sys
import threading
from collections.abc import Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import grpc
from grpc import aio
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_health.v1.health import aio as health_aio

from graph.road_graph import RoadGraph
from mapmatch.errors import ConfigError
from mapmatch.extras import MissingExtraError
from mapmatch.logs import resolve_format
from service.auth import IdentityTable, Quotas
from service.batch_workers import BatchWorkers, MapFile, TrackLimits
from service.config import ServerConfig
from service.errors import MapLoadError
from service.gen import mapmatch_pb2 as pb
from service.gen import mapmatch_pb2_grpc as pb_grpc
from service.interceptors import AccessSettings, Metrics, interceptors
from service.maps import MapRegistry, load_map_file, open_map_path, stop_builds, warm_batch, warm_up
from service.reflection import enable_reflection
from service.servicer import SERVICE_NAME, MapMatchServicer, OnlineQueue, load_limits
from service.sessions import SessionStore
from service.store import RedisStore
from service.store_checkpoints import STORE_HEALTH, Checkpointer, CheckpointSettings

log = logging.getLogger("mapmatch.service")

BATCH_HEALTH = "mapmatch.v1.MapMatch.Batch"
"""Health name of batch matching: SERVING once a ``MatchTrack`` is answered without waiting for
a batch worker process to prepare (on a machine's first run, to compile the batch kernels)."""

KERNELS_HEALTH = "mapmatch.v1.MapMatch.Compiled"
"""Health name of the online kernels: SERVING while fixes are answered by the compiled kernels;
NOT_SERVING while they run interpreted (a cold start answers interpreted while they compile in
the background: the same answers, slower per fix)."""

MapsArg = MapRegistry | Mapping[str, RoadGraph | Path | str] | None
SERVING = health_pb2.HealthCheckResponse.SERVING
NOT_SERVING = health_pb2.HealthCheckResponse.NOT_SERVING
# the GIL is handed over at most this often (s): online updates wait less behind batch work
SWITCH_INTERVAL = 0.001


def new_event_loop() -> asyncio.AbstractEventLoop:
    """The server's event loop: uvloop's when it is installed (a core dependency on Linux and
    macOS; its wake-ups and callbacks cost less CPU per message than asyncio's), else asyncio's."""
    try:
        import uvloop
    except ImportError:
        return asyncio.new_event_loop()
    return uvloop.new_event_loop()


class ServiceRuntime:
    """A server's runtime: :meth:`start`, :meth:`warm`, the session sweeper, :meth:`stop`.

    Built by :func:`create_server`; nothing runs until :meth:`start`.
    """

    def __init__(
        self, *, config: ServerConfig, registry: MapRegistry, to_load: list[tuple[str, Path]]
    ) -> None:
        self.config = config
        self.maps = registry
        self.to_load = to_load
        self.sessions = SessionStore(max_sessions=config.max_sessions, ttl=config.session_ttl)
        registry.on_unload.append(self.sessions.drop_map)
        self.executor = ThreadPoolExecutor(max_workers=config.workers, thread_name_prefix="mapmatch-batch")
        self.online = OnlineQueue(workers=config.online_workers)
        self.batch_workers = (
            BatchWorkers(
                processes=config.batch_processes,
                limits=TrackLimits(
                    max_track_points=config.max_track_points, max_answer_bytes=config.max_answer_bytes
                ),
                nice=config.batch_nice,
                sched=config.batch_sched,
                match_config=config.batch_matcher,
            )
            if config.batch_processes > 0
            else None
        )
        self.metrics = Metrics()
        self.credentials = _credentials(config)
        self.identities = IdentityTable(path=config.identities, token=config.token)
        self.quotas = Quotas(
            max_sessions=config.max_identity_sessions, max_streams=config.max_identity_streams
        )
        self.servicer = MapMatchServicer(
            maps=registry,
            sessions=self.sessions,
            executor=self.executor,
            online=self.online,
            batch_workers=self.batch_workers,
            config=config,
            on_maps_changed=self.maps_changed,
        )
        self.servicer.quotas = self.quotas
        self.port = 0
        self.loop: asyncio.AbstractEventLoop | None = None
        self.thread: threading.Thread | None = None
        self.aio_server: aio.Server | None = None
        self.health = health_aio.HealthServicer()
        self._health_names: set[str] = set()
        self._stopped = threading.Event()
        self._stop_lock = threading.Lock()
        self._sweeper: asyncio.Task[None] | None = None
        self.ready: Future[None] = Future()
        self.tier_kernels = False
        """Whether :meth:`warm` answers interpreted at once while the online kernels compile in
        the background, when they are not compiled yet and ``--kernels`` is ``auto``
        (:func:`mapmatch.kernels.tiered_wanted`); set by :func:`serve`."""
        self.tiered: Any = None  # the mapmatch.kernels.TieredGroup, when tiered
        self.checkpoints = _checkpointer(self) if config.session_store else None
        self.servicer.checkpoints = self.checkpoints
        if self.batch_workers is not None:  # a map the batch workers cannot load: health says so
            self.batch_workers.on_failed = lambda failed: self._health_soon()
            self.batch_workers.on_warm = self._health_soon

    # ------------------------------------------------------------------ start
    def call(self, coro: Any, timeout: float | None = None) -> Any:
        """Run a coroutine on the server's loop from another thread and return its result."""
        assert self.loop is not None, "the server has not started"
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def start(self, *, wait_ready: bool = True) -> int:
        """Bind the port, start serving (health NOT_SERVING), then :meth:`warm` (in the
        background unless ``wait_ready``). Returns the bound port.

        Raises
        ------
        ConfigError
            The address cannot be bound; with ``wait_ready``, a map that cannot be served.
        """
        loop = new_event_loop()
        started = threading.Event()

        def run() -> None:
            asyncio.set_event_loop(loop)
            loop.call_soon(started.set)
            loop.run_forever()
            loop.close()

        self.loop = loop
        self.thread = threading.Thread(target=run, name="mapmatch-grpc", daemon=True)
        self.thread.start()
        started.wait()
        self.online.start()
        try:
            self.port = self.call(self._bind_and_start())
        except BaseException:
            loop.call_soon_threadsafe(loop.stop)
            self.thread.join()
            self._shutdown_pools()
            raise
        log.info(
            "listening on %s (port %d, %s)",
            self.config.address,
            self.port,
            "TLS" if self.credentials else "plain text",
        )
        fut = self.executor.submit(self.warm)
        fut.add_done_callback(lambda f: _copy_result(f, self.ready))
        if wait_ready:
            try:
                fut.result()
            except BaseException:
                self.stop(0)
                raise
        return self.port

    async def _bind_and_start(self) -> int:
        cfg = self.config
        options = [
            ("grpc.max_receive_message_length", cfg.max_message_bytes),
            ("grpc.max_send_message_length", -1),
            ("grpc.so_reuseport", 1 if cfg.reuse_port else 0),
            ("grpc.keepalive_permit_without_calls", 1),
            ("grpc.http2.min_ping_interval_without_data_ms", 10_000),
        ]
        access = AccessSettings(
            table=self.identities,
            quotas=self.quotas,
            max_watch_per_connection=cfg.max_watch_per_connection,
            max_watch_total=cfg.max_watch_total,
        )
        if not self.identities.enabled:
            log.warning("no --token and no --identities: every client may call every method")
        srv = aio.server(
            interceptors=interceptors(
                access=access, metrics=self.metrics, log_format=resolve_format(cfg.log_format, sys.stderr)
            ),
            options=options,
        )
        add_servicer(self.servicer, srv)
        health_pb2_grpc.add_HealthServicer_to_server(self.health, srv)
        names = (
            pb.DESCRIPTOR.services_by_name["MapMatch"].full_name,
            health_pb2.DESCRIPTOR.services_by_name["Health"].full_name,
        )
        enable_reflection(names, srv)  # v1 and v1alpha
        if not cfg.reuse_port:
            _check_port_free(cfg.address)
        try:
            if self.credentials:
                port = srv.add_secure_port(cfg.address, self.credentials)
            else:
                port = srv.add_insecure_port(cfg.address)
        except RuntimeError:
            port = 0
        if not port:
            raise ConfigError(f"cannot listen on {cfg.address} (address in use or not available)")
        for name in ("", SERVICE_NAME, BATCH_HEALTH) + ((STORE_HEALTH,) if self.checkpoints else ()):
            await self.health.set(name, NOT_SERVING)
        await srv.start()
        self.aio_server = srv
        period = min(60.0, max(cfg.session_ttl / 2, 0.05))
        self._sweeper = asyncio.get_running_loop().create_task(_sweep(self.sessions, period=period))
        if self.checkpoints is not None:
            self.checkpoints.start()
        return int(port)

    def warm(self) -> None:
        """Load the maps still to be loaded, warm every map up, then report SERVING."""
        limits = load_limits(self.config)
        self._tier_online()
        try:
            for name, path in self.to_load:
                log.info("loading map %s from %s", name, path.name)
                src = open_map_path(path)  # opened once: the map and the batch workers read this
                graph = load_map_file(src, limits=limits, name=path.name)
                log.info("warming up map %s (%d edges)", name, graph.n_edges)
                if src.is_map:
                    self.maps.add(name, graph, source=path.name, batch=False, path=path, file=src.file)
                else:
                    self.maps.add(name, graph, source=path.name, batch=False)
            for entry in self.maps.entries():
                if entry.map_id not in {n for n, _ in self.to_load}:
                    log.info("warming up map %s (%d edges)", entry.map_id, entry.graph.n_edges)
                    warm_up(entry, batch=False)
                log.info("map %s ready (checksum %s)", entry.map_id, entry.checksum)
        except Exception as exc:
            log.error("map loading or warm-up failed, health stays NOT_SERVING: %s", exc)
            raise
        self.to_load = []
        # SERVING only once every kind of call can be answered: the batch matchers are warm
        # too (a first MatchTrack would otherwise wait for a worker's start within its deadline)
        self._warm_batch()
        self.call(self.update_health())

    def _tier_online(self) -> None:
        """With :attr:`tier_kernels`, on a cold start: answer fixes interpreted at once while a
        child process compiles the online kernels, then switch to them (logged, and health
        :data:`KERNELS_HEALTH`)."""
        if not self.tier_kernels or self.tiered is not None:
            return
        from mapmatch.kernels import COMPILE_SECONDS, TieredGroup, tiered_wanted

        if not tiered_wanted("online"):
            return
        self.tiered = TieredGroup("online", on_switch=self._on_compiled, on_failed=self._on_not_compiled)
        self.tiered.start()
        log.info(
            "online kernels not compiled yet: fixes are answered interpreted (the same answers, slower "
            "per fix) while a child process compiles them, once, about %.0f s of CPU; health %s is "
            "NOT_SERVING until they run compiled",
            COMPILE_SECONDS["online"],
            KERNELS_HEALTH,
        )

    def _on_compiled(self, report: Any) -> None:
        """The online kernels run compiled from now on (a :class:`mapmatch.kernels.TierReport`)."""
        how = "compiled by the child process" if report.child_compiled else "compiled in this process"
        log.info(
            "online kernels %s: fixes are answered compiled from now on (%.1f s after the start of "
            "their compile; loading them took %.2f s)",
            how,
            report.seconds,
            report.load_seconds,
        )
        gc.freeze()  # the compiled kernels are long-lived too (see _serve_one)
        self._health_soon()

    @staticmethod
    def _on_not_compiled(exc: Exception) -> None:
        log.error(
            "online kernels could not be compiled (%s: %s): fixes stay answered interpreted (the same "
            "answers, slower per fix); health %s stays NOT_SERVING",
            type(exc).__name__,
            exc,
            KERNELS_HEALTH,
        )

    def _warm_batch(self) -> None:
        """Start the batch worker processes and wait (up to ``load_timeout``) until one has
        warmed up its maps; warm up the batch matchers of the maps matched in this process."""
        from mapmatch.kernels import COMPILE_SECONDS, compiled_on_disk, is_interpreted

        in_workers = self._sync_workers()
        workers = self.batch_workers
        if not is_interpreted() and not compiled_on_disk("batch"):  # read without importing them
            log.info(
                "batch kernels not compiled yet: the batch worker processes compile them, once, about "
                "%.0f s; until then MatchTrack answers UNAVAILABLE before its deadline and health "
                "%s is NOT_SERVING",
                COMPILE_SECONDS["batch"],
                BATCH_HEALTH,
            )
            return
        if in_workers and workers is not None and not workers.wait_warm(self.config.load_timeout):
            log.error("the batch worker processes did not warm up in %.0f s", self.config.load_timeout)
        for entry in self.maps.entries():
            if entry.map_id in in_workers:
                continue  # matched (and warmed up) in the batch worker processes
            try:
                warm_batch(entry)
            except MapLoadError as exc:
                log.error("map %s: %s (MatchTrack on it will fail)", entry.map_id, exc)

    def _sync_workers(self) -> set[str]:
        """Tell the batch worker processes the maps with files (started on the first such
        map); returns the ids of the maps they serve."""
        if self.batch_workers is None:
            return set()
        files = [
            MapFile(map_id=e.map_id, path=str(e.path), checksum=e.checksum, file=e.file)
            for e in self.maps.entries()
            if e.path is not None and e.file is not None
        ]
        self.batch_workers.set_maps(files)
        if files:
            self.batch_workers.start()
        return {f.map_id for f in files}

    async def maps_changed(self) -> None:
        """After LoadMap/UnloadMap: health, and the batch workers' maps."""
        self._sync_workers()
        await self.update_health()

    def _health_soon(self) -> None:
        """:meth:`update_health` on the server's loop, from any thread."""
        if self.loop is not None and not self._stopped.is_set():
            with contextlib.suppress(RuntimeError):  # the loop has closed
                asyncio.run_coroutine_threadsafe(self.update_health(), self.loop)

    async def update_health(self) -> None:
        """SERVING when maps are loaded (each has passed its warm-up), else NOT_SERVING; and
        one service name per map, NOT_SERVING for a map the batch worker processes cannot
        load (its MatchTrack would fail)."""
        ids = {e.map_id for e in self.maps.entries()}
        broken = set(self.batch_workers.failed) if self.batch_workers is not None else set()
        ok = bool(ids) and not self._stopped.is_set()
        was = getattr(self, "_serving", None)
        for name in ("", SERVICE_NAME):
            await self.health.set(name, SERVING if ok else NOT_SERVING)
        workers = self.batch_workers
        batch_ok = ok and (workers is None or not workers.started or workers.warm)
        await self.health.set(BATCH_HEALTH, SERVING if batch_ok else NOT_SERVING)
        await self.health.set(KERNELS_HEALTH, SERVING if ok and self._compiled() else NOT_SERVING)
        for map_id in ids | self._health_names:
            await self.health.set(
                f"{SERVICE_NAME}/{map_id}",
                SERVING if map_id in ids and map_id not in broken and ok else NOT_SERVING,
            )
        self._health_names |= ids
        self._serving = ok
        if ok and not was:
            log.info("SERVING %d map(s) on port %d", len(ids), self.port)
        elif was and not ok:
            log.info("NOT_SERVING: no map loaded")

    def _compiled(self) -> bool:
        """Whether fixes are answered by the compiled online kernels."""
        from mapmatch.kernels import is_interpreted

        return not is_interpreted() and (self.tiered is None or self.tiered.compiled.is_set())

    # ------------------------------------------------------------------ stop
    def stop(self, grace: float | None = None) -> None:
        """Graceful shutdown: NOT_SERVING, refuse new calls, drain in-flight ones for ``grace`` s."""
        with self._stop_lock:
            if self._stopped.is_set():
                return
            self._stopped.set()
        g = self.config.grace if grace is None else grace
        if self.loop is None or self.thread is None:
            self._shutdown_pools()
            return

        async def _stop() -> None:
            await self.health.enter_graceful_shutdown()
            if self.aio_server is not None:
                stopping = asyncio.ensure_future(self.aio_server.stop(g))  # no new calls from here
                if self.checkpoints is not None:  # open streams hand their vehicles over
                    await asyncio.sleep(0)
                    self.checkpoints.drain()
                await stopping
            if self.checkpoints is not None:
                await self.checkpoints.store.aclose()
            for task in asyncio.all_tasks():
                if task is not asyncio.current_task():
                    task.cancel()

        try:
            self.call(_stop(), timeout=g + 10.0)
        finally:
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(timeout=g + 5.0)
            self._shutdown_pools()
            if self.checkpoints is not None:
                self.checkpoints.stop()  # the last pass: every session used since the one before
            log.info("stopped")

    def _shutdown_pools(self) -> None:
        if n := stop_builds():  # a map build in flight would hold the process past its grace
            log.info("stopped %d map build(s) in flight", n)
        self.executor.shutdown(wait=False, cancel_futures=True)
        self.online.shutdown()
        if self.tiered is not None:
            self.tiered.stop()
        if self.batch_workers is not None:
            self.batch_workers.stop()

    def wait_for_termination(self, timeout: float | None = None) -> bool:
        """Block until :meth:`stop` has run; returns False on timeout."""
        return self._stopped.wait(timeout)


Server = ServiceRuntime  # the name older code uses


def _pass_bytes(serialize: Any) -> Any:
    """A response serializer that sends ``bytes`` as they are (answers serialised elsewhere)."""

    def out(msg: Any) -> bytes:
        return msg if type(msg) is bytes else serialize(msg)

    return out


class _Collect:
    """Stands for a server while the generated code registers a servicer's handlers."""

    def __init__(self) -> None:
        self.handlers: dict[str, grpc.RpcMethodHandler] = {}

    def add_generic_rpc_handlers(self, handlers: Any) -> None:
        pass

    def add_registered_method_handlers(self, service: str, handlers: dict[str, Any]) -> None:
        self.handlers = dict(handlers)


def add_servicer(servicer: MapMatchServicer, server: aio.Server) -> None:
    """Register the MapMatch servicer; ``MatchTrack`` gets its request as bytes (passed on to
    a batch worker process as they are), and the batch methods may answer with bytes."""
    got = _Collect()
    pb_grpc.add_MapMatchServicer_to_server(servicer, got)
    h = got.handlers
    h["MatchTrack"] = grpc.unary_unary_rpc_method_handler(
        servicer.MatchTrack,
        request_deserializer=None,
        response_serializer=_pass_bytes(pb.TrackResult.SerializeToString),
    )
    h["MatchTracks"] = grpc.unary_stream_rpc_method_handler(
        servicer.MatchTracks,
        request_deserializer=pb.MatchTracksRequest.FromString,
        response_serializer=_pass_bytes(pb.TrackResult.SerializeToString),
    )
    name = pb.DESCRIPTOR.services_by_name["MapMatch"].full_name
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(name, h),))
    server.add_registered_method_handlers(name, h)


def _checkpointer(runtime: ServiceRuntime) -> Checkpointer:
    """The session store's checkpointer of a runtime (health follows the store)."""
    cfg = runtime.config
    assert cfg.session_store is not None
    try:
        store = RedisStore(cfg.session_store, timeout=cfg.store_timeout)
    except MissingExtraError as exc:
        raise ConfigError(str(exc)) from None
    except ValueError as exc:  # a URL redis cannot parse
        raise ConfigError(f"session_store: {exc}") from None

    def on_health(ok: bool) -> None:
        loop = runtime.loop
        if loop is not None and not runtime._stopped.is_set():
            status = SERVING if ok else NOT_SERVING
            with contextlib.suppress(RuntimeError):  # the loop has closed
                asyncio.run_coroutine_threadsafe(runtime.health.set(STORE_HEALTH, status), loop)

    settings = CheckpointSettings(
        interval=cfg.checkpoint_interval,
        ttl=cfg.session_ttl,
        timeout=cfg.store_timeout,
        max_vehicle_id=cfg.max_vehicle_id,
    )
    return Checkpointer(
        store=store, sessions=runtime.sessions, maps=runtime.maps, settings=settings, on_health=on_health
    )


def _copy_result(src: Future[None], dst: Future[None]) -> None:
    exc = src.exception()
    if exc is not None:
        dst.set_exception(exc)
    else:
        dst.set_result(None)


def _check_port_free(address: str) -> None:
    """A clear error when ``address`` is in use (SO_REUSEPORT off), before gRPC tries it."""
    host, _, port_text = address.rpartition(":")
    host = host.strip("[]")
    try:
        port = int(port_text)
    except ValueError:
        raise ConfigError(f"address must be HOST:PORT, got {address!r}") from None
    if port == 0:
        return
    try:
        infos = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise ConfigError(f"cannot listen on {address}: {exc.strerror}") from None
    for family, kind, proto, _, sockaddr in infos[:1]:
        with socket.socket(family, kind, proto) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(sockaddr)
            except OSError as exc:
                why = (
                    "address already in use" if exc.errno == errno.EADDRINUSE else (exc.strerror or str(exc))
                )
                raise ConfigError(f"cannot listen on {address}: {why}") from None


def _credentials(config: ServerConfig) -> grpc.ServerCredentials | None:
    """Server credentials from the PEM files, each checked first (one clear line when bad)."""
    if config.tls_cert is None or config.tls_key is None:
        return None
    try:
        cert = Path(config.tls_cert).read_bytes()
        key = Path(config.tls_key).read_bytes()
        ca = Path(config.client_ca).read_bytes() if config.client_ca else None
    except OSError as exc:
        raise ConfigError(f"cannot read TLS file {exc.filename}: {exc.strerror}") from None
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    try:
        ctx.load_cert_chain(config.tls_cert, config.tls_key)
    except (ssl.SSLError, ValueError) as exc:
        raise ConfigError(
            f"TLS: {config.tls_cert.name} and {config.tls_key.name} are not a PEM certificate chain "
            f"and its private key ({getattr(exc, 'reason', None) or exc})"
        ) from None
    if config.client_ca is not None:
        try:
            ctx.load_verify_locations(cafile=str(config.client_ca))
        except (ssl.SSLError, ValueError) as exc:
            raise ConfigError(
                f"TLS: {config.client_ca.name} is not a PEM CA certificate "
                f"({getattr(exc, 'reason', None) or exc})"
            ) from None
    return grpc.ssl_server_credentials(
        [(key, cert)], root_certificates=ca, require_client_auth=ca is not None
    )


def _registry(maps: MapsArg, config: ServerConfig) -> tuple[MapRegistry, list[tuple[str, Path]]]:
    """The registry (with the configured matcher parameters), plus maps still to be loaded."""
    if isinstance(maps, MapRegistry):
        return maps, []
    reg = MapRegistry(config=config.matcher, batch_config=config.batch_matcher)
    to_load: list[tuple[str, Path]] = []
    for name, m in (maps or {}).items():
        if isinstance(m, RoadGraph):
            reg.install(reg.prepare(name, m, source="memory"))  # warmed up by ServiceRuntime.warm
        else:
            to_load.append((name, Path(m)))
    return reg, to_load


async def _sweep(sessions: SessionStore, *, period: float) -> None:
    """Drop expired sessions now and then, so idle ones free memory without new traffic."""
    while True:
        await asyncio.sleep(period)
        n = sessions.sweep()
        if n:
            log.info("expired %d idle session(s)", n)


def create_server(config: ServerConfig, maps: MapsArg = None) -> ServiceRuntime:
    """Build a server (nothing starts): check the configuration and TLS files, set up the
    registry, the session store and the pools.

    Parameters
    ----------
    config
        Address, security, limits.
    maps
        A :class:`MapRegistry`, or ``{name: RoadGraph | path}``; ``config.maps`` are loaded too.

    Raises
    ------
    ConfigError
        A TLS file is unreadable or not PEM, or a map name is bad.
    """
    registry, to_load = _registry(maps, config)
    to_load += [(n, p) for n, p in config.maps if n not in registry]
    log.info("configuration checked (%s)", "TLS" if config.tls else "plain text")
    return ServiceRuntime(config=config, registry=registry, to_load=to_load)


def start_server(
    config: ServerConfig, maps: MapsArg = None, *, wait_ready: bool = True
) -> tuple[ServiceRuntime, int]:
    """:func:`create_server`, then :meth:`ServiceRuntime.start`; returns the runtime and port."""
    runtime = create_server(config, maps)
    port = runtime.start(wait_ready=wait_ready)
    return runtime, port


class JsonLinesFormatter(logging.Formatter):
    """One JSON object per line: time, level, logger and message (an access-log record's
    fields are merged in)."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "time": self.formatTime(record, "%Y-%m-%dT%H:%M:%S") + f".{int(record.msecs):03d}",
            "level": record.levelname,
            "logger": record.name,
        }
        rpc = getattr(record, "rpc", None)
        if isinstance(rpc, dict):
            out.update(rpc)
        else:
            out["message"] = record.getMessage()
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out)


class _StderrHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """Writes to whatever ``sys.stderr`` is at the time of each record."""

    @property  # type: ignore[override]
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, value: Any) -> None:
        pass


def configure_logging(log_format: str, *, access: bool) -> None:
    """Lifecycle lines always; access lines when ``access``; JSON lines for ``"json"``.

    Replaces the root handlers' format for the ``mapmatch`` loggers with a handler of its own.
    """
    handler: logging.Handler = _StderrHandler()
    if resolve_format(log_format, sys.stderr) == "json":
        handler.setFormatter(JsonLinesFormatter())
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    for name, level in (
        ("mapmatch.service", logging.INFO),
        ("mapmatch.access", logging.INFO if access else logging.WARNING),
    ):
        lg = logging.getLogger(name)
        lg.handlers = [handler]
        lg.propagate = False
        lg.setLevel(level)


def serve(config: ServerConfig, maps: MapsArg = None) -> int:
    """Run a server in the foreground until SIGTERM or SIGINT, then shut down gracefully.

    With ``config.processes > 1`` this process starts that many server processes on one port
    (SO_REUSEPORT; the kernel spreads connections over them) and supervises them.
    """
    if config.processes > 1:
        if maps:
            raise ConfigError("several processes load their maps from files (config.maps), not objects")
        return _serve_processes(config)
    return _serve_one(config, maps, on_ready=_announce)


def _announce(address: str, port: int, n_maps: int) -> None:
    host = address.rsplit(":", 1)[0]
    print(f"mapmatch serve: listening on {host}:{port} ({n_maps} map(s))", flush=True)


def _serve_one(config: ServerConfig, maps: MapsArg, *, on_ready: Any) -> int:
    sys.setswitchinterval(SWITCH_INTERVAL)
    done = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        log.info("signal %d: shutting down (grace %.1f s)", signum, config.grace)
        done.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    hup = signal.getsignal(signal.SIGHUP)
    try:
        log.info("starting (pid %d)", os.getpid())
        runtime = create_server(config, maps)
        runtime.tier_kernels = True
        signal.signal(signal.SIGHUP, lambda signum, frame: runtime.identities.reload())
        port = runtime.start(wait_ready=False)
        while not done.wait(0.2):
            if runtime.ready.done():
                break
        if runtime.ready.done() and runtime.ready.exception() is not None:
            runtime.stop(0)
            raise ConfigError(f"cannot serve: {runtime.ready.exception()}")
        if runtime.ready.done():
            on_ready(config.address, port, len(runtime.maps))
        # the maps, matchers and compiled code are long-lived: keep them out of the cyclic GC's
        # scans so full collections stay short (they showed as latency spikes)
        gc.collect()
        gc.freeze()
        while not done.wait(0.5):
            pass
        runtime.stop()
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if hup is not None:
            signal.signal(signal.SIGHUP, hup)
    return 0


def _child_main(config: ServerConfig, reports: Any, log_format: str, access: bool) -> None:
    """A server process of :func:`_serve_processes`: serve, and report readiness or failure."""
    configure_logging(log_format, access=access)
    try:
        _serve_one(config, None, on_ready=lambda address, port, n: reports.put(("ready", port, n)))
    except ConfigError as exc:
        reports.put(("error", str(exc), 0))
        sys.exit(3)


def _wait_ready(procs: list[Any], reports: Any, done: threading.Event) -> list[tuple[str, Any, int]]:
    """The server processes' start-up reports, until each has reported, one has ended, or a
    signal came; a reported error is raised as a :class:`ConfigError`."""
    import queue as queue_mod

    ready: list[tuple[str, Any, int]] = []
    while len(ready) < len(procs) and not done.is_set():
        try:
            ready.append(reports.get(timeout=0.2))
        except queue_mod.Empty:
            if any(p.exitcode is not None for p in procs):
                with contextlib.suppress(queue_mod.Empty):  # its report may still be on the way
                    ready.append(reports.get(timeout=1.0))
                if not any(r[0] == "error" for r in ready):
                    break
        failed = [r for r in ready if r[0] == "error"]
        if failed:
            raise ConfigError(str(failed[0][1]))
    return ready


def _serve_processes(config: ServerConfig) -> int:
    """Start ``config.processes`` servers on one port and supervise them until a signal."""
    import multiprocessing as mp

    host, _, port_text = config.address.rpartition(":")
    if not config.reuse_port:
        _check_port_free(config.address)  # a port in use is an error unless sharing was asked for
    holder: socket.socket | None = None
    port = int(port_text)
    if port == 0:  # pick one port for all: held (bound, not listening) until every child listens
        family = socket.AF_INET6 if ":" in host.strip("[]") else socket.AF_INET
        holder = socket.socket(family, socket.SOCK_STREAM)
        holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        holder.bind((host.strip("[]"), 0))
        port = holder.getsockname()[1]
    child = config.replace(address=f"{host}:{port}", reuse_port=True, processes=1)
    ctx = mp.get_context("spawn")
    reports = ctx.Queue()
    access = logging.getLogger("mapmatch.access").isEnabledFor(logging.INFO)
    procs = [
        ctx.Process(
            target=_child_main, args=(child, reports, config.log_format, access), name=f"mapmatch-serve-{i}"
        )
        for i in range(config.processes)
    ]
    done = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        log.info("signal %d: stopping %d server processes", signum, len(procs))
        done.set()

    def on_hup(signum: int, frame: Any) -> None:  # each process reads its identities again
        for p in procs:
            if p.is_alive() and p.pid is not None:
                os.kill(p.pid, signal.SIGHUP)

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    old[signal.SIGHUP] = signal.signal(signal.SIGHUP, on_hup)
    try:
        log.info("starting %d server processes on port %d", len(procs), port)
        for p in procs:
            p.start()
        ready = _wait_ready(procs, reports, done)
        if not done.is_set():
            if len(ready) < len(procs):
                raise ConfigError("cannot serve: a server process ended during start-up")
            if holder is not None:
                holder.close()
                holder = None
            _announce(config.address, port, ready[0][2])
            print(f"mapmatch serve: {len(procs)} server processes", flush=True)
        while not done.wait(0.5):
            codes = [p.exitcode for p in procs]
            if any(c is not None for c in codes):
                raise ConfigError(f"cannot serve: a server process ended (exit statuses {codes})")
    finally:
        for p in procs:
            if p.is_alive() and p.pid is not None:
                os.kill(p.pid, signal.SIGTERM)
        for p in procs:
            p.join(config.grace + 10.0)
            if p.is_alive():
                p.kill()
                p.join()
        if holder is not None:
            holder.close()
        for s, h in old.items():
            signal.signal(s, h)
    return 0
