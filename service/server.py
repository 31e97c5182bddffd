"""Build, run and stop the gRPC server.

:func:`create_server` starts a ``grpc.aio`` server on its own event-loop thread and returns a
:class:`Server` handle and the bound port; :func:`serve` runs one until SIGTERM/SIGINT and
then shuts down gracefully: health goes NOT_SERVING, new calls are refused and in-flight
calls get ``grace`` seconds to finish.

Health (``grpc.health.v1``) is NOT_SERVING until at least one map is loaded and a warm-up
query on every map has passed; server reflection is on.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import signal
import threading
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import grpc
from grpc import aio
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_health.v1.health import aio as health_aio
from grpc_reflection.v1alpha import reflection

from graph.road_graph import RoadGraph
from mapmatch.errors import ConfigError
from service.config import ServerConfig
from service.gen.mapmatch.v1 import mapmatch_pb2 as pb
from service.gen.mapmatch.v1 import mapmatch_pb2_grpc as pb_grpc
from service.interceptors import Metrics, ServiceInterceptor
from service.maps import MapRegistry
from service.servicer import SERVICE_NAME, MapMatchServicer, warm_up
from service.sessions import SessionStore

log = logging.getLogger("mapmatch.service")

MapsArg = MapRegistry | Mapping[str, RoadGraph | Path | str] | None


class Server:
    """A running server: its event loop thread, registries and health state."""

    def __init__(
        self,
        *,
        config: ServerConfig,
        server: aio.Server,
        loop: asyncio.AbstractEventLoop,
        thread: threading.Thread,
        servicer: MapMatchServicer,
        health: health_aio.HealthServicer,
        executor: ThreadPoolExecutor,
        metrics: Metrics,
    ) -> None:
        self.config = config
        self.aio_server = server
        self.loop = loop
        self.thread = thread
        self.servicer = servicer
        self.health = health
        self.executor = executor
        self.metrics = metrics
        self.port = 0
        self._stopped = threading.Event()
        self._stop_lock = threading.Lock()

    @property
    def maps(self) -> MapRegistry:
        return self.servicer.maps

    @property
    def sessions(self) -> SessionStore:
        return self.servicer.sessions

    def call(self, coro: Any, timeout: float | None = None) -> Any:
        """Run a coroutine on the server's loop from another thread and return its result."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    async def update_health(self) -> None:
        """SERVING when maps are loaded (each has passed its warm-up), else NOT_SERVING."""
        ok = len(self.maps) > 0 and not self._stopped.is_set()
        status = health_pb2.HealthCheckResponse.SERVING if ok else health_pb2.HealthCheckResponse.NOT_SERVING
        for name in ("", SERVICE_NAME):
            await self.health.set(name, status)

    def stop(self, grace: float | None = None) -> None:
        """Graceful shutdown: NOT_SERVING, refuse new calls, drain in-flight ones for ``grace`` s."""
        with self._stop_lock:
            if self._stopped.is_set():
                return
            self._stopped.set()
        g = self.config.grace if grace is None else grace

        async def _stop() -> None:
            await self.health.enter_graceful_shutdown()
            await self.aio_server.stop(g)
            for task in asyncio.all_tasks():
                if task is not asyncio.current_task():
                    task.cancel()

        try:
            self.call(_stop())
        finally:
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(timeout=g + 5.0)
            self.executor.shutdown(wait=False, cancel_futures=True)

    def wait_for_termination(self, timeout: float | None = None) -> bool:
        """Block until :meth:`stop` has run; returns False on timeout."""
        return self._stopped.wait(timeout)


def _credentials(config: ServerConfig) -> grpc.ServerCredentials | None:
    if config.tls_cert is None or config.tls_key is None:
        return None
    try:
        cert = Path(config.tls_cert).read_bytes()
        key = Path(config.tls_key).read_bytes()
        ca = Path(config.client_ca).read_bytes() if config.client_ca else None
    except OSError as exc:
        raise ConfigError(f"cannot read TLS file {exc.filename}: {exc.strerror}") from exc
    return grpc.ssl_server_credentials(
        [(key, cert)], root_certificates=ca, require_client_auth=ca is not None
    )


def _registry(maps: MapsArg) -> tuple[MapRegistry, list[tuple[str, Path]]]:
    """The registry, plus maps still to be loaded from files."""
    if isinstance(maps, MapRegistry):
        return maps, []
    reg = MapRegistry()
    to_load: list[tuple[str, Path]] = []
    for name, m in (maps or {}).items():
        if isinstance(m, RoadGraph):
            reg.add(name, m, source="memory")
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


def create_server(
    config: ServerConfig, maps: MapsArg = None, *, wait_ready: bool = True
) -> tuple[Server, int]:
    """Start a server; return its handle and the bound port.

    Parameters
    ----------
    config
        Address, security, limits.
    maps
        A :class:`MapRegistry`, or ``{name: RoadGraph | path}``; ``config.maps`` are loaded too.
    wait_ready
        Block until the maps are loaded and warmed up (health SERVING). Otherwise loading goes
        on in the background while health says NOT_SERVING.

    Raises
    ------
    ConfigError
        The address cannot be bound, or a TLS file is unreadable.
    """
    registry, to_load = _registry(maps)
    to_load += [(n, p) for n, p in config.maps if n not in registry]
    sessions = SessionStore(max_sessions=config.max_sessions, ttl=config.session_ttl)
    registry.on_unload.append(sessions.drop_map)
    executor = ThreadPoolExecutor(max_workers=config.workers, thread_name_prefix="mapmatch-worker")
    metrics = Metrics()
    creds = _credentials(config)
    loop = asyncio.new_event_loop()
    ready = threading.Event()
    background: list[asyncio.Task[None]] = []  # the session sweeper (cancelled on stop)

    def run() -> None:
        asyncio.set_event_loop(loop)
        loop.call_soon(ready.set)
        loop.run_forever()
        loop.close()

    thread = threading.Thread(target=run, name="mapmatch-grpc", daemon=True)
    thread.start()
    ready.wait()

    async def build() -> tuple[aio.Server, health_aio.HealthServicer, MapMatchServicer, int]:
        options = [
            ("grpc.max_receive_message_length", config.max_message_bytes),
            ("grpc.max_send_message_length", -1),
            ("grpc.so_reuseport", 1 if config.reuse_port else 0),
            ("grpc.keepalive_permit_without_calls", 1),
            ("grpc.http2.min_ping_interval_without_data_ms", 10_000),
        ]
        srv = aio.server(
            interceptors=[
                ServiceInterceptor(token=config.token, metrics=metrics, log_format=config.log_format)
            ],
            options=options,
        )
        servicer = MapMatchServicer(maps=registry, sessions=sessions, executor=executor)
        pb_grpc.add_MapMatchServicer_to_server(servicer, srv)
        health = health_aio.HealthServicer()
        health_pb2_grpc.add_HealthServicer_to_server(health, srv)
        names = (
            pb.DESCRIPTOR.services_by_name["MapMatch"].full_name,
            health_pb2.DESCRIPTOR.services_by_name["Health"].full_name,
            reflection.SERVICE_NAME,
        )
        reflection.enable_server_reflection(names, srv)
        try:
            port = (
                srv.add_secure_port(config.address, creds) if creds else srv.add_insecure_port(config.address)
            )
        except RuntimeError as exc:
            raise ConfigError(f"cannot listen on {config.address}: {exc}") from None
        if not port:
            raise ConfigError(f"cannot listen on {config.address}")
        for name in ("", SERVICE_NAME):
            await health.set(name, health_pb2.HealthCheckResponse.NOT_SERVING)
        await srv.start()
        background.append(
            loop.create_task(_sweep(sessions, period=min(60.0, max(config.session_ttl / 2, 0.05))))
        )
        return srv, health, servicer, port

    try:
        srv, health, servicer, port = asyncio.run_coroutine_threadsafe(build(), loop).result()
    except BaseException:
        loop.call_soon_threadsafe(loop.stop)
        thread.join()
        executor.shutdown(wait=False)
        raise
    server = Server(
        config=config,
        server=srv,
        loop=loop,
        thread=thread,
        servicer=servicer,
        health=health,
        executor=executor,
        metrics=metrics,
    )
    server.port = port
    servicer.on_maps_changed = server.update_health

    def prepare() -> None:
        from mapmatch.kernels import COMPILE_SECONDS, is_cached

        # the batch kernels are warmed up only when compiled already: on a machine's first run
        # the first MatchTrack compiles them, so live streams need not wait for that
        batch = is_cached("batch")
        try:
            for name, path in to_load:
                log.info("loading map %s from %s", name, path)
                registry.load(name, path)
            for entry in registry.entries():
                log.info("warming up map %s", entry.map_id)
                warm_up(entry, servicer, batch=batch)
        except Exception as exc:
            log.error("map loading or warm-up failed, health stays NOT_SERVING: %s", exc)
            raise
        server.call(server.update_health())
        log.info("serving %d map(s) on port %d", len(registry), port)
        if not batch:
            log.info(
                "batch kernels not compiled yet: the first MatchTrack compiles them, once, about %.0f s",
                COMPILE_SECONDS["batch"],
            )

    fut = executor.submit(prepare)
    if wait_ready:
        try:
            fut.result()
        except BaseException:
            server.stop(0)
            raise
    return server, port


def serve(config: ServerConfig, maps: MapsArg = None) -> int:
    """Run a server in the foreground until SIGTERM or SIGINT, then shut down gracefully."""
    server, port = create_server(config, maps)
    # the maps, matchers and compiled code are long-lived: keep them out of the cyclic GC's
    # scans so full collections stay short (they showed as latency spikes)
    gc.collect()
    gc.freeze()
    done = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        log.info("signal %d: shutting down (grace %.1f s)", signum, config.grace)
        done.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    host = config.address.rsplit(":", 1)[0]
    print(f"mapmatch serve: listening on {host}:{port} ({len(server.maps)} map(s))", flush=True)
    try:
        while not done.wait(0.5):
            pass
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        server.stop()
    return 0
