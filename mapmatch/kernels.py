"""The compiled (numba) kernels: which a job needs, whether they are compiled yet, and compiling them.

Kernels compile on first use and are cached on disk (``__pycache__`` next to the source, or
``NUMBA_CACHE_DIR``), so only the first run on a machine pays for it. Commands call
:func:`announce` before work that needs a group, which prints one line when the group is not
cached yet. ``simulate`` needs the fusion filter, ``match`` (and the service's ``MatchTrack``)
the batch matcher, the online matcher (``replay``, ``serve``, ``demo``) its placement kernel.

``python -m mapmatch.kernels [GROUP...]`` compiles groups ahead of time (a container build
does it, so a container's first start is warm).

Kernels can also run *interpreted*: as the plain Python functions they are compiled from
(numba's ``NUMBA_DISABLE_JIT``), the same code and so the same answers, slower per fix but
with nothing to compile. The mode is chosen once per process, before the first kernel is
defined (:func:`choose_mode`, :func:`set_mode`); worker processes inherit it through the
environment. ``auto`` runs a job interpreted when a group it needs is not compiled yet and
the job is small enough that interpreting it costs less than compiling
(:data:`INTERPRETED_SECONDS_PER_ITEM`, :data:`COMPILE_SECONDS`).

A long-running process (``serve``) runs a cold group *tiered* (:class:`TieredGroup`):
interpreted at once, while a child process compiles it, then compiled from the switch on.

A kernel that runs once per job on an input of a size the job chose (a map's nodes, a route's
metres) goes through :func:`graph.jit.for_size`: on a small input it runs as plain Python (the same code,
so the same results), which takes milliseconds where compiling takes seconds.
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NamedTuple, TextIO

GROUPS: dict[str, tuple[str, ...]] = {
    "simulator": ("mapmatch.sim.kalman:_ekf",),
    "batch": (
        "mapmatch.batch.lattice",
        "mapmatch.viterbi",
        "mapmatch.batch.split",
        "mapmatch.batch.step",
        "mapmatch.batch.leave_out",
        "mapmatch.batch.viterbi",
        "mapmatch.batch.route",
        "mapmatch.batch.packed",
        "mapmatch.batch.run",
        "mapmatch.batch.context",
        "mapmatch.routing",
        "mapmatch.route_table",
        "mapmatch.gridindex",
        "mapmatch.model",
    ),
    "online": (
        "mapmatch.online.geometry",
        "mapmatch.online.along",
        "mapmatch.online.placement",
        "graph.index:project_point_compiled",
        "mapmatch.model:emission_logp_one",
        "mapmatch.model:transition_one_compiled",
    ),
}
"""Kernel groups: the compiled functions a kind of job uses, as modules (all their kernels) or
``module:kernel`` (that kernel, with what it calls: the filter's map-aided update compiles only
for a closed loop). Kernels called through :func:`graph.jit.for_size`, which compile only for large
inputs, are in none."""

COMPILE_SECONDS: dict[str, float] = {"simulator": 5.0, "batch": 95.0, "online": 10.0}
"""About how long (CPU seconds) a group takes to compile on the 2-core development machine
(``bench/bench_compile.py``, ``bench/bench_first_minute.py``)."""

INTERPRETED_SECONDS_PER_ITEM: dict[str, float] = {"simulator": 0.0025, "batch": 0.001, "online": 0.001}
"""About how long (CPU seconds) a group's kernels take interpreted per item of work (a second
of a simulated drive, a point of a track, a fix) on the 2-core development machine: with
:data:`COMPILE_SECONDS`, ``auto`` runs interpreted below about 2,000 s of driving, 95,000
points or 10,000 fixes (docs/design/dependencies.md)."""

ENTRY_KERNELS: dict[str, str] = {
    "simulator": "mapmatch/sim/kalman.py:_ekf",
    "batch": "mapmatch/batch/run.py:run_track_in",
    "online": "mapmatch/online/placement.py:_place_all",
}
"""Per group, a kernel (source file under the package root, function) every job of the group
compiles: its cache on disk tells whether the group was compiled, read before any kernel is
defined (:func:`compiled_on_disk`)."""

MODES = ("auto", "compiled", "interpreted")
"""How kernels run: ``compiled`` (numba, compiled on first use and cached), ``interpreted``
(plain Python, nothing compiled) or ``auto`` (interpreted for a small job whose kernels are
not compiled yet, else compiled)."""
MODE_ENV = "MAPMATCH_KERNELS"
"""The environment variable of the mode (the ``--kernels`` option wins)."""
BELOW_ENV = "MAPMATCH_INTERPRETED_BELOW"
"""The environment variable of ``--interpreted-below``."""

_announced: set[str] = set()


def compiled_on_disk(group: str) -> bool:
    """Whether the group's kernels are compiled and cached for the current sources, read from
    numba's cache index of its entry kernel (:data:`ENTRY_KERNELS`) without importing any kernel
    module, so before :func:`set_mode`. Cached kernels of changed sources are cleared first, as
    the first kernel of a process would (:func:`graph.kernel_cache.refresh_installed`)."""
    from graph.kernel_cache import has_cached, refresh_installed

    refresh_installed()
    path, _, kernel = ENTRY_KERNELS[group].partition(":")
    return has_cached(Path(__file__).resolve().parents[1] / path, kernel)


def is_interpreted() -> bool:
    """Whether this process runs kernels interpreted (``NUMBA_DISABLE_JIT`` set), read from the
    environment without importing numba."""
    return os.environ.get("NUMBA_DISABLE_JIT", "0").strip() not in ("", "0")


def kernels_defined() -> bool:
    """Whether a kernel was defined in this process already (the mode is then fixed)."""
    jit = sys.modules.get("graph.jit")
    return bool(getattr(jit, "_refreshed", False))


def set_mode(*, interpreted: bool) -> bool:
    """Run kernels interpreted or compiled in this process and the processes it starts (through
    ``NUMBA_DISABLE_JIT``). Only before the first kernel is defined: returns whether the mode
    is now the one asked for."""
    if kernels_defined():
        return is_interpreted() == interpreted
    os.environ["NUMBA_DISABLE_JIT"] = "1" if interpreted else "0"
    numba = sys.modules.get("numba")
    if numba is not None:
        numba.config.DISABLE_JIT = int(interpreted)
    return True


class ModeChoice(NamedTuple):
    """What :func:`choose_mode` decided: interpreted or not, and the one line saying why
    (``None``: nothing to say)."""

    interpreted: bool
    notice: str | None = None


def _estimates(groups: tuple[str, ...], cold: list[str], items: int) -> tuple[float, float]:
    """CPU seconds of the job's kernels (interpreted, compiling the cold groups)."""
    interp = items * sum(INTERPRETED_SECONDS_PER_ITEM[g] for g in groups)
    return interp, sum(COMPILE_SECONDS[g] for g in cold)


def choose_mode(
    mode: str, groups: tuple[str, ...], items: int | None, *, below: int | None = None, noun: str = "items"
) -> ModeChoice:
    """Decide how a job that needs kernel ``groups`` runs, in ``mode`` (:data:`MODES`).

    ``items`` is the job's size (``noun``: fixes or points; ``None``: unknown). ``auto`` runs the job
    interpreted when some group is not compiled yet (:func:`compiled_on_disk`) and the job is
    small: fewer items than ``below`` when given, else when interpreting its items is estimated
    to cost less CPU than compiling those groups. Speed only: both modes give the same answers.
    """
    if mode not in MODES:
        raise ValueError(f"kernel mode must be one of {', '.join(MODES)}, not {mode!r}")
    if mode != "auto":
        return ModeChoice(mode == "interpreted")
    if is_interpreted():  # the environment asks for it (NUMBA_DISABLE_JIT)
        return ModeChoice(True)
    if not groups:
        return ModeChoice(False)
    cold = [g for g in groups if not compiled_on_disk(g)]
    if not cold or items is None:
        return ModeChoice(False)
    interp, compile_s = _estimates(groups, cold, items)
    small = items < below if below is not None else interp < compile_s
    if not small:
        return ModeChoice(False)
    names = ", ".join(cold)
    return ModeChoice(
        True,
        f"kernels ({names}) not compiled yet: running interpreted for {items:,} {noun} (about "
        f"{interp:.0f} s, where compiling takes about {compile_s:.0f} s once; `python -m "
        f"mapmatch.kernels` compiles them)",
    )


def _kernel(entry: str) -> Any:
    name, _, kernel = entry.partition(":")
    return getattr(importlib.import_module(name), kernel)


def dispatchers(group: str) -> list[Any]:
    """The group's numba dispatchers (the jitted functions in its modules)."""
    from numba.core.registry import CPUDispatcher

    out = []
    for entry in GROUPS[group]:
        name, _, kernel = entry.partition(":")
        mod = importlib.import_module(name)
        if kernel:
            out.append(getattr(mod, kernel))
        else:
            out += [v for v in vars(mod).values() if isinstance(v, CPUDispatcher) and v.__module__ == name]
    return out


CACHE_PROBES: dict[str, tuple[str, ...]] = {
    "batch": ("mapmatch.batch.run:run_track_in",),
    "online": ("mapmatch.online.placement:_place_all",),
}
"""Per group, the entry kernels whose cache tells it was compiled (default: every kernel). The
batch group's other entries (``run``, for tests), its ``inline="always"`` helpers and the
online group's kernels called only from other kernels are compiled into their callers and
never get a cache of their own."""


def is_cached(group: str) -> bool:
    """Whether the group's kernels have an on-disk cache index valid for their source (compiled
    before). With kernels run interpreted, every group is ready: nothing compiles."""
    if is_interpreted():
        return True
    probes = CACHE_PROBES.get(group)
    kernels = dispatchers(group) if probes is None else [_kernel(e) for e in probes]
    for d in kernels:
        if getattr(d, "targetoptions", {}).get("inline") == "always":
            continue  # compiled only into its callers: never cached on its own
        try:
            cache_file = d._cache._cache_file  # numba's cache locator
            index = cache_file._index_path
        except AttributeError:
            return True  # unknown numba internals: do not claim anything
        if not os.path.exists(index):
            return False
        try:
            if not cache_file._load_index():  # stale: written for another source or numba version
                return False
        except Exception:
            return True
    return True


def announce(group: str, *, stream: TextIO | None = None) -> bool:
    """Print "preparing compiled kernels, once, about N s" when the group is not compiled yet.

    Returns whether it was not cached (a compile follows). Printed once per group and process.
    """
    if group in _announced:
        return False
    _announced.add(group)
    if is_cached(group):
        return False
    out = stream or sys.stderr
    about = COMPILE_SECONDS[group]
    print(f"preparing compiled kernels ({group}), once, about {about:.0f} s", file=out, flush=True)
    threading.Thread(target=_heartbeat, args=(group, out), name=f"kernels-{group}", daemon=True).start()
    return True


HEARTBEAT_SECONDS = 15.0
"""How often a compile that :func:`announce` announced says it is still going."""


def _heartbeat(group: str, out: TextIO) -> None:
    """Every :data:`HEARTBEAT_SECONDS`, a line saying the group is still compiling (a busy
    machine can take several times the announced time), and one when its cache is written;
    quiet after ten times the announced time."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < 10 * COMPILE_SECONDS[group]:
        time.sleep(HEARTBEAT_SECONDS)
        try:
            done = is_cached(group)
            what = "ready after" if done else "still preparing, so far"
            print(f"compiled kernels ({group}): {what} {time.monotonic() - t0:.0f} s", file=out, flush=True)
        except Exception:  # the process is ending (stream closed, modules going): say nothing more
            return
        if done:
            return


BACKGROUND_WAIT_SECONDS = 300.0
"""How long :func:`compiling_in_background` waits for its child before compiling in process."""


class BackgroundCompile:
    """A group's kernels compiling in a child process (see :func:`compiling_in_background`)."""

    def __init__(self, child: subprocess.Popen[bytes] | None) -> None:
        self.child = child

    def running(self) -> bool:
        """Whether the child is still compiling."""
        return self.child is not None and self.child.poll() is None

    def wait(self) -> bool:
        """Wait for the child; whether it compiled and saved the group (False: no child ran,
        it failed, or it took longer than :data:`BACKGROUND_WAIT_SECONDS` and was stopped)."""
        if self.child is None:
            return False
        try:
            return self.child.wait(timeout=BACKGROUND_WAIT_SECONDS) == 0
        except subprocess.TimeoutExpired:
            self.stop()
            return False

    def stop(self) -> None:
        """Stop the child if it is still running."""
        if self.running():
            assert self.child is not None
            self.child.kill()
            self.child.wait()


@contextmanager
def compiling_in_background(group: str) -> Iterator[BackgroundCompile]:
    """Compile a group's kernels into the on-disk cache in a child process while this one does
    other work (on the machine's second core). Call ``wait()`` on what it yields before the
    group's first use: this process then loads the kernels from the cache.

    Nothing starts when the group is cached already, or when kernels run interpreted. Should
    the child fail, take longer than :data:`BACKGROUND_WAIT_SECONDS` or not save its kernels
    (an unwritable cache), this process compiles them on first use as it would without a child:
    the results are the same. The child is stopped when the block is left.
    """
    child = _compile_child(group) if not is_interpreted() and not is_cached(group) else None
    background = BackgroundCompile(child)
    try:
        yield background
    finally:
        background.stop()


def _compile_child(group: str) -> subprocess.Popen[bytes]:
    """A child process compiling the group's kernels into numba's on-disk cache
    (``python -m mapmatch.kernels GROUP``, this package first on its path)."""
    package_root = str(Path(__file__).resolve().parents[1])  # the child imports this mapmatch
    path = os.pathsep.join(filter(None, [package_root, os.environ.get("PYTHONPATH")]))
    return subprocess.Popen(
        [sys.executable, "-m", "mapmatch.kernels", group],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=dict(os.environ, PYTHONPATH=path, NUMBA_DISABLE_JIT="0"),
    )


def tiered_wanted(group: str) -> bool:
    """Whether a long-running process (``serve``) should run ``group`` tiered
    (:class:`TieredGroup`): kernels run compiled in this process, the mode is ``auto``
    (``MAPMATCH_KERNELS``, which ``mapmatch`` sets from ``--kernels`` for the command it runs;
    unset: ``compiled``, so a server started in process compiles as it always did), and the
    group is not compiled yet (:func:`compiled_on_disk`)."""
    mode = os.environ.get(MODE_ENV, "").strip() or "compiled"
    return mode == "auto" and not is_interpreted() and not compiled_on_disk(group)


class TierReport(NamedTuple):
    """What a :class:`TieredGroup` did: seconds from its start to the switch to compiled,
    seconds loading the compiled kernels in this process, and whether a child compiled them
    (False: it failed or took too long, and this process compiled them)."""

    seconds: float
    load_seconds: float
    child_compiled: bool


class TieredGroup:
    """A group's kernels answering interpreted at once, then compiled without a restart.

    :meth:`start` makes the group's kernels, called from Python, run their interpreted twins
    (:func:`graph.jit.tier`: the same answers as compiled), starts a child process compiling
    them into numba's on-disk cache (``python -m mapmatch.kernels GROUP``), and a thread that
    waits for it, loads the compiled kernels in this process (a tiny job run compiled in that
    thread: :func:`graph.jit.compiled_calls`; other threads keep answering meanwhile), then
    switches every kernel to compiled (:func:`graph.jit.untier`) and calls ``on_switch``
    (``on_failed`` if they cannot be compiled: they stay interpreted).
    Should the child fail, not save them (an unwritable cache) or take longer than
    :data:`BACKGROUND_WAIT_SECONDS`, that thread compiles them in this process instead. Work
    in flight (sessions, streams) carries on across the switch: only which code computes the
    next answer changes, not the answer.
    """

    def __init__(
        self,
        group: str,
        *,
        on_switch: Callable[[TierReport], None] | None = None,
        on_failed: Callable[[Exception], None] | None = None,
    ) -> None:
        self.group = group
        self.on_switch = on_switch
        self.on_failed = on_failed
        self.compiled = threading.Event()
        self.report: TierReport | None = None
        self._background = BackgroundCompile(None)
        self._tiered: list[Any] = []
        self._thread: threading.Thread | None = None
        self._stopped = threading.Event()

    def start(self) -> None:
        """Tier the group's kernels and start compiling them (see the class)."""
        from graph.jit import tier

        self._tiered = tier(dispatchers(self.group))
        self._background = BackgroundCompile(_compile_child(self.group))
        self._thread = threading.Thread(target=self._run, name=f"kernels-{self.group}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from graph.jit import compiled_calls, untier

        t0 = time.monotonic()
        ok = self._background.wait() and compiled_on_disk(self.group)  # else: compile here
        t1 = time.monotonic()
        if self._stopped.is_set():  # the process is ending: compile nothing
            return
        try:
            with compiled_calls():
                compile_group(self.group)
        except Exception as exc:  # the kernels stay interpreted (the same answers)
            if self.on_failed is not None and not self._stopped.is_set():
                self.on_failed(exc)
            return
        untier(self._tiered)
        self.report = TierReport(time.monotonic() - t0, time.monotonic() - t1, ok)
        self.compiled.set()
        if self.on_switch is not None:
            self.on_switch(self.report)

    def stop(self) -> None:
        """Stop the child if it is still compiling, and compile nothing in this process (the
        kernels stay as they are)."""
        self._stopped.set()
        self._background.stop()


def compile_group(group: str) -> float:
    """Compile (or load from the cache) a group's kernels by running a tiny job; seconds taken."""
    import numpy as np

    t0 = time.perf_counter()
    if group == "batch":
        from graph.ascii import parse_ascii_map
        from mapmatch.batch import BatchMatcher
        from mapmatch.types import Track

        m = parse_ascii_map("a-----------b-----------c\n|           |\nd-----------e", scale=10)
        g = m.graph
        x0, y0 = m.xy("a")
        x1, _ = m.xy("c")
        xs = np.linspace(x0 + 5, x1 - 5, 8)
        ll = np.array([m.lonlat(x, y0 + 1.0) for x in xs])
        t = np.arange(len(xs), dtype=np.float64) * 2.0
        BatchMatcher(g).match(Track("warm", t, ll[:, 1].astype(np.float64), ll[:, 0].astype(np.float64)))
    elif group == "online":
        from graph.ascii import parse_ascii_map
        from mapmatch.online import OnlineMatcher
        from mapmatch.types import Fix

        m = parse_ascii_map("a-----------b-----------c", scale=10)
        om = OnlineMatcher(m.graph)
        session = om.new_session()
        (x0, y0), (x1, _) = m.xy("a"), m.xy("c")
        for i, x in enumerate(np.linspace(x0 + 5, x1 - 5, 6).tolist()):
            lon, lat = m.lonlat(x, y0 + 1.0)
            om.update(session, Fix(time=float(i), lat=lat, lon=lon, heading=90.0, speed=10.0, pos_sigma=5.0))
    elif group == "simulator":
        from mapmatch.sim.kalman import run_filter
        from mapmatch.sim.sensors import SensorData

        # 5 s straight east at 10 m/s (the filter's own inputs: fewer imports than a drive)
        t = np.arange(6, dtype=np.float64)
        full = np.full_like
        run_filter(
            SensorData(
                gps_t=t, gps_x=10.0 * t, gps_y=0.0 * t, gps_sigma=full(t, 3.0), gps_speed=full(t, 10.0),
                gps_course=full(t, 90.0), gps_outlier=np.zeros(len(t), dtype=np.bool_), gyro_t=t,
                gyro=0.0 * t, odo_t=t, odo=10.0 * t, compass_t=t, compass=full(t, 90.0),
                true_gyro_bias=0.0 * t, true_odo_scale=0.0, outages=(),
            )
        )  # fmt: skip
    else:
        raise KeyError(group)
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    """Compile the groups named (default: all), whatever ``MAPMATCH_KERNELS`` says."""
    groups = (argv if argv is not None else sys.argv[1:]) or list(GROUPS)
    if not set_mode(interpreted=False):
        print("kernels run interpreted in this process: nothing to compile", file=sys.stderr)
        return 2
    for group in groups:
        if group not in GROUPS:
            print(f"unknown kernel group {group!r} (groups: {', '.join(GROUPS)})", file=sys.stderr)
            return 2
        announce(group)
        print(f"{group}: ready in {compile_group(group):.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
