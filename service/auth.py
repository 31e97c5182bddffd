"""Who may call what: identities, roles and the rule of every RPC.

A caller is a *vehicle* or an *operator* (:class:`Role`). Its :class:`Identity` comes from

* a bearer token (``authorization: Bearer <token>``) found in the identities file
  (``--identities``; the file stores each token's SHA-256, never the token), or the one
  ``--token`` of the server (the operator);
* under mutual TLS, the client certificate: its common name or a DNS/URI subject alternative
  name names an identity of the identities file.

A vehicle identity names its vehicle ids (``vehicles``) and/or id prefixes
(``vehicle_prefixes``, for a fusion node that serves several vehicles). :data:`METHOD_RULES`
states for every RPC who may call it; a vehicle may snap, stream, export and end only the
sessions of its own vehicles (checked for every fix of a stream), and only the operator may
load and unload maps, import sessions and list them. A refusal is UNAUTHENTICATED (no or an unknown
credential) or PERMISSION_DENIED naming the missing right; it never tells whether another
vehicle's session exists. With neither a token nor an identities file every call is allowed
(the server logs a warning).

The identities file is TOML or JSON::

    [[identity]]
    name = "node-7"                      # also the certificate name under mutual TLS
    role = "vehicle"                     # or "operator"
    token_sha256 = "9f86d08..."          # sha256 of the token, hex (optional under mTLS)
    vehicles = ["car-1", "car-2"]
    vehicle_prefixes = ["node7/"]
    max_sessions = 50                    # optional: over the server's defaults
    max_streams = 4

It is read again on SIGHUP and when its modification time changes (looked at at most once a
second); a file that does not parse keeps the table in force and logs why.
"""

from __future__ import annotations

import contextvars
import enum
import hashlib
import hmac
import json
import logging
import os
import threading
import time
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc

from mapmatch.errors import ConfigError
from service.errors import LimitError, StatusError

log = logging.getLogger("mapmatch.service")

__all__ = [
    "CALLER",
    "METHOD_RULES",
    "AccessError",
    "Identity",
    "IdentityTable",
    "Quotas",
    "Role",
    "Rule",
    "check_vehicle",
    "hash_token",
    "read_identities",
    "rule_for",
]


class Role(enum.Enum):
    """What a caller is."""

    VEHICLE = "vehicle"
    OPERATOR = "operator"


@dataclass(frozen=True, slots=True)
class Identity:
    """One caller: its name, role, vehicles and quotas.

    Attributes
    ----------
    name : str
        Shown in logs; under mutual TLS the certificate name that selects it.
    role : Role
        Vehicle or operator.
    vehicles : frozenset of str
        The vehicle ids a vehicle identity may act for.
    vehicle_prefixes : tuple of str
        Id prefixes it may act for (every id starting with one).
    token_sha256 : str
        SHA-256 of its bearer token, lower-case hex ("" for certificate-only identities).
    max_sessions, max_streams : int or None
        Its own quotas (None: the server's ``max_identity_sessions``/``max_identity_streams``).
    """

    name: str
    role: Role
    vehicles: frozenset[str] = frozenset()
    vehicle_prefixes: tuple[str, ...] = ()
    token_sha256: str = field(default="", repr=False)
    max_sessions: int | None = None
    max_streams: int | None = None

    @property
    def operator(self) -> bool:
        return self.role is Role.OPERATOR

    def may_act_for(self, vehicle_id: str) -> bool:
        """Whether this identity may act for ``vehicle_id`` (the operator for every vehicle)."""
        if self.role is Role.OPERATOR or vehicle_id in self.vehicles:
            return True
        return bool(self.vehicle_prefixes) and vehicle_id.startswith(self.vehicle_prefixes)


class AccessError(StatusError):
    """A refused call: UNAUTHENTICATED or PERMISSION_DENIED, ``field`` naming what is missing."""

    @classmethod
    def unauthenticated(cls) -> AccessError:
        return cls(
            grpc.StatusCode.UNAUTHENTICATED,
            "",
            "missing or unknown credential (send authorization: Bearer <token>, or a client "
            "certificate named in the identities file)",
        )

    @classmethod
    def vehicle(cls, fld: str = "vehicle_id") -> AccessError:
        return cls(
            grpc.StatusCode.PERMISSION_DENIED, fld, f"{fld}: this credential may not act for that vehicle"
        )

    @classmethod
    def operator(cls, method: str) -> AccessError:
        return cls(grpc.StatusCode.PERMISSION_DENIED, "", f"{method} needs the operator role")


# ---------------------------------------------------------------------------------- rules
@dataclass(frozen=True, slots=True)
class Rule:
    """Who may call one RPC.

    Attributes
    ----------
    open : bool
        Anyone, with or without a credential (health ``Check`` and ``Watch``).
    operator_only : bool
        Only the operator role.
    vehicle_field : str or None
        The request's field naming a vehicle the caller must own (checked by the
        interceptor for unary calls); None: none, or checked per message by the servicer.
    per_fix : bool
        A stream whose every fix names a vehicle the caller must own (checked by the servicer).
    stream : bool
        Counts against the caller's concurrent-stream quota.
    """

    open: bool = False
    operator_only: bool = False
    vehicle_field: str | None = None
    per_fix: bool = False
    stream: bool = False


_MM = "/mapmatch.v1.MapMatch/"
_ANY = Rule()
_OPERATOR = Rule(operator_only=True)
_OWN = Rule(vehicle_field="vehicle_id")
METHOD_RULES: dict[str, Rule] = {
    _MM + "StreamFixes": Rule(per_fix=True, stream=True),
    _MM + "StreamFixBatches": Rule(per_fix=True, stream=True),
    _MM + "SnapFix": _OWN,
    _MM + "MatchTrack": _ANY,
    _MM + "MatchTracks": Rule(stream=True),
    _MM + "ListMaps": _ANY,
    _MM + "GetMapInfo": _ANY,
    _MM + "LoadMap": _OPERATOR,
    _MM + "UnloadMap": _OPERATOR,
    _MM + "ExportSession": _OWN,
    _MM + "ImportSession": _OPERATOR,
    _MM + "EndSession": _OWN,
    _MM + "ListSessions": _OPERATOR,
    "/grpc.health.v1.Health/Check": Rule(open=True),
    "/grpc.health.v1.Health/Watch": Rule(open=True),
    "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo": _ANY,
    "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo": _ANY,
}
"""The rule of every RPC; a method not listed needs the operator role."""


def rule_for(method: str) -> Rule:
    """The rule of a full method name (``/package.Service/Method``)."""
    return METHOD_RULES.get(method, _OPERATOR)


CALLER: contextvars.ContextVar[Identity | None] = contextvars.ContextVar("mapmatch_caller", default=None)
"""The identity of the call being served (None: the server checks no credentials)."""


def check_vehicle(caller: Identity | None, vehicle_id: str, fld: str = "vehicle_id") -> None:
    """Raise :class:`AccessError` unless ``caller`` may act for ``vehicle_id``.

    The same refusal whether or not that vehicle has a session. An empty id passes: the
    request's own validation names the missing field.
    """
    if caller is not None and vehicle_id and not caller.may_act_for(vehicle_id):
        raise AccessError.vehicle(fld)


# ---------------------------------------------------------------------------------- the table
def hash_token(token: str | bytes) -> str:
    """SHA-256 of a token, lower-case hex (how the identities file stores tokens)."""
    data = token.encode() if isinstance(token, str) else token
    return hashlib.sha256(data).hexdigest()


def _strings(entry: Mapping[str, Any], key: str, where: str) -> list[str]:
    v = entry.get(key, [])
    if not isinstance(v, list) or not all(isinstance(s, str) and s for s in v):
        raise ConfigError(f"{where}: {key} must be a list of non-empty strings")
    return list(v)


def _quota(entry: Mapping[str, Any], key: str, where: str) -> int | None:
    v = entry.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ConfigError(f"{where}: {key} must be a positive integer")
    return v


_KEYS = {"name", "role", "token_sha256", "vehicles", "vehicle_prefixes", "max_sessions", "max_streams"}


def _identity(entry: Any, where: str) -> Identity:
    if not isinstance(entry, dict):
        raise ConfigError(f"{where}: must be a table")
    unknown = sorted(set(entry) - _KEYS)
    if unknown:
        raise ConfigError(f"{where}: unknown key {unknown[0]!r}")
    name, role = entry.get("name"), entry.get("role")
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{where}: name is required")
    if role not in ("vehicle", "operator"):
        raise ConfigError(f"{where}: role must be vehicle or operator, got {role!r}")
    digest = entry.get("token_sha256", "")
    if not isinstance(digest, str) or (
        digest and (len(digest) != 64 or any(c not in "0123456789abcdefABCDEF" for c in digest))
    ):
        raise ConfigError(f"{where}: token_sha256 must be 64 hex digits (the SHA-256 of the token)")
    vehicles = _strings(entry, "vehicles", where)
    prefixes = _strings(entry, "vehicle_prefixes", where)
    if role == "vehicle" and not (vehicles or prefixes):
        raise ConfigError(f"{where}: a vehicle identity needs vehicles or vehicle_prefixes")
    return Identity(
        name=name,
        role=Role(role),
        vehicles=frozenset(vehicles),
        vehicle_prefixes=tuple(prefixes),
        token_sha256=digest.lower(),
        max_sessions=_quota(entry, "max_sessions", where),
        max_streams=_quota(entry, "max_streams", where),
    )


def read_identities(path: Path) -> list[Identity]:
    """The identities of a TOML or JSON file (``identity = [...]``, or a JSON list).

    Raises
    ------
    ConfigError
        Unreadable file, bad syntax, a bad entry, or a name or token used twice.
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"identities file {path}: cannot read it ({exc})") from None
    try:
        data: Any = json.loads(text) if Path(path).suffix.lower() == ".json" else tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"identities file {path}: does not parse ({exc})") from None
    entries = data.get("identity", None) if isinstance(data, dict) else data
    if not isinstance(entries, list):
        raise ConfigError(f"identities file {path}: needs a list of identities ([[identity]] tables)")
    out = [_identity(e, f"identities file {path}: identity {i}") for i, e in enumerate(entries)]
    for what, keys in (
        ("name", [i.name for i in out]),
        ("token", [i.token_sha256 for i in out if i.token_sha256]),
    ):
        if len(set(keys)) != len(keys):
            raise ConfigError(f"identities file {path}: a {what} is used twice")
    return out


class IdentityTable:
    """The credentials a server accepts: the identities file (reloadable) and ``--token``.

    Parameters
    ----------
    path
        The identities file, or None.
    token
        The server's single bearer token (the operator), or None.
    check_every
        Seconds between two looks at the file's modification time.
    """

    def __init__(self, *, path: Path | None, token: str | None, check_every: float = 1.0) -> None:
        self.path = path
        self.check_every = check_every
        self._lock = threading.Lock()
        self._tokens: dict[str, Identity] = {}
        self._names: dict[str, Identity] = {}
        self._legacy = hash_token(token) if token else ""
        self._legacy_id = Identity(name="token", role=Role.OPERATOR, token_sha256=self._legacy)
        self._mtime: int | None = None
        self._next_check = 0.0
        if path is not None:
            self._install(read_identities(path), self._stat())

    @property
    def enabled(self) -> bool:
        """Whether credentials are checked at all."""
        return self.path is not None or bool(self._legacy)

    def _stat(self) -> int | None:
        assert self.path is not None
        try:
            return os.stat(self.path).st_mtime_ns
        except OSError:
            return None

    def _install(self, ids: Iterable[Identity], mtime: int | None) -> None:
        ids = list(ids)
        with self._lock:
            self._tokens = {i.token_sha256: i for i in ids if i.token_sha256}
            self._names = {i.name: i for i in ids}
            self._mtime = mtime

    def reload(self) -> bool:
        """Read the identities file again; on an error keep the table in force (logged)."""
        if self.path is None:
            return False
        mtime = self._stat()
        try:
            ids = read_identities(self.path)
        except ConfigError as exc:
            log.error("%s; the identities read before stay in force", exc)
            self._mtime = mtime
            return False
        self._install(ids, mtime)
        log.info("identities file %s read: %d identities", self.path.name, len(ids))
        return True

    def _maybe_reload(self) -> None:
        now = time.monotonic()
        if self.path is None or now < self._next_check:
            return
        self._next_check = now + self.check_every
        if self._stat() != self._mtime:
            self.reload()

    def by_token(self, token: bytes) -> Identity | None:
        """The identity of a bearer token (digests compared in constant time)."""
        self._maybe_reload()
        digest = hash_token(token)
        found = self._tokens.get(digest)
        if found is not None and hmac.compare_digest(found.token_sha256, digest):
            return found
        if self._legacy and hmac.compare_digest(self._legacy, digest):
            return self._legacy_id
        return None

    def by_names(self, names: Iterable[str]) -> Identity | None:
        """The identity a client certificate's names select (the first that is known)."""
        self._maybe_reload()
        for n in names:
            found = self._names.get(n)
            if found is not None:
                return found
        return None


# ---------------------------------------------------------------------------------- quotas
class Quotas:
    """Per-identity counts of concurrent streams and live sessions.

    A vehicle identity without quotas of its own gets the defaults; an operator has no quota
    unless the identities file gives it one (the ``--token`` of a server that predates the
    identities file may stand for a whole fleet).

    Parameters
    ----------
    max_sessions, max_streams
        Defaults for vehicle identities without quotas of their own.
    """

    def __init__(self, *, max_sessions: int, max_streams: int) -> None:
        self.max_sessions = max_sessions
        self.max_streams = max_streams
        self._lock = threading.Lock()
        self._streams: dict[str, int] = {}
        self._sessions: dict[str, dict[tuple[str, str], None]] = {}

    def _cap(self, who: Identity, own: int | None, default: int) -> int | None:
        if own is not None:
            return own
        return None if who.operator else default

    def open_stream(self, who: Identity) -> None:
        """Count a stream of ``who``; :class:`LimitError` past its quota."""
        cap = self._cap(who, who.max_streams, self.max_streams)
        with self._lock:
            n = self._streams.get(who.name, 0)
            if cap is not None and n >= cap:
                raise LimitError(
                    "max_identity_streams", f"this credential has {n} streams open, its limit is {cap}"
                )
            self._streams[who.name] = n + 1

    def close_stream(self, who: Identity) -> None:
        with self._lock:
            n = self._streams.get(who.name, 0) - 1
            if n > 0:
                self._streams[who.name] = n
            else:
                self._streams.pop(who.name, None)

    def claim_session(self, who: Identity, key: tuple[str, str], live: Any) -> None:
        """Count a new session ``key`` for ``who``; :class:`LimitError` past its quota.

        ``live(key)`` tells whether a session counted before still lives (ended and expired
        ones are forgotten here when the quota is reached).
        """
        cap = self._cap(who, who.max_sessions, self.max_sessions)
        if cap is None:
            return
        with self._lock:
            mine = self._sessions.setdefault(who.name, {})
            if key in mine:
                return
            if len(mine) >= cap:
                for k in [k for k in mine if live(k) is None]:
                    del mine[k]
                if len(mine) >= cap:
                    raise LimitError(
                        "max_identity_sessions",
                        f"this credential holds {len(mine)} sessions, its limit is {cap}",
                    )
            mine[key] = None

    def streams(self, who: Identity) -> int:
        with self._lock:
            return self._streams.get(who.name, 0)
