"""Sessions that outlive their process: checkpoints to the session store, and look-ups.

With ``--session-store``, a :class:`Checkpointer` runs beside the server:

* **Checkpoints, behind the answer.** A thread of its own wakes every
  ``checkpoint_interval`` s, takes the sessions used since its last pass (the session table
  keeps them in order of use, so this costs what it writes) and writes each one's record
  (:mod:`service.store`), with the session TTL. A fix never waits for the store, nor for a
  session's lock: a session is read without its lock (:func:`read_session`; what an update
  changed meanwhile is read again, or left to the next pass, which that update's use puts it
  in). The thread competes with the fixes only for the interpreter while it encodes, so a
  pass is spread over half the interval in slices of about a millisecond of encoding, with
  the fixes served between two slices; the records are written in pipelined round trips of
  :data:`WRITE_EVERY` (and the pass's last ones).
* **Hand-over when a stream ends.** The stream's vehicles are written at once and, once
  written and unused meanwhile, dropped from this process: their next stream, on whichever
  server, resumes from the store, never from an older copy left in some process's memory.
  On shutdown (:meth:`Checkpointer.drain`) each open stream hands its vehicles over on its
  next fix and then ends with UNAVAILABLE, without answering that fix: the client sends it
  again, to another server, which finds the session as it was after the last answer.
* **Look-up before a new session.** A fix for a vehicle this process does not hold first
  looks the vehicle up in the store, bounded by ``store_timeout``. The record is validated as
  ``ImportSession`` validates a session; a miss, a timeout, a failure or a bad record starts
  the session afresh, as without a store (each counted).
* **Failures never fail a fix.** Store errors are counted, logged when the store goes away
  and when it comes back, and reported on the health service ``mapmatch.v1.SessionStore``
  (NOT_SERVING while the store fails; ``""`` and ``mapmatch.v1.MapMatch`` stay SERVING, as
  fixes are still answered). While the store is away the checkpoint passes keep their place:
  the first pass that succeeds writes every session used since the last one that did.

A process killed outright loses at most what its vehicles did since the last pass, about
``checkpoint_interval`` s of fixes; a vehicle resumes from the older state (it is not started
afresh). A fix whose answer was lost is sent again by the client (:class:`VehicleStream
<service.client.VehicleStream>`); a session answers a resend of its last accepted fix (same
time, same position) with that fix's answer, so no fix is applied twice.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import threading
import time
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass, field, fields
from typing import Any

import grpc
from grpc import aio

from mapmatch.online.codec import StateCaps, from_bytes, to_bytes
from service import convert
from service.errors import SessionExistsError, SessionLimitError
from service.gen import mapmatch_pb2 as pb
from service.maps import MapEntry, MapRegistry
from service.sessions import Session, SessionKey, SessionStore
from service.store import WRITE_TIMEOUT, RedisStore, pack, session_key, unpack

log = logging.getLogger("mapmatch.service")

STORE_HEALTH = "mapmatch.v1.SessionStore"  # health service name of the session store
STATS_PERIOD = 60.0  # s between two log lines of the counters (when they changed)
SPREAD = 0.5  # a checkpoint pass is spread over this share of the checkpoint interval ...
SLICE_SECONDS = 0.001  # ... in slices that each encode for about this long, then write ...
SLICE_MOST = 64  # ... at most this many sessions ...
WRITE_EVERY = 32  # ... and their records are written once this many wait (or the pass ends) ...
MIN_GAP = 0.001  # ... at least this many seconds apart (the fixes have the interpreter between)
READ_TRIES = 3  # a hand-over reads a session in the middle of an update again, this many times


@dataclass
class StoreCounters:
    """Running counts of the session store's work (read them with :meth:`as_dict`)."""

    passes: int = 0  # checkpoint passes that wrote something
    written: int = 0  # session records written
    bytes_written: int = 0
    write_seconds: float = 0.0  # encoding and writing, in the checkpoint thread
    write_failures: int = 0  # records not written because the store failed
    handed_over: int = 0  # sessions written and dropped when their stream ended
    lookups: int = 0  # fixes of vehicles this process did not hold
    restored: int = 0  # ... whose session came from the store
    misses: int = 0  # ... the store had none: started afresh
    timeouts: int = 0  # ... the store did not answer in time: started afresh
    lookup_failures: int = 0  # ... the store failed: started afresh
    bad_records: int = 0  # ... the record did not validate: started afresh
    deleted: int = 0  # records removed by EndSession

    def as_dict(self) -> dict[str, float]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True)
class CheckpointSettings:
    """How often to write, how long records live, how long a look-up may take."""

    interval: float = 1.0
    ttl: float = 600.0
    timeout: float = 0.1
    max_vehicle_id: int = 128


@dataclass
class _Pass:
    """A checkpoint pass under way: the sessions still to write (the next last), the store
    times it covers (used after ``since``, up to ``until``), and when it should be done."""

    todo: list[Session]
    since: float
    until: float
    end: float  # time.monotonic() by which the pass should be written
    next_at: float = 0.0  # time.monotonic() of the next slice
    ok: bool = True  # False once the store failed: the next pass starts from ``since`` again
    wrote: bool = False
    waiting: list[tuple[bytes, bytes]] = field(default_factory=list)  # records not yet written
    spent: float = 0.0  # seconds spent encoding them
    again: set[SessionKey] = field(default_factory=set)  # read in the middle of an update once

    def due(self) -> bool:
        return time.monotonic() >= self.next_at

    def wait(self) -> float:
        return self.next_at - time.monotonic()

    def gap(self, taken: int) -> float:
        """Seconds to the next slice: what is left of the pass's time over the slices left."""
        if not self.todo:
            return 0.0
        slices = math.ceil(len(self.todo) / max(taken, 1))
        return max(MIN_GAP, (self.end - time.monotonic()) / slices)


@dataclass
class _Encoded:
    """Sessions encoded: their records, each with the use time it was read at, and the ones
    an update was changing (not encoded)."""

    records: list[tuple[bytes, bytes]] = field(default_factory=list)
    done: list[tuple[Session, float]] = field(default_factory=list)
    busy: list[Session] = field(default_factory=list)


def read_session(s: Session) -> tuple[bytes, Any, float] | None:
    """A session's state blob, last answer and use time, read without its lock; None when an
    update was under way or began meanwhile (then what was read may be torn)."""
    version = s.version
    if version & 1:
        return None
    try:
        blob, answer, used = to_bytes(s.state), s.answer, s.last_used
    except Exception:  # the update changed the state under the encoder
        if s.version == version:
            raise
        return None
    return (blob, answer, used) if s.version == version else None


class Checkpointer:
    """Checkpoints, hand-overs and look-ups of one server's sessions (see the module).

    Parameters
    ----------
    store
        The Redis clients.
    sessions
        The server's session table.
    maps
        The server's maps (a record is keyed by its map's checksum).
    settings
        Interval, TTL, look-up timeout.
    on_health
        Called with True/False when the store comes back / fails (from any thread).
    """

    def __init__(
        self,
        *,
        store: RedisStore,
        sessions: SessionStore,
        maps: MapRegistry,
        settings: CheckpointSettings,
        on_health: Callable[[bool], None] = lambda ok: None,
    ) -> None:
        self.store = store
        self.sessions = sessions
        self.maps = maps
        self.settings = settings
        self.on_health = on_health
        self.counters = StoreCounters()
        self.healthy: bool | None = None  # unknown until the first operation
        self.draining = False
        self._ttl_ms = max(1, int(settings.ttl * 1000))
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._handover: set[SessionKey] = set()
        self._forget: list[bytes] = []
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._asked: dict[bytes, list[asyncio.Future[bytes | None]]] = {}
        self._tasks: set[asyncio.Task[Any]] = set()
        self._logged: dict[str, float] = {}
        self._logged_at = time.monotonic()

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Start the checkpoint thread (it first probes the store: health and a log line);
        on an event loop, open the look-up connection too."""
        with contextlib.suppress(RuntimeError):  # no running loop
            task = asyncio.get_running_loop().create_task(self.warm())
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="mapmatch-checkpoints", daemon=True)
            self._thread.start()

    def drain(self) -> None:
        """Shutdown has begun: each open stream hands its vehicles over on its next fix."""
        self.draining = True

    def stop(self, timeout: float = 10.0) -> None:
        """A last pass (every session used since the last one, every stream handed over),
        then end the thread."""
        self._stopping = True
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout)
        log.info("session store: %s", _counts_text(self.counters.as_dict()))
        self.store.close()

    # ------------------------------------------------------------------ the fixes' side (event loop)
    def _entry(self, req: pb.FixRequest) -> MapEntry | None:
        """The request's map when its vehicle could have a session (else the fix's own
        checks answer it)."""
        vid = req.vehicle_id
        if not vid or len(vid.encode()) > self.settings.max_vehicle_id:
            return None
        try:
            return self.maps.get(req.map_id)
        except Exception:  # an unknown map: answered by the fix's own path
            return None

    async def before(self, req: pb.FixRequest) -> None:
        """Bring the vehicle's session from the store when this process does not hold it."""
        entry = self._entry(req)
        if entry is not None and self.sessions.live((entry.map_id, req.vehicle_id)) is None:
            await self._restore(entry, req.vehicle_id)

    async def before_batch(self, reqs: Iterable[pb.FixRequest]) -> None:
        """:meth:`before` for a batch's vehicles (their look-ups go in one round trip)."""
        todo: dict[SessionKey, MapEntry] = {}
        for req in reqs:
            entry = self._entry(req)
            if entry is not None and self.sessions.live((entry.map_id, req.vehicle_id)) is None:
                todo[(entry.map_id, req.vehicle_id)] = entry
        if todo:
            await asyncio.gather(*(self._restore(e, vid) for (_, vid), e in todo.items()))

    async def _restore(self, entry: MapEntry, vehicle_id: str) -> None:
        c = self.counters
        c.lookups += 1
        try:
            data = await asyncio.wait_for(
                self._lookup(session_key(entry.checksum, vehicle_id)), self.settings.timeout
            )
        except TimeoutError:
            c.timeouts += 1
            self._failed("a look-up took longer than store_timeout")
            return
        except Exception as exc:
            c.lookup_failures += 1
            self._failed(f"a look-up failed: {type(exc).__name__}: {exc}")
            return
        self._ok()
        self._install(entry, vehicle_id, data)

    def _lookup(self, key: bytes) -> asyncio.Future[bytes | None]:
        """The record of ``key``: look-ups asked for in one turn of the event loop share one
        round trip (after a failover, many vehicles arrive at once)."""
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[bytes | None] = loop.create_future()
        if not self._asked:
            loop.call_soon(self._send_lookups)
        self._asked.setdefault(key, []).append(fut)
        return fut

    def _send_lookups(self) -> None:
        asked, self._asked = self._asked, {}
        task = asyncio.ensure_future(self.store.read_many(list(asked)))
        self._tasks.add(task)

        def done(t: asyncio.Task[list[bytes | None]]) -> None:
            self._tasks.discard(t)
            exc = None if t.cancelled() else t.exception()
            values = t.result() if not t.cancelled() and exc is None else [None] * len(asked)
            for futs, value in zip(asked.values(), values, strict=True):
                for f in futs:
                    if f.done():  # its waiter gave up (timeout)
                        continue
                    if t.cancelled():
                        f.cancel()
                    elif exc is not None:
                        f.set_exception(exc)
                    else:
                        f.set_result(value)

        task.add_done_callback(done)

    async def warm(self) -> None:
        """Open the look-up connection before the first look-up needs it (failures ignored:
        the checkpoint thread reports the store's state)."""
        with contextlib.suppress(Exception):
            await asyncio.wait_for(self.store.aping(), WRITE_TIMEOUT)

    def _install(self, entry: MapEntry, vehicle_id: str, data: bytes | None) -> None:
        if data is None:
            self.counters.misses += 1
            return
        try:
            blob, answer_bytes = unpack(data)
            state = from_bytes(blob, n_edges=entry.graph.n_edges, caps=StateCaps.of(entry.online.config))
            answer = (
                convert.snap_result_from_proto(pb.SnapResult.FromString(answer_bytes))
                if answer_bytes
                else None
            )
        except Exception as exc:  # a record that does not validate: start afresh
            self.counters.bad_records += 1
            log.warning(
                "session store: the record of vehicle %r is not valid (%s): it starts afresh", vehicle_id, exc
            )
            return
        try:
            self.sessions.put(entry.map_id, vehicle_id, state, answer=answer)
        except (SessionExistsError, SessionLimitError):  # made meanwhile, or full: the fix's path decides
            return
        self.counters.restored += 1

    async def serve(
        self,
        context: Any,
        answer: Callable[[pb.FixRequest], pb.SnapResponse],
        submit: Callable[[Callable[[], pb.SnapResponse]], Awaitable[pb.SnapResponse]] | None = None,
        allowed: Callable[[str], bool] | None = None,
    ) -> None:
        """``StreamFixes`` with the store, reading and writing on the call's ``context``: look
        up unknown vehicles, hand the stream's vehicles over when it ends (or, while
        draining, before its next fix). A fix for a vehicle the caller may not act for
        (``allowed`` false) is only answered: its vehicle is neither looked up nor handed over."""
        seen: set[tuple[str, str]] = set()
        read, write, eof = context.read, context.write, aio.EOF
        try:
            while (req := await read()) is not eof:
                if not isinstance(req, pb.FixRequest):  # bytes that did not decode: an error answer
                    await write(answer(req))
                    continue
                if self.draining:
                    await asyncio.to_thread(self._hand_over, self._keys(seen))
                    seen.clear()
                    await context.abort(
                        grpc.StatusCode.UNAVAILABLE,
                        "the server is shutting down: send this fix again (its session is in the store)",
                    )
                if allowed is None or allowed(req.vehicle_id):
                    seen.add((req.map_id, req.vehicle_id))
                    await self.before(req)
                await write(answer(req) if submit is None else await submit(functools.partial(answer, req)))
        finally:
            if seen:
                self._queue_handover(self._keys(seen))

    def _keys(self, seen: Iterable[tuple[str, str]]) -> list[SessionKey]:
        out = []
        for map_id, vid in seen:
            try:
                out.append((self.maps.get(map_id).map_id, vid))
            except Exception:  # unloaded meanwhile, or never valid
                continue
        return out

    def forget(self, map_id: str, vehicle_id: str) -> None:
        """EndSession: remove the vehicle's record too (on the checkpoint thread)."""
        try:
            entry = self.maps.get(map_id)
        except Exception:
            return
        with self._lock:
            self._forget.append(session_key(entry.checksum, vehicle_id))
        self._wake.set()

    def _queue_handover(self, keys: list[SessionKey]) -> None:
        with self._lock:
            self._handover.update(keys)
        self._wake.set()

    # ------------------------------------------------------------------ the checkpoint thread
    def _run(self) -> None:
        interval = self.settings.interval
        self._probe()
        since = self.sessions.now()
        next_at = time.monotonic() + interval
        current: _Pass | None = None
        while True:
            wait = current.wait() if current is not None else next_at - time.monotonic()
            self._wake.wait(max(0.0, wait))
            self._wake.clear()
            stopping = self._stopping
            with self._lock:
                handover, self._handover = self._handover, set()
                forget, self._forget = self._forget, []
            if handover:
                self._hand_over(list(handover))
            if forget:
                self._delete(forget)
            if current is None and (stopping or time.monotonic() >= next_at):
                current, since = self._begin(since, spread=0.0 if stopping else SPREAD * interval)
                next_at = time.monotonic() + interval
            while current is not None and (stopping or current.due()):
                if self._slice(current):
                    since = current.until if current.ok else current.since
                    current = None
                    self._log_counts()
            if stopping:  # the last pass: every session used since
                last, since = self._begin(since, spread=0.0)
                while last is not None and not self._slice(last):
                    pass
                return

    def _begin(self, since: float, *, spread: float) -> tuple[_Pass | None, float]:
        """A pass over the sessions used after ``since`` (None when none was), spread over
        ``spread`` s; returns it and where the next pass starts if it has nothing to write."""
        now = self.sessions.now()
        used = self.sessions.used_since(since)
        if not used:
            if self.healthy is False:
                self._probe()
            return None, now
        return _Pass(todo=used[::-1], since=since, until=now, end=time.monotonic() + spread), now

    def _slice(self, p: _Pass) -> bool:
        """Write the next slice of a pass (the sessions encoded in about :data:`SLICE_SECONDS`);
        returns whether the pass is over (all written, or the store failed)."""
        t0 = time.perf_counter()
        checksums = self._checksums()
        out = _Encoded()
        taken = 0
        while p.todo and taken < SLICE_MOST and time.perf_counter() - t0 < SLICE_SECONDS:
            self._encode_one(p.todo.pop(), checksums, out)
            taken += 1
        for s in out.busy:  # read again at the end of the pass, once (then its update's pass has it)
            if s.key not in p.again:
                p.again.add(s.key)
                p.todo.insert(0, s)
        p.waiting += out.records
        p.spent += time.perf_counter() - t0
        if p.waiting and (len(p.waiting) >= WRITE_EVERY or not p.todo):
            if self._send(p.waiting, p.spent):
                self.counters.passes += int(not p.wrote)
                p.wrote = True
            else:
                self.counters.write_failures += len(p.todo)  # nor will the rest be written
                p.ok = False
                p.todo.clear()
            p.waiting, p.spent = [], 0.0
        p.next_at = time.monotonic() + p.gap(taken)
        return not p.todo

    def _hand_over(self, keys: list[SessionKey]) -> None:
        """Write these sessions now and drop them here once written (if unused meanwhile)."""
        live = [s for s in (self.sessions.live(k) for k in keys) if s is not None]
        written = self._write(live) if live else None
        for s, used in written or ():
            if self.sessions.drop_unused(s, used):
                self.counters.handed_over += 1

    def _write(self, sessions: list[Session]) -> list[tuple[Session, float]] | None:
        """Encode and write ``sessions`` now (a session in the middle of an update is read
        again, up to :data:`READ_TRIES` times); returns each written one with the use time it
        was encoded at, or None when the store failed."""
        t0 = time.perf_counter()
        out = self._encode(sessions)
        for _ in range(READ_TRIES - 1):
            if not out.busy:
                break
            time.sleep(0.0005)  # let the update end
            more = self._encode(out.busy)
            out = _Encoded(out.records + more.records, out.done + more.done, more.busy)
        if out.records:
            if not self._send(out.records, time.perf_counter() - t0):
                return None
            self.counters.passes += 1
        return out.done

    def _encode(self, sessions: list[Session]) -> _Encoded:
        """The records of ``sessions``, read without their locks (see :meth:`_encode_one`)."""
        checksums = self._checksums()
        out = _Encoded()
        for s in sessions:
            self._encode_one(s, checksums, out)
        return out

    def _checksums(self) -> dict[str, str]:
        return {e.map_id: e.checksum for e in self.maps.entries()}

    def _encode_one(self, s: Session, checksums: dict[str, str], out: _Encoded) -> None:
        """Add the session's record to ``out``, or the session to ``out.busy`` when an update
        was under way. A session no longer in the table (handed over, ended, expired) is not
        written: its vehicle's record may be another server's by now."""
        checksum = checksums.get(s.key[0])
        if checksum is None or self.sessions.live(s.key) is not s:  # unloaded map; handed over
            return
        got = read_session(s)
        if got is None:
            out.busy.append(s)
            return
        blob, answer, used = got
        last = convert.snap_result_to_proto(answer).SerializeToString() if answer is not None else b""
        out.records.append((session_key(checksum, s.key[1]), pack(blob, last)))
        out.done.append((s, used))

    def _send(self, records: list[tuple[bytes, bytes]], spent: float) -> bool:
        """Write records (``spent``: the seconds their encoding took); False when the store
        failed (counted and reported)."""
        t0 = time.perf_counter()
        try:
            sent = self.store.write(records, ttl_ms=self._ttl_ms)
        except Exception as exc:
            self.counters.write_failures += len(records)
            self._failed(f"a checkpoint failed: {type(exc).__name__}: {exc}")
            return False
        c = self.counters
        c.written += len(records)
        c.bytes_written += sent
        c.write_seconds += spent + time.perf_counter() - t0
        self._ok()
        return True

    def _delete(self, keys: list[bytes]) -> None:
        try:
            self.counters.deleted += self.store.delete(keys)
        except Exception as exc:
            self._failed(f"a delete failed: {type(exc).__name__}: {exc}")

    def _probe(self) -> None:
        try:
            self.store.ping()
        except Exception as exc:
            self._failed(f"{type(exc).__name__}: {exc}")
        else:
            self._ok()

    # ------------------------------------------------------------------ health and logs
    def _failed(self, why: str) -> None:
        with self._lock:
            was, self.healthy = self.healthy, False
        if was is not False:
            log.warning(
                "session store unavailable (%s): fixes are answered as before, sessions stay in "
                "their process until it is back",
                why,
            )
            self.on_health(False)

    def _ok(self) -> None:
        with self._lock:
            was, self.healthy = self.healthy, True
        if was is not True:
            if was is False:
                log.info("session store available again (%s)", _counts_text(self.counters.as_dict()))
            else:
                log.info("session store reachable; checkpoints every %g s", self.settings.interval)
            self.on_health(True)

    def _log_counts(self) -> None:
        now = time.monotonic()
        if now - self._logged_at < STATS_PERIOD:
            return
        counts = self.counters.as_dict()
        if counts != self._logged:
            log.info("session store: %s", _counts_text(counts))
            self._logged = counts
        self._logged_at = now


def _counts_text(counts: dict[str, float]) -> str:
    return ", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in counts.items())
