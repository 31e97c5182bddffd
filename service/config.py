"""Server configuration from CLI flags, ``MAPMATCH_*`` environment variables and a TOML file.

Precedence: a CLI flag, else the environment variable, else the config file (``--config``),
else the default. Defaults are safe: plain (no TLS) on loopback, no ``LoadMap`` of paths.

==========================  ==========================  ===================================
environment variable        flag                        meaning
==========================  ==========================  ===================================
MAPMATCH_ADDRESS            --address HOST:PORT         listen address (127.0.0.1:50051)
MAPMATCH_MAPS               --map NAME=PATH (repeat)    maps, ``NAME=PATH,NAME=PATH``
MAPMATCH_TLS_CERT           --tls-cert FILE             server certificate chain (PEM)
MAPMATCH_TLS_KEY            --tls-key FILE              server private key (PEM)
MAPMATCH_CLIENT_CA          --client-ca FILE            CA for client certificates: mutual TLS
MAPMATCH_TOKEN              --token TOKEN               required bearer token (``authorization``)
MAPMATCH_TOKEN_FILE         --token-file FILE           the same, read from a file
MAPMATCH_MAX_SESSIONS       --max-sessions N            live vehicle sessions (100000)
MAPMATCH_SESSION_TTL        --session-ttl SECONDS       idle session lifetime (600)
MAPMATCH_MAX_MESSAGE_BYTES  --max-message-bytes N       largest request message (4 MiB)
MAPMATCH_WORKERS            --workers N                 threads for batch matching and map loads (2)
MAPMATCH_GRACE              --grace SECONDS             drain time on shutdown (10)
MAPMATCH_REUSE_PORT         --reuse-port                SO_REUSEPORT (off), for several processes
MAPMATCH_LOG_FORMAT         --log-format auto|json|text JSON lines or text logs (auto: text on a terminal)
MAPMATCH_MAP_DIR            --map-dir DIR               LoadMap reads files only here (off)
MAPMATCH_MAX_BATCH_FIXES    --max-batch-fixes N         fixes per FixBatch (1000)
MAPMATCH_MAX_TRACK_POINTS   --max-track-points N        points per track (50000)
MAPMATCH_MAX_ANSWER_BYTES   --max-answer-bytes N        largest answer message (4 MiB)
MAPMATCH_MAX_VEHICLE_ID     --max-vehicle-id N          vehicle_id length, UTF-8 bytes (128)
MAPMATCH_MAX_TIME_JUMP      --max-time-jump SECONDS     larger time jumps restart a session (3600)
MAPMATCH_ONLINE_WORKERS     --online-workers N          threads for FixBatch slices (1)
MAPMATCH_INLINE_FIXES       --inline-fixes              single fixes on the event loop (on)
MAPMATCH_PROCESSES          --processes N               server processes on one port (1)
MAPMATCH_BATCH_PROCESSES    --batch-processes N         child processes for MatchTrack(s); 0: threads (1)
MAPMATCH_BATCH_NICE         --batch-nice N              their lower CPU priority, 0-19 (10)
MAPMATCH_BATCH_SCHED        --batch-sched CLASS         their CPU class: idle, idle-session, normal (idle)
MAPMATCH_BATCH_SLICE        --batch-slice N             fixes per slice of a batch answer (64)
MAPMATCH_MAX_MAP_BYTES      --max-map-bytes N           largest map file LoadMap reads (4 GiB)
MAPMATCH_LOAD_TIMEOUT       --load-timeout SECONDS      time limit of a map build from source (300)
MAPMATCH_LOAD_MEMORY_BYTES  --load-memory-bytes N       memory limit of a map build from source (8 GiB)
MAPMATCH_CONFIG             --config FILE               TOML file with any of the above
(none)                      --set SECTION.FIELD=VALUE   a matcher parameter (repeat), both matchers
==========================  ==========================  ===================================

The session store (:mod:`service.store_checkpoints`):

============================  ==========================  =================================
environment variable          flag                        meaning
============================  ==========================  =================================
MAPMATCH_SESSION_STORE        --session-store URL         Redis, ``redis://HOST:PORT/DB`` (off)
MAPMATCH_CHECKPOINT_INTERVAL  --checkpoint-interval S     seconds between checkpoints (1)
MAPMATCH_STORE_TIMEOUT        --store-timeout SECONDS     bound of a look-up (0.1)
============================  ==========================  =================================

Identities and caps (:mod:`service.auth`):

=================================  ==============================  ==========================
environment variable               flag                            meaning
=================================  ==============================  ==========================
MAPMATCH_IDENTITIES                --identities FILE               credentials (off)
MAPMATCH_MAX_IDENTITY_SESSIONS     --max-identity-sessions N       sessions per identity
MAPMATCH_MAX_IDENTITY_STREAMS      --max-identity-streams N        streams per identity
MAPMATCH_MAX_WATCH_PER_CONNECTION  --max-watch-per-connection N    health Watch per connection
MAPMATCH_MAX_WATCH_TOTAL           --max-watch-total N             health Watch in all
=================================  ==============================  ==========================

The TOML file uses the attribute names of :class:`ServerConfig` (``-`` or ``_``), maps as a
table of ``name = "path"``; relative paths are taken from the file's folder::

    address = "0.0.0.0:50051"
    map_dir = "/srv/maps"
    max_time_jump = 600
    [maps]
    hel = "helsinki.map"
    [match.model]          # matcher parameters (mapmatch.config), for the online matcher
    gps_sigma = 6.0        # over its defaults and the batch matcher over its own
    [match.online.region]  # a sub-section's table: the field's dotted path
    max_hypotheses = 16
    [match.batch.route]
    max_route_factor = 5

``--set SECTION.FIELD=VALUE`` flags (``--set batch.route.max_route_factor=5``) apply over the file's
``[match]`` tables.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mapmatch.config import BATCH_CONFIG, DEFAULT_CONFIG, MatchConfig
from mapmatch.errors import ConfigError

ENV_PREFIX = "MAPMATCH_"
BATCH_SCHED = ("idle", "idle-session", "normal")  # the batch workers' CPU classes
STORE_SCHEMES = ("redis://", "rediss://", "unix://")  # session store URLs


@dataclass(frozen=True)
class ServerConfig:
    """Everything the server needs besides the maps' contents.

    Attributes
    ----------
    address : str
        ``host:port`` to listen on; port 0 picks a free port.
    maps : tuple of (name, path)
        Maps to load at start.
    tls_cert, tls_key : Path or None
        PEM server certificate chain and key; both or neither.
    client_ca : Path or None
        PEM CA bundle; when set, clients must present a certificate it signed (mutual TLS).
    token : str or None
        When set, every call except health checks needs ``authorization: Bearer <token>``;
        that token is the operator (:mod:`service.auth`).
    identities : Path or None
        The identities file (TOML or JSON): vehicle and operator credentials, tokens stored
        as SHA-256; under mutual TLS a client certificate's name selects one. Read again on
        SIGHUP and when it changes. With neither this nor ``token``, every call is allowed.
    max_identity_sessions : int
        Live sessions one vehicle identity may hold (its own ``max_sessions`` in the
        identities file overrides it; an operator has no quota unless it has its own); one
        more gives RESOURCE_EXHAUSTED naming ``max_identity_sessions``.
    max_identity_streams : int
        Streams (``StreamFixes``, ``StreamFixBatches``, ``MatchTracks``) one vehicle identity
        may have open at once (its own ``max_streams`` overrides it; operators as above).
    max_watch_per_connection, max_watch_total : int
        Health ``Watch`` calls open at once on one connection, and in all; more are refused
        with RESOURCE_EXHAUSTED.
    max_sessions : int
        Live sessions over all maps; a new vehicle beyond it gets RESOURCE_EXHAUSTED.
    session_ttl : float
        Seconds an idle session lives.
    max_message_bytes : int
        Largest accepted request message; larger ones get RESOURCE_EXHAUSTED.
    workers : int
        Threads for batch matching and map loading (online updates run on the event loop).
    grace : float
        Seconds in-flight calls get to finish on shutdown.
    reuse_port : bool
        Set SO_REUSEPORT so several processes can share one port (off: a port in use is an error).
    log_format : str
        ``"json"`` (one JSON object per line) or ``"text"`` logs; ``"auto"``: text when standard
        error is a terminal, else JSON (``mapmatch serve`` resolves it before starting).
    map_dir : Path or None
        ``LoadMap`` reads only regular files inside this folder; None disables ``LoadMap`` of paths.
    max_batch_fixes : int
        Fixes in one ``FixBatch``; more give RESOURCE_EXHAUSTED naming ``max_batch_fixes``.
    max_track_points : int
        Points in one track; more give RESOURCE_EXHAUSTED naming ``max_track_points``, before
        any work. The default's answer fits in the default ``max_answer_bytes`` (a point
        takes at most 57 bytes of it); a track whose points alone cannot fit is refused before
        any work too, naming ``max_answer_bytes``.
    max_answer_bytes : int
        Largest answer message; a larger answer gives RESOURCE_EXHAUSTED naming ``max_answer_bytes``.
    max_vehicle_id : int
        Longest ``vehicle_id`` in UTF-8 bytes.
    max_time_jump : float
        A fix more than this many seconds away from its session's last accepted fix (either
        way) starts the session afresh (state ``reinitialised``) instead of being rejected.
    online_workers : int
        Threads matching ``FixBatch`` slices (and single fixes unless ``inline_fixes``).
    processes : int
        Server processes sharing the port (SO_REUSEPORT), so one host uses every core. Each
        process has its own sessions; a stream stays on the process that accepted its
        connection, so a vehicle should keep its connection (or export/import its session).
    batch_processes : int
        Child processes matching ``MatchTrack``/``MatchTracks`` on maps loaded from map files,
        off the online process's GIL (0: on the ``workers`` threads).
    batch_nice : int
        Added to those processes' nice value (0-19): on a busy host the online streams get
        the cores first.
    batch_sched : str
        Those processes' CPU class: ``"idle"`` (Linux ``SCHED_IDLE``: they run on CPU time the
        server's own threads do not want, so a long match cannot delay an online update),
        ``"idle-session"`` (also a session of their own, in an autogroup at ``batch_nice``, so
        on a host busy with other sessions their CPU time does not count against the
        server's share; the batch work then gets only what those sessions leave) or
        ``"normal"`` (time-shared at ``batch_nice``). Where ``SCHED_IDLE`` is missing,
        ``batch_nice`` alone applies.
    inline_fixes : bool
        Match a single fix (``StreamFixes``, ``SnapFix``) on the event loop, without a hop to
        an online thread: one fix is short, bounded work, and the hop costs more than it saves.
    batch_slice : int
        A ``FixBatch`` is matched in slices of this many fixes, other streams' work in between.
    max_map_bytes : int
        Largest file ``LoadMap`` (or a start-up map) reads.
    load_timeout : float
        Seconds a map build from an OSM/GIS source may take (in a child process).
    matcher, batch_matcher : MatchConfig
        The online and the batch matchers' parameters: each its own defaults
        (:data:`~mapmatch.config.DEFAULT_CONFIG`, :data:`~mapmatch.config.BATCH_CONFIG`) with
        the ``[match]`` tables of the config file and the ``--set`` flags applied.
    load_memory_bytes : int
        Address-space limit of that child process.
    session_store : str or None
        ``redis://HOST:PORT/DB`` (or ``rediss://``, ``unix://``): sessions outlive their
        process. Each changed session is written there behind its answer, at most every
        ``checkpoint_interval`` s and when its stream ends; a fix for a vehicle this process
        does not hold looks the vehicle up there first (:mod:`service.store_checkpoints`).
        None: sessions live in this process only.
    checkpoint_interval : float
        Seconds between two checkpoint passes (the most a process that dies can lose of a
        vehicle's session).
    store_timeout : float
        Seconds a fix for an unknown vehicle waits for the store's answer; past it the
        session starts afresh (counted).
    """

    address: str = "127.0.0.1:50051"
    maps: tuple[tuple[str, Path], ...] = ()
    tls_cert: Path | None = None
    tls_key: Path | None = None
    client_ca: Path | None = None
    token: str | None = field(default=None, repr=False)
    identities: Path | None = None
    max_identity_sessions: int = 10_000
    max_identity_streams: int = 256
    max_watch_per_connection: int = 16
    max_watch_total: int = 1000
    max_sessions: int = 100_000
    session_ttl: float = 600.0
    max_message_bytes: int = 4 * 1024 * 1024
    workers: int = 2
    grace: float = 10.0
    reuse_port: bool = False
    log_format: str = "auto"
    map_dir: Path | None = None
    max_batch_fixes: int = 1000
    max_track_points: int = 50_000
    max_answer_bytes: int = 4 * 1024 * 1024
    max_vehicle_id: int = 128
    max_time_jump: float = 3600.0
    online_workers: int = 1
    inline_fixes: bool = True
    processes: int = 1
    batch_processes: int = 1
    batch_nice: int = 10
    batch_sched: str = "idle"
    batch_slice: int = 64
    max_map_bytes: int = 4 * 1024**3
    load_timeout: float = 300.0
    load_memory_bytes: int = 8 * 1024**3
    matcher: MatchConfig = field(default=DEFAULT_CONFIG, repr=False)
    batch_matcher: MatchConfig = field(default=BATCH_CONFIG, repr=False)
    session_store: str | None = field(default=None, repr=False)  # the URL may hold a password
    checkpoint_interval: float = 1.0
    store_timeout: float = 0.1

    def __post_init__(self) -> None:
        if ":" not in self.address:
            raise ConfigError(f"address must be HOST:PORT, got {self.address!r}")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ConfigError("tls_cert and tls_key must be given together")
        if self.client_ca is not None and self.tls_cert is None:
            raise ConfigError("client_ca (mutual TLS) needs tls_cert and tls_key")
        if self.max_sessions < 1 or self.workers < 1 or self.max_message_bytes < 1024:
            raise ConfigError("max_sessions and workers must be >= 1, max_message_bytes >= 1024")
        if not self.session_ttl > 0 or self.grace < 0:
            raise ConfigError("session_ttl must be positive and grace non-negative")
        if self.batch_sched not in BATCH_SCHED:
            classes = ", ".join(BATCH_SCHED)
            raise ConfigError(f"batch_sched must be one of {classes}, got {self.batch_sched!r}")
        if self.log_format not in ("auto", "json", "text"):
            raise ConfigError(f"log_format must be auto, json or text, got {self.log_format!r}")
        if self.token is not None and not self.token.strip():
            raise ConfigError("token must not be empty")
        for name in ("max_batch_fixes", "max_track_points", "max_answer_bytes", "max_vehicle_id",
                     "online_workers", "batch_slice", "max_map_bytes", "load_memory_bytes",
                     "processes", "max_identity_sessions", "max_identity_streams",
                     "max_watch_per_connection", "max_watch_total"):  # fmt: skip
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"{name} must be a positive integer, got {v!r}")
        if (
            isinstance(self.batch_processes, bool)
            or not isinstance(self.batch_processes, int)
            or (self.batch_processes < 0)
        ):
            raise ConfigError(f"batch_processes must be 0 or more, got {self.batch_processes!r}")
        if (
            isinstance(self.batch_nice, bool)
            or not isinstance(self.batch_nice, int)
            or not (0 <= self.batch_nice <= 19)
        ):
            raise ConfigError(f"batch_nice must be an integer from 0 to 19, got {self.batch_nice!r}")
        if self.session_store is not None and not self.session_store.startswith(STORE_SCHEMES):
            raise ConfigError(
                "session_store must be a Redis URL (redis://HOST:PORT/DB, rediss://... or unix://...)"
            )
        for name in ("max_time_jump", "load_timeout", "checkpoint_interval", "store_timeout"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not v > 0:
                raise ConfigError(f"{name} must be a positive number of seconds, got {v!r}")
        names = [n for n, _ in self.maps]
        if len(set(names)) != len(names):
            raise ConfigError("map names must be unique")

    @property
    def tls(self) -> bool:
        return self.tls_cert is not None

    def replace(self, **changes: object) -> ServerConfig:
        return dataclasses.replace(self, **changes)  # type: ignore[arg-type]


def parse_map_spec(spec: str) -> tuple[str, Path]:
    """``NAME=PATH`` to ``(name, path)``; a bare PATH is named after its file stem."""
    name, sep, path = spec.partition("=")
    if not sep:
        p = Path(spec)
        name, path = p.name.split(".")[0], spec
    name = name.strip()
    if not name or not path:
        raise ConfigError(f"map must be NAME=PATH, got {spec!r}")
    return name, Path(path)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the server flags (all default to None: unset flags fall back to the environment)."""
    parser.add_argument("--address", help="HOST:PORT to listen on [MAPMATCH_ADDRESS; 127.0.0.1:50051]")
    parser.add_argument(
        "--map",
        dest="maps",
        action="append",
        metavar="NAME=PATH",
        help="a map artifact (or OSM/GIS source) to serve; repeat for several cities [MAPMATCH_MAPS]",
    )
    parser.add_argument("--tls-cert", type=Path, help="PEM certificate chain [MAPMATCH_TLS_CERT]")
    parser.add_argument("--tls-key", type=Path, help="PEM private key [MAPMATCH_TLS_KEY]")
    parser.add_argument("--client-ca", type=Path, help="PEM CA: require client certs [MAPMATCH_CLIENT_CA]")
    parser.add_argument("--token", help="required bearer token [MAPMATCH_TOKEN]")
    parser.add_argument("--token-file", type=Path, help="file holding the bearer token [MAPMATCH_TOKEN_FILE]")
    parser.add_argument(
        "--identities",
        type=Path,
        help="vehicle/operator credentials, TOML or JSON, reloaded on SIGHUP [MAPMATCH_IDENTITIES]",
    )
    parser.add_argument("--max-sessions", type=int, help="live sessions [MAPMATCH_MAX_SESSIONS; 100000]")
    parser.add_argument("--session-ttl", type=float, help="idle session seconds [MAPMATCH_SESSION_TTL; 600]")
    parser.add_argument("--max-message-bytes", type=int, help="largest request [MAPMATCH_MAX_MESSAGE_BYTES]")
    parser.add_argument("--workers", type=int, help="batch/map-load threads [MAPMATCH_WORKERS; 2]")
    parser.add_argument("--grace", type=float, help="shutdown drain seconds [MAPMATCH_GRACE; 10]")
    parser.add_argument(
        "--reuse-port",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="SO_REUSEPORT for several processes on one port [MAPMATCH_REUSE_PORT; off]",
    )
    parser.add_argument(
        "--log-format",
        choices=("auto", "json", "text"),
        help="JSON lines or text logs; auto: text on a terminal [MAPMATCH_LOG_FORMAT; auto]",
    )
    parser.add_argument(
        "--inline-fixes",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="match single fixes on the event loop, no thread hop [MAPMATCH_INLINE_FIXES; on]",
    )
    parser.add_argument(
        "--batch-sched",
        choices=BATCH_SCHED,
        help="CPU class of the batch processes: idle (SCHED_IDLE), idle-session (also a session "
        "of their own at --batch-nice) or normal (at --batch-nice) [MAPMATCH_BATCH_SCHED; idle]",
    )
    parser.add_argument(
        "--session-store",
        metavar="URL",
        help="Redis session store, redis://HOST:PORT/DB: sessions outlive their process "
        "[MAPMATCH_SESSION_STORE; off]",
    )
    parser.add_argument("--config", type=Path, help="TOML file with server settings [MAPMATCH_CONFIG]")
    parser.add_argument(
        "--set", action="append", default=None, metavar="SECTION.FIELD=VALUE", dest="settings",
        help="a matcher parameter by its full name in mapmatch.config, for the online and the "
        "batch matcher (repeatable; over the config file's [match] tables)",
    )  # fmt: skip
    parser.add_argument(
        "--map-dir", type=Path, help="LoadMap reads only files in here [MAPMATCH_MAP_DIR; off]"
    )
    for flag, kind, text in _LIMIT_FLAGS:
        parser.add_argument(flag, type=kind, help=text)


_LIMIT_FLAGS: tuple[tuple[str, type, str], ...] = (
    ("--max-batch-fixes", int, "fixes per FixBatch [MAPMATCH_MAX_BATCH_FIXES; 1000]"),
    ("--max-track-points", int, "points per track [MAPMATCH_MAX_TRACK_POINTS; 50000]"),
    ("--max-answer-bytes", int, "largest answer message [MAPMATCH_MAX_ANSWER_BYTES; 4 MiB]"),
    ("--max-vehicle-id", int, "vehicle_id length in bytes [MAPMATCH_MAX_VEHICLE_ID; 128]"),
    ("--max-time-jump", float, "seconds; larger jumps restart a session [MAPMATCH_MAX_TIME_JUMP; 3600]"),
    ("--online-workers", int, "threads for FixBatch slices [MAPMATCH_ONLINE_WORKERS; 1]"),
    ("--batch-slice", int, "fixes per slice of a batch answer [MAPMATCH_BATCH_SLICE; 64]"),
    ("--max-map-bytes", int, "largest map file read [MAPMATCH_MAX_MAP_BYTES; 4 GiB]"),
    ("--load-timeout", float, "seconds for a map build from source [MAPMATCH_LOAD_TIMEOUT; 300]"),
    ("--load-memory-bytes", int, "memory for a map build from source [MAPMATCH_LOAD_MEMORY_BYTES; 8 GiB]"),
    ("--processes", int, "server processes sharing the port, own sessions each [MAPMATCH_PROCESSES; 1]"),
    ("--batch-processes", int, "child processes for MatchTrack(s), 0: threads [MAPMATCH_BATCH_PROCESSES; 1]"),
    ("--batch-nice", int, "lower CPU priority of those, 0-19 [MAPMATCH_BATCH_NICE; 10]"),
    ("--checkpoint-interval", float, "seconds between checkpoints [MAPMATCH_CHECKPOINT_INTERVAL; 1]"),
    ("--store-timeout", float, "seconds a look-up in the store may take [MAPMATCH_STORE_TIMEOUT; 0.1]"),
    ("--max-identity-sessions", int, "sessions per identity [MAPMATCH_MAX_IDENTITY_SESSIONS; 10000]"),
    ("--max-identity-streams", int, "open streams per identity [MAPMATCH_MAX_IDENTITY_STREAMS; 256]"),
    (
        "--max-watch-per-connection",
        int,
        "health Watch calls per connection [MAPMATCH_MAX_WATCH_PER_CONNECTION; 16]",
    ),
    ("--max-watch-total", int, "health Watch calls in all [MAPMATCH_MAX_WATCH_TOTAL; 1000]"),
)
_NUMBERS: dict[str, type[int] | type[float]] = {
    "max_sessions": int,
    "session_ttl": float,
    "max_message_bytes": int,
    "workers": int,
    "grace": float,
    **{f[2:].replace("-", "_"): k for f, k, _ in _LIMIT_FLAGS},
}
_PATHS = ("tls_cert", "tls_key", "client_ca", "map_dir", "identities")
_BOOLS = ("reuse_port", "inline_fixes")
_FIELDS = {f.name for f in dataclasses.fields(ServerConfig)}


def _bool(name: str, text: str) -> bool:
    t = text.strip().lower()
    if t in ("1", "true", "yes", "on"):
        return True
    if t in ("0", "false", "no", "off"):
        return False
    raise ConfigError(f"{ENV_PREFIX}{name} must be a boolean, got {text!r}")


def _num(name: str, text: str, kind: type[int] | type[float]) -> int | float:
    try:
        return kind(text)
    except ValueError:
        raise ConfigError(f"{ENV_PREFIX}{name} must be a number, got {text!r}") from None


def read_config_file(path: Path) -> dict[str, Any]:
    """Settings from a TOML file, keyed by :class:`ServerConfig` attribute (paths resolved).

    Raises
    ------
    ConfigError
        Unreadable file, bad TOML, an unknown key or a value of the wrong type.
    """
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"config file {path}: cannot read it ({exc.strerror})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"config file {path}: not valid TOML ({exc})") from None
    base = Path(path).parent
    out: dict[str, Any] = {}
    for raw_key, value in data.items():
        key = raw_key.replace("-", "_")
        if key in ("matcher", "batch_matcher") or (key not in _FIELDS and key not in ("token_file", "match")):
            raise ConfigError(f"config file {path}: unknown setting {raw_key!r}")
        if key == "match":
            if not isinstance(value, dict):
                raise ConfigError(
                    f"config file {path}: match must be a table of sections ([match.model], ...)"
                )
            try:
                out["matcher"] = DEFAULT_CONFIG.updated(value, prefix="match.")
                out["batch_matcher"] = BATCH_CONFIG.updated(value, prefix="match.")
            except ConfigError as exc:
                raise ConfigError(f"config file {path}: {exc}") from None
        elif key == "maps":
            if not isinstance(value, dict) or not all(isinstance(v, str) for v in value.values()):
                raise ConfigError(f'config file {path}: maps must be a table of name = "path"')
            out[key] = tuple((str(n), base / v) for n, v in value.items())
        elif key in _PATHS or key == "token_file":
            if not isinstance(value, str):
                raise ConfigError(f"config file {path}: {raw_key} must be a path string")
            out[key] = base / value
        elif key in _NUMBERS:
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ConfigError(f"config file {path}: {raw_key} must be a number")
            out[key] = _NUMBERS[key](value)
        elif key in _BOOLS:
            if not isinstance(value, bool):
                raise ConfigError(f"config file {path}: {raw_key} must be true or false")
            out[key] = value
        else:
            if not isinstance(value, str):
                raise ConfigError(f"config file {path}: {raw_key} must be a string")
            out[key] = value
    return out


def _read_token(path: Path) -> str:
    try:
        return Path(path).read_text().strip()
    except OSError as exc:
        raise ConfigError(f"token file {path}: cannot read it ({exc.strerror})") from None


def config_from(
    args: argparse.Namespace | None = None, environ: Mapping[str, str] | None = None
) -> ServerConfig:
    """Merge CLI flags (``args`` from :func:`add_arguments`) over the environment over the
    config file over defaults."""
    env = os.environ if environ is None else environ
    ns = vars(args) if args is not None else {}
    cfg_path = ns.get("config") or env.get(ENV_PREFIX + "CONFIG") or None
    file = read_config_file(Path(cfg_path)) if cfg_path else {}
    out: dict[str, object] = {k: v for k, v in file.items() if k != "token_file"}

    def pick(key: str) -> object:
        v = ns.get(key)
        if v is not None:
            return v
        text = env.get(ENV_PREFIX + key.upper())
        return text if text not in (None, "") else None

    for key, kind in _NUMBERS.items():
        v = pick(key)
        if v is not None:
            out[key] = _num(key.upper(), v, kind) if isinstance(v, str) else v
    for key in ("address", "log_format", "token", "batch_sched", "session_store"):
        v = pick(key)
        if v is not None:
            out[key] = str(v)
    for key in _PATHS:
        v = pick(key)
        if v is not None:
            out[key] = Path(str(v))
    for key in _BOOLS:
        v = pick(key)
        if v is not None:
            out[key] = _bool(key.upper(), v) if isinstance(v, str) else bool(v)
    if pick("token") is None:
        tf = pick("token_file")
        if tf is not None:
            out["token"] = _read_token(Path(str(tf)))
        elif "token" not in out and "token_file" in file:
            out["token"] = _read_token(file["token_file"])
    specs = ns.get("maps")
    if not specs:
        text = env.get(ENV_PREFIX + "MAPS", "")
        specs = [s for s in text.split(",") if s.strip()]
    if specs:
        out["maps"] = tuple(parse_map_spec(s) for s in specs)
    settings = ns.get("settings") or []
    if settings:
        for key, default in (("matcher", DEFAULT_CONFIG), ("batch_matcher", BATCH_CONFIG)):
            base = out.get(key, default)
            assert isinstance(base, MatchConfig)
            out[key] = base.with_settings(settings)
    try:
        return ServerConfig(**out)  # type: ignore[arg-type]
    except TypeError as exc:
        raise ConfigError(f"bad setting: {exc}") from None
