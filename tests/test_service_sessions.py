"""The session store on its own: TTL with an injected clock, limits, per-vehicle locking."""

from __future__ import annotations

import threading
import time

import pytest

from service.sessions import (
    SessionExistsError,
    SessionLimitError,
    SessionNotFoundError,
    SessionStore,
)


class State:
    def __init__(self, data: bytes = b"") -> None:
        self.data = data
        self.log: list[int] = []

    def to_bytes(self) -> bytes:
        return self.data


def test_ttl_and_limit_with_a_fake_clock():
    now = [0.0]
    store = SessionStore(max_sessions=2, ttl=10.0, clock=lambda: now[0])
    with store.use("m", "a", State):
        pass
    now[0] = 5.0
    with store.use("m", "b", State):
        pass
    with pytest.raises(SessionLimitError), store.use("m", "c", State):
        pass
    now[0] = 9.0
    with store.use("m", "a", State):  # touching renews "a"
        pass
    now[0] = 15.5  # "b" (last used at 5) expired, "a" (9) alive
    with store.use("m", "c", State):
        pass
    assert store.count() == 2 and store.count("m") == 2 and store.expired_total == 1
    with pytest.raises(SessionNotFoundError):
        store.export("m", "b")
    now[0] = 100.0
    assert store.sweep() == 2 and len(store) == 0


def test_export_put_and_drop():
    store = SessionStore(max_sessions=10, ttl=60.0)
    store.put("m", "v", State(b"xyz"))
    with pytest.raises(SessionExistsError):
        store.put("m", "v", State(b"other"))
    store.put("m", "v", State(b"new"), replace=True)
    assert store.export("m", "v") == b"new"
    assert store.export("m", "v", remove=True) == b"new"
    assert not store.drop("m", "v")
    store.put("m", "1", State())
    store.put("n", "1", State())
    assert store.drop_map("m") == 1 and store.count() == 1


def test_one_vehicle_is_processed_in_order_while_others_run():
    store = SessionStore(max_sessions=100, ttl=60.0)
    inside = {"v": 0, "max": 0}
    lock = threading.Lock()

    def work(vid: str, k: int) -> None:
        with store.use("m", vid, State) as s:
            with lock:
                inside["v"] += 1 if vid == "same" else 0
                inside["max"] = max(inside["max"], inside["v"])
            time.sleep(0.002)
            s.state.log.append(k)
            with lock:
                inside["v"] -= 1 if vid == "same" else 0

    threads = [threading.Thread(target=work, args=("same" if k % 2 else f"o{k}", k)) for k in range(40)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert inside["max"] == 1  # never two updates of one vehicle at once
    with store.use("m", "same", State) as s:
        assert sorted(s.state.log) == list(range(1, 40, 2))
    assert store.count() == 21


def test_the_fast_path_finds_only_stored_live_sessions_and_touch_renews_without_restoring():
    now = [0.0]
    store = SessionStore(max_sessions=10, ttl=10.0, clock=lambda: now[0])
    assert store.live(("m", "a")) is None  # nothing stored: the caller goes through use()
    with store.use("m", "a", State) as made:
        pass
    s = store.live(("m", "a"))
    assert s is made
    now[0] = 8.0
    store.touch(s)  # an accepted fix at 8 s keeps "a" alive until 18 s
    now[0] = 17.0
    assert store.live(("m", "a")) is s and store.count() == 1
    now[0] = 27.5  # idle for 10.5 s: expired, the fast path does not return it
    assert store.live(("m", "a")) is None
    now[0] = 28.0
    with store.use("m", "b", State):
        pass
    b = store.live(("m", "b"))
    assert b is not None and store.drop("m", "b")
    store.touch(b)  # ended meanwhile (EndSession): a touch does not bring it back
    assert store.live(("m", "b")) is None and store.count() == 0
