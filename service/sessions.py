"""Per-vehicle matcher sessions keyed by ``(map id, vehicle id)``.

Sessions hold only the online matcher's small state. They expire after ``ttl`` seconds
without a fix, their number is capped (memory stays bounded), and each has its own lock so
one vehicle's fixes are processed one at a time, in order, while other vehicles proceed.
The store is thread-safe. State can be exported as bytes and imported on another server;
:meth:`SessionStore.used_since` lists the sessions a checkpoint pass writes to the session
store (:mod:`service.store_checkpoints`).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from service.errors import SessionExistsError, SessionLimitError, SessionNotFoundError

__all__ = ["Session", "SessionExistsError", "SessionLimitError", "SessionNotFoundError", "SessionStore"]

SessionKey = tuple[str, str]


@dataclass(eq=False, slots=True)
class Session:
    """One vehicle's matcher state; hold ``lock`` while using ``state``.

    ``version`` counts the updates begun and ended on ``state`` (odd while one is under way):
    a checkpoint reads the state without the lock and keeps what it read only when
    ``version`` was even and did not change meanwhile.
    """

    key: SessionKey
    state: Any
    last_used: float
    lock: threading.Lock = field(default_factory=threading.Lock)
    waiting: int = 0  # users of a provisional session (not yet stored)
    answer: Any = None  # the last accepted fix's result: a resend of that fix gets it again
    version: int = 0  # updates begun plus updates ended (odd: an update is under way)


class _Use:
    """The context manager of :meth:`SessionStore.use` (a plain class: it runs once per fix)."""

    __slots__ = ("factory", "key", "session", "store")

    def __init__(self, store: SessionStore, key: SessionKey, factory: Callable[[], Any]) -> None:
        self.store = store
        self.key = key
        self.factory = factory
        self.session: Session | None = None

    def __enter__(self) -> Session:
        s = self.session = self.store._enter(self.key, self.factory)
        try:
            s.lock.acquire()
        except BaseException:
            self.store._leave(s, False)
            raise
        return s

    def __exit__(self, kind: Any, exc: Any, tb: Any) -> None:
        s = self.session
        assert s is not None
        s.lock.release()
        self.store._leave(s, kind is None)


class SessionStore:
    """Bounded, expiring, thread-safe store of sessions.

    Parameters
    ----------
    max_sessions
        Cap on live sessions; creating one more raises :class:`SessionLimitError`.
    ttl
        Seconds a session lives without being used.
    clock
        Monotonic clock in seconds (injectable for tests).
    """

    def __init__(self, *, max_sessions: int, ttl: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.max_sessions = max_sessions
        self.ttl = ttl
        self._clock = clock
        self._lock = threading.Lock()
        # least recently used first: expiry pops from the front
        self._sessions: OrderedDict[SessionKey, Session] = OrderedDict()
        # new sessions whose first fix is being matched: stored only once one is accepted
        self._pending: dict[SessionKey, Session] = {}
        self.expired_total = 0

    # ------------------------------------------------------------------ internal
    def _expire_locked(self, now: float) -> int:
        n = 0
        limit = now - self.ttl
        while self._sessions:
            key, s = next(iter(self._sessions.items()))
            if s.last_used > limit:
                break
            del self._sessions[key]
            n += 1
        self.expired_total += n
        return n

    def _get_locked(self, key: SessionKey, now: float) -> Session | None:
        s = self._sessions.get(key)
        if s is None:
            return None
        if s.last_used <= now - self.ttl:
            del self._sessions[key]
            self.expired_total += 1
            return None
        return s

    # ------------------------------------------------------------------ API
    def use(self, map_id: str, vehicle_id: str, factory: Callable[[], Any]) -> _Use:
        """The vehicle's session (a new one from ``factory()`` when absent), locked for the block.

        Only a block that ends without an exception counts as use: it refreshes the session's
        idle timer, and a new session is stored only then. A rejected fix (an exception out of
        the block) neither creates a session nor keeps one alive.

        Raises
        ------
        SessionLimitError
            When a new session is needed and the store is full of live sessions.
        """
        return _Use(self, (map_id, vehicle_id), factory)

    def live(self, key: SessionKey) -> Session | None:
        """The stored, unexpired session of ``key``, or None (then use :meth:`use`). A fast
        path for a known vehicle: one dict read, no lock (the dict is only changed under the
        store's lock, and a read of it is atomic). Lock the session before using its state and
        :meth:`touch` it once the fix is accepted."""
        s = self._sessions.get(key)
        if s is None or s.last_used <= self._clock() - self.ttl:
            return None
        return s

    def touch(self, s: Session) -> None:
        """Count an accepted fix on a session from :meth:`live`: refresh its idle timer (it
        is not stored again if it was dropped meanwhile)."""
        key = s.key
        with self._lock:
            if self._sessions.get(key) is s:
                s.last_used = self._clock()
                self._sessions.move_to_end(key)

    def _enter(self, key: SessionKey, factory: Callable[[], Any]) -> Session:
        now = self._clock()
        with self._lock:
            s = self._get_locked(key, now)
            if s is None:  # a provisional session, shared by concurrent first fixes
                s = self._pending.get(key)
                if s is None:
                    self._full_check_locked(now)
                    s = self._pending[key] = Session(key=key, state=factory(), last_used=now)
                s.waiting += 1
        return s

    def _leave(self, s: Session, accepted: bool) -> None:
        key = s.key
        with self._lock:
            if self._pending.get(key) is s:
                s.waiting -= 1
                if accepted or s.waiting == 0:
                    del self._pending[key]
                if accepted:
                    if key not in self._sessions:
                        self._full_check_locked(self._clock())
                    self._sessions[key] = s
            if accepted and self._sessions.get(key) is s:
                s.last_used = self._clock()
                self._sessions.move_to_end(key)

    def _full_check_locked(self, now: float) -> None:
        self._expire_locked(now)
        if len(self._sessions) >= self.max_sessions:
            raise SessionLimitError(
                f"session limit reached ({self.max_sessions} vehicles); retry later or end sessions"
            )

    def drop(self, map_id: str, vehicle_id: str) -> bool:
        """End a session; returns whether it existed (and was live)."""
        now = self._clock()
        with self._lock:
            s = self._get_locked((map_id, vehicle_id), now)
            if s is None:
                return False
            del self._sessions[s.key]
            return True

    def drop_map(self, map_id: str) -> int:
        """End every session on a map; returns how many."""
        with self._lock:
            keys = [k for k in self._sessions if k[0] == map_id]
            for k in keys:
                del self._sessions[k]
            return len(keys)

    def export(self, map_id: str, vehicle_id: str, *, remove: bool = False) -> bytes:
        """The session's state as bytes (``state.to_bytes()``); optionally end it here."""
        now = self._clock()
        with self._lock:
            s = self._get_locked((map_id, vehicle_id), now)
            if s is None:
                raise SessionNotFoundError(
                    f"vehicle_id: no live session for vehicle {vehicle_id!r} on map {map_id!r}"
                )
            if remove:
                del self._sessions[s.key]
        with s.lock:
            return bytes(s.state.to_bytes())

    def put(
        self, map_id: str, vehicle_id: str, state: Any, *, replace: bool = False, answer: Any = None
    ) -> None:
        """Install a session (e.g. an imported one), with its last fix's ``answer`` if known."""
        key = (map_id, vehicle_id)
        now = self._clock()
        with self._lock:
            old = self._get_locked(key, now)
            if old is not None and not replace:
                raise SessionExistsError(f"vehicle {vehicle_id!r} already has a session on map {map_id!r}")
            if old is None:
                self._full_check_locked(now)
            self._sessions[key] = Session(key=key, state=state, last_used=now, answer=answer)
            self._sessions.move_to_end(key)

    def now(self) -> float:
        """The store's clock (the time base of ``Session.last_used``)."""
        return self._clock()

    def used_since(self, since: float) -> list[Session]:
        """The stored sessions used after ``since`` (store clock), latest first: O(their
        number), since the store keeps its sessions in order of use."""
        out = []
        with self._lock:
            for s in reversed(self._sessions.values()):
                if s.last_used <= since:
                    break
                out.append(s)
        return out

    def drop_unused(self, s: Session, last_used: float) -> bool:
        """End the session ``s`` unless it was used after ``last_used`` (or replaced);
        returns whether it was ended."""
        with self._lock:
            if self._sessions.get(s.key) is not s or s.last_used != last_used:
                return False
            del self._sessions[s.key]
            return True

    def sweep(self) -> int:
        """Remove expired sessions now; returns how many."""
        with self._lock:
            return self._expire_locked(self._clock())

    def count(self, map_id: str | None = None) -> int:
        """Live sessions (on one map, or all)."""
        with self._lock:
            self._expire_locked(self._clock())
            if map_id is None:
                return len(self._sessions)
            return sum(1 for k in self._sessions if k[0] == map_id)

    def __len__(self) -> int:
        return self.count()
