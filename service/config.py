"""Server configuration from CLI flags and ``MAPMATCH_*`` environment variables.

Precedence: a CLI flag, else the environment variable, else the default. Defaults are safe:
plain (no TLS) on loopback.

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
MAPMATCH_REUSE_PORT         --reuse-port / --no-reuse-port  SO_REUSEPORT (on), for several processes
MAPMATCH_LOG_FORMAT         --log-format json|text      access log format (json)
==========================  ==========================  ===================================
"""

from __future__ import annotations

import argparse
import dataclasses
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from mapmatch.errors import ConfigError

ENV_PREFIX = "MAPMATCH_"


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
        When set, every call except health checks needs ``authorization: Bearer <token>``.
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
        Set SO_REUSEPORT so several processes can share one port.
    log_format : str
        ``"json"`` or ``"text"`` access logs.
    """

    address: str = "127.0.0.1:50051"
    maps: tuple[tuple[str, Path], ...] = ()
    tls_cert: Path | None = None
    tls_key: Path | None = None
    client_ca: Path | None = None
    token: str | None = field(default=None, repr=False)
    max_sessions: int = 100_000
    session_ttl: float = 600.0
    max_message_bytes: int = 4 * 1024 * 1024
    workers: int = 2
    grace: float = 10.0
    reuse_port: bool = True
    log_format: str = "json"

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
        if self.log_format not in ("json", "text"):
            raise ConfigError(f"log_format must be json or text, got {self.log_format!r}")
        if self.token is not None and not self.token.strip():
            raise ConfigError("token must not be empty")
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
    parser.add_argument("--max-sessions", type=int, help="live sessions [MAPMATCH_MAX_SESSIONS; 100000]")
    parser.add_argument("--session-ttl", type=float, help="idle session seconds [MAPMATCH_SESSION_TTL; 600]")
    parser.add_argument("--max-message-bytes", type=int, help="largest request [MAPMATCH_MAX_MESSAGE_BYTES]")
    parser.add_argument("--workers", type=int, help="batch/map-load threads [MAPMATCH_WORKERS; 2]")
    parser.add_argument("--grace", type=float, help="shutdown drain seconds [MAPMATCH_GRACE; 10]")
    parser.add_argument(
        "--reuse-port",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="SO_REUSEPORT for several processes on one port [MAPMATCH_REUSE_PORT; on]",
    )
    parser.add_argument("--log-format", choices=("json", "text"), help="access logs [MAPMATCH_LOG_FORMAT]")


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


def config_from(
    args: argparse.Namespace | None = None, environ: Mapping[str, str] | None = None
) -> ServerConfig:
    """Merge CLI flags (``args`` from :func:`add_arguments`) over the environment over defaults."""
    env = os.environ if environ is None else environ
    ns = vars(args) if args is not None else {}
    out: dict[str, object] = {}

    def pick(key: str) -> object:
        v = ns.get(key)
        if v is not None:
            return v
        text = env.get(ENV_PREFIX + key.upper())
        return text if text not in (None, "") else None

    for key, kind in (("max_sessions", int), ("session_ttl", float), ("max_message_bytes", int),
                      ("workers", int), ("grace", float)):  # fmt: skip
        v = pick(key)
        if v is not None:
            out[key] = _num(key.upper(), v, kind) if isinstance(v, str) else v
    for key in ("address", "log_format", "token"):
        v = pick(key)
        if v is not None:
            out[key] = str(v)
    for key in ("tls_cert", "tls_key", "client_ca"):
        v = pick(key)
        if v is not None:
            out[key] = Path(str(v))
    v = pick("reuse_port")
    if v is not None:
        out["reuse_port"] = _bool("REUSE_PORT", v) if isinstance(v, str) else bool(v)
    if "token" not in out:
        tf = pick("token_file")
        if tf is not None:
            out["token"] = Path(str(tf)).read_text().strip()
    specs = ns.get("maps")
    if not specs:
        text = env.get(ENV_PREFIX + "MAPS", "")
        specs = [s for s in text.split(",") if s.strip()]
    out["maps"] = tuple(parse_map_spec(s) for s in specs)
    return ServerConfig(**out)  # type: ignore[arg-type]
