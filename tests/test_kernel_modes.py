"""Kernel modes: interpreted kernels give the compiled answers (match, replay, simulate, in
real processes), ``--kernels`` and ``MAPMATCH_KERNELS`` are checked, and ``auto`` on a cold
cache runs a small job interpreted, saying so in one line."""

from __future__ import annotations

from pathlib import Path

import numba
import numpy as np
import pytest
from test_cli_traps import cross, fixes_lines, run_cli, write_csv  # noqa: F401  (cross: a fixture)
from test_sim_demo import GRID  # the demo tests' map

import graph.jit as jit
import mapmatch.kernels as kernels
from graph.artifact import save_map
from graph.ascii import AsciiMap, parse_ascii_map
from mapmatch.cli import EXIT_USAGE

LONG = 1800.0
"""Seconds a compiled run may take: on a cold cache it compiles its kernels first (the batch
ones: about 100 s of CPU, several minutes on a busy machine)."""


def _both(tmp_path: Path, name: str, *args: str) -> tuple[bytes, bytes]:
    """The output file of ``mapmatch ARGS -o OUT`` compiled and interpreted."""
    out = []
    for mode in ("compiled", "interpreted"):
        path = tmp_path / f"{name}-{mode}.csv"
        proc = run_cli("--kernels", mode, *args, "-o", str(path), timeout=LONG)
        assert proc.returncode == 0, proc.stderr.decode()
        out.append(path.read_bytes())
    return out[0], out[1]


@pytest.mark.slow  # replay and match, compiled and interpreted
@pytest.mark.timeout(2 * LONG)
def test_interpreted_replay_and_match_give_the_compiled_answers(
    cross: tuple[AsciiMap, Path],  # noqa: F811
    tmp_path: Path,
) -> None:
    m, map_path = cross
    fixes = write_csv(tmp_path / "fixes.csv", fixes_lines(m, "car-1") + fixes_lines(m, "car-2", t0=500.0))
    compiled, interpreted = _both(tmp_path, "online", "replay", "--map", str(map_path), str(fixes))
    assert compiled == interpreted and compiled.count(b"\n") > 20
    compiled, interpreted = _both(
        tmp_path, "points", "match", "--map", str(map_path), str(fixes), "--id-col", "vehicle_id",
        "--workers", "1", "--no-progress",
    )  # fmt: skip
    assert compiled == interpreted and b"matched" in compiled


@pytest.mark.slow  # the drive simulated compiled and interpreted
@pytest.mark.timeout(LONG)
def test_interpreted_simulate_gives_the_compiled_drive(tmp_path: Path) -> None:
    save_map(parse_ascii_map(GRID, scale=25.0).graph, tmp_path / "grid.map")
    compiled, interpreted = _both(
        tmp_path, "fixes", "simulate", "--map", str(tmp_path / "grid.map"), "--random-route",
        "--length-km", "1.5", "--outages", "40:15", "--seed", "5",
    )  # fmt: skip
    assert compiled == interpreted and compiled.count(b"\n") > 100


def test_a_bad_kernel_mode_is_a_usage_error(cross: tuple[AsciiMap, Path], tmp_path: Path) -> None:  # noqa: F811
    m, map_path = cross
    fixes = write_csv(tmp_path / "fixes.csv", fixes_lines(m))
    out = tmp_path / "out.csv"
    proc = run_cli("--kernels", "fast", "replay", "--map", str(map_path), str(fixes), "-o", str(out))
    assert proc.returncode == EXIT_USAGE
    assert b"--kernels" in proc.stderr and b"invalid choice" in proc.stderr
    assert b"Traceback" not in proc.stderr
    proc = run_cli("replay", "--map", str(map_path), str(fixes), "-o", str(out), MAPMATCH_KERNELS="fast")
    assert proc.returncode == EXIT_USAGE
    err = proc.stderr.decode().strip().splitlines()
    want = "mapmatch replay: error: MAPMATCH_KERNELS='fast': must be one of auto, compiled, interpreted"
    assert err == [want]
    proc = run_cli("--interpreted-below", "-1", "replay", "--map", str(map_path), str(fixes), "-o", str(out))
    assert proc.returncode == EXIT_USAGE and b"--interpreted-below" in proc.stderr
    assert not out.exists()


@pytest.mark.slow  # processes on a cold kernel cache
@pytest.mark.timeout(LONG)
def test_auto_on_a_cold_cache_runs_a_small_job_interpreted_and_says_so(
    cross: tuple[AsciiMap, Path],  # noqa: F811
    tmp_path: Path,
) -> None:
    m, map_path = cross
    fixes = write_csv(tmp_path / "fixes.csv", fixes_lines(m))
    n = len(fixes_lines(m))
    cold = tmp_path / "cache"
    cold.mkdir()
    args = ("replay", "--map", str(map_path), str(fixes))
    auto = run_cli(*args, "-o", str(tmp_path / "auto.csv"), NUMBA_CACHE_DIR=str(cold), MAPMATCH_KERNELS="")
    assert auto.returncode == 0, auto.stderr.decode()
    notice = [x for x in auto.stderr.decode().splitlines() if "kernels" in x]
    assert len(notice) == 1, auto.stderr.decode()
    assert f"not compiled yet: running interpreted for {n:,} fixes" in notice[0]
    assert "python -m mapmatch.kernels" in notice[0]
    assert not list(cold.rglob("*.nbi"))  # nothing compiled
    compiled = run_cli("--kernels", "compiled", *args, "-o", str(tmp_path / "compiled.csv"), timeout=LONG)
    assert compiled.returncode == 0, compiled.stderr.decode()
    assert (tmp_path / "auto.csv").read_bytes() == (tmp_path / "compiled.csv").read_bytes()
    # -q: no notice
    quiet = run_cli("-q", *args, "-o", str(tmp_path / "q.csv"), NUMBA_CACHE_DIR=str(cold))
    assert quiet.returncode == 0 and b"kernels" not in quiet.stderr


@pytest.fixture()
def cold(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every kernel group reads as not compiled, and the environment asks for no mode."""
    monkeypatch.setattr(kernels, "compiled_on_disk", lambda group: False)
    monkeypatch.delenv("NUMBA_DISABLE_JIT", raising=False)


@pytest.mark.usefixtures("cold")
def test_auto_weighs_interpreting_against_compiling() -> None:
    small = kernels.choose_mode("auto", ("online",), 500, noun="fixes")
    assert small.interpreted and small.notice is not None and "500 fixes" in small.notice
    assert not kernels.choose_mode("auto", ("online",), 1_000_000).interpreted
    assert not kernels.choose_mode("auto", ("online",), None).interpreted  # size unknown
    assert not kernels.choose_mode("auto", (), 10).interpreted  # no kernels
    assert kernels.choose_mode("auto", ("online",), 1_000_000, below=2_000_000).interpreted
    assert not kernels.choose_mode("auto", ("online",), 500, below=100).interpreted
    assert kernels.choose_mode("interpreted", ("batch",), None) == kernels.ModeChoice(True)
    assert kernels.choose_mode("compiled", ("batch",), 1) == kernels.ModeChoice(False)
    # the demo's default drive (6 km) runs interpreted on a cold cache
    demo = kernels.choose_mode("auto", ("simulator", "online"), round(6000 / 7.6))
    assert demo.interpreted
    with pytest.raises(ValueError, match="kernel mode"):
        kernels.choose_mode("fast", ("online",), 1)


def test_auto_keeps_compiled_kernels(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(kernels, "compiled_on_disk", lambda group: True)
    monkeypatch.delenv("NUMBA_DISABLE_JIT", raising=False)
    assert kernels.choose_mode("auto", ("online",), 10) == kernels.ModeChoice(False)


def test_interpreted_powers_are_the_compiled_ones() -> None:
    """``x ** 2`` in a kernel is ``x * x`` (numba), where Python's ``pow`` can differ in the
    last bit: the interpreted copy multiplies."""
    xs = [0.1 * k + 1e-3 for k in range(1, 2000)]
    assert all(jit.int_power(x, 2) == x * x for x in xs)
    assert all(jit.int_power(x, 3) == x * (x * x) for x in xs)
    assert jit.int_power(3, 2) == 9 and isinstance(jit.int_power(3, 2), int)
    assert any(x**2 != x * x for x in [0.1 * k + 1e-3 for k in range(1, 200_000)])

    def k(a, b):  # type: ignore[no-untyped-def]
        return (a - b) ** 2 + 1.0

    fast = jit.as_compiled(k)
    assert fast is not k and getattr(fast, "py_func", None) is k
    assert all(fast(x, 0.3) == (x - 0.3) * (x - 0.3) + 1.0 for x in xs)


def test_the_filters_interpreted_product_is_the_compiled_one() -> None:
    from mapmatch.sim.kalman import _fpft, fpft_lists

    rng = np.random.default_rng(3)
    for scale in (1e-3, 1.0, 1e3):
        f, p = rng.normal(size=(8, 8)) * scale, rng.normal(size=(8, 8))
        p1, p2, fp1, fp2 = p.copy(), p.copy(), np.empty((8, 8)), np.empty((8, 8))
        _fpft(f, p1, fp1)
        fpft_lists(f, p2, fp2)
        assert np.array_equal(p1, p2) and np.array_equal(fp1, fp2)
        assert not np.array_equal(p1, p)


@numba.njit
def _square(x):  # type: ignore[no-untyped-def]
    return x**2


@numba.njit
def _square_plus_one(x):  # type: ignore[no-untyped-def]
    return _square(x) + 1.0


def test_tiered_kernels_run_their_twins_from_python_until_untiered() -> None:
    """:func:`graph.jit.tier`: a kernel and the kernels it calls answer from Python as numba
    would compute, with nothing compiled; in a ``compiled_calls`` block they compile; untiered,
    they are plain dispatchers again."""
    if jit.interpreted():
        pytest.skip("kernels run interpreted in this process")
    from numba.core.registry import CPUDispatcher

    xs = [0.1 * k + 1e-3 for k in range(1, 200_000, 7)]
    assert any(x**2 != x * x for x in xs)  # plain Python would differ from the kernel
    tiered = jit.tier([_square_plus_one])
    try:
        assert {id(d) for d in tiered} == {id(_square_plus_one), id(_square)}
        assert all(_square_plus_one(x) == x * x + 1.0 for x in xs)
        assert not _square_plus_one.overloads and not _square.overloads  # nothing compiled
        with jit.compiled_calls():
            assert _square_plus_one(0.3) == 0.3 * 0.3 + 1.0
        assert _square_plus_one.overloads
    finally:
        jit.untier(tiered)
    assert type(_square_plus_one) is CPUDispatcher and type(_square) is CPUDispatcher
    assert all(_square_plus_one(x) == x * x + 1.0 for x in xs[:100])


def test_a_tiered_group_that_cannot_compile_says_so_and_stays_interpreted(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    if jit.interpreted():
        pytest.skip("kernels run interpreted in this process")
    import subprocess
    import sys

    from mapmatch.online.placement import _place_all

    def failing_child(group: str) -> subprocess.Popen[bytes]:
        return subprocess.Popen([sys.executable, "-c", "raise SystemExit(1)"])

    def no_compiler(group: str) -> float:
        raise RuntimeError("no compiler")

    monkeypatch.setattr(kernels, "_compile_child", failing_child)
    monkeypatch.setattr(kernels, "compile_group", no_compiler)
    failed: list[Exception] = []
    group = kernels.TieredGroup("online", on_failed=failed.append)
    group.start()
    try:
        assert group._thread is not None
        group._thread.join(120)
        assert [str(e) for e in failed] == ["no compiler"]
        assert not group.compiled.is_set() and group.report is None
        assert type(_place_all).__name__.startswith("Tiered")  # still answering interpreted
    finally:
        jit.untier(group._tiered)
    assert type(_place_all).__name__ == "CPUDispatcher"
