"""The session store on Redis: its keys, its records and its two clients.

A record is one vehicle's session as a checkpoint writes it: the session's state (the v2
blob of :mod:`mapmatch.online.codec`) and the answer to its last accepted fix (a serialised
``mapmatch.v1.SnapResult``, empty when none), so that a resend of that fix to another server
gets the same answer. It is kept under ``mapmatch:session:<map checksum>:<vehicle id>``: a
session moves only between servers that hold the same version of its map.

Writes go through a blocking client (the checkpoint thread, in pipelined batches); look-ups
go through an asyncio client on the server's event loop, so a slow store delays only the fix
that waits for it. Every call raises on failure (``redis.RedisError``, ``OSError``,
``TimeoutError``); the caller counts it and carries on.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import Any

from mapmatch.extras import require

KEY_PREFIX = b"mapmatch:session:"
MAGIC = b"MMS1"
_HEAD = struct.Struct(">4sI")  # magic, length of the state blob
WRITE_BATCH = 256  # sessions per pipelined round trip
WRITE_TIMEOUT = 2.0  # s: a write or probe that takes longer has failed (off the fixes' path)


class RecordError(ValueError):
    """A store record that is not one this module wrote."""


def session_key(checksum: str, vehicle_id: str) -> bytes:
    """The record key of a vehicle on a map (by the map's content checksum)."""
    return KEY_PREFIX + checksum.encode() + b":" + vehicle_id.encode()


def pack(state: bytes, answer: bytes = b"") -> bytes:
    """A record: the state blob and the last answer (a serialised ``SnapResult``)."""
    return _HEAD.pack(MAGIC, len(state)) + state + answer


def unpack(data: bytes) -> tuple[bytes, bytes]:
    """``(state, answer)`` of a record; raises :class:`RecordError` for anything else."""
    if len(data) < _HEAD.size:
        raise RecordError("record too short")
    magic, n = _HEAD.unpack_from(data)
    if magic != MAGIC or _HEAD.size + n > len(data):
        raise RecordError("not a session record")
    return data[_HEAD.size : _HEAD.size + n], data[_HEAD.size + n :]


class RedisStore:
    """The session store's clients for one Redis URL.

    Parameters
    ----------
    url
        ``redis://[:password@]HOST:PORT/DB``, ``rediss://...`` or ``unix://PATH?db=N``.
    timeout
        Seconds a look-up may take (the asyncio client's socket timeout; the caller bounds
        the whole look-up with it too).

    Raises
    ------
    MissingExtraError
        The ``redis`` package is not installed (``pip install 'mapmatch[redis]'``).
    """

    def __init__(self, url: str, *, timeout: float) -> None:
        why = "the session store (--session-store)"
        self._redis = require("redis", extra="redis", needed_for=why)
        self._aredis = require("redis.asyncio", extra="redis", needed_for=why)
        self.url = url
        self.timeout = timeout
        self._sync = self._redis.Redis.from_url(
            url, socket_timeout=WRITE_TIMEOUT, socket_connect_timeout=WRITE_TIMEOUT
        )
        self._async: Any = None  # made on the event loop that first looks a vehicle up

    # ------------------------------------------------------------------ blocking (checkpoint thread)
    def ping(self) -> None:
        self._sync.ping()

    def write(self, records: Sequence[tuple[bytes, bytes]], *, ttl_ms: int) -> int:
        """Set each ``(key, record)`` with a time to live; returns the bytes sent."""
        sent = 0
        for i in range(0, len(records), WRITE_BATCH):
            pipe = self._sync.pipeline(transaction=False)
            for key, value in records[i : i + WRITE_BATCH]:
                pipe.set(key, value, px=ttl_ms)
                sent += len(key) + len(value)
            pipe.execute()
        return sent

    def delete(self, keys: Sequence[bytes]) -> int:
        return int(self._sync.delete(*keys)) if keys else 0

    def read_blocking(self, key: bytes) -> bytes | None:
        value = self._sync.get(key)
        return None if value is None else bytes(value)

    def info_memory(self) -> dict[str, Any]:
        """Redis's ``INFO memory`` section (benchmarks)."""
        return dict(self._sync.info("memory"))

    # ------------------------------------------------------------------ asyncio (event loop)
    def _aclient(self) -> Any:
        if self._async is None:
            self._async = self._aredis.Redis.from_url(
                self.url, socket_timeout=self.timeout, socket_connect_timeout=self.timeout
            )
        return self._async

    async def aping(self) -> None:
        await self._aclient().ping()

    async def read_many(self, keys: Sequence[bytes]) -> list[bytes | None]:
        values = await self._aclient().mget(keys)
        return [None if v is None else bytes(v) for v in values]

    async def aclose(self) -> None:
        """Close the asyncio client (on its event loop)."""
        if self._async is not None:
            await self._async.aclose()
            self._async = None

    def close(self) -> None:
        self._sync.close()
