"""Compiled kernels on a first run: small inputs run as Python with the same results, and a
kernel group compiled in a background process is loaded from the cache, not compiled again."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest
from conftest import helsinki_pbf
from test_sim_demo import GRID  # the demo tests' map

import graph.jit as jit
import mapmatch.kernels as kernels
from graph.ascii import parse_ascii_map
from graph.build import build_map
from graph.road_graph import RoadGraph
from mapmatch.sim.demo import demo_drive
from mapmatch.sim.kalman import filter_setup, new_carry, new_outputs, no_map_aid, run_steps
from mapmatch.sim.profile import _limit_accel

ROOT = Path(__file__).resolve().parents[1]


def _same_graph(a: RoadGraph, b: RoadGraph) -> None:
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True), f.name
        elif f.name != "meta":
            assert x == y, f.name


def test_small_inputs_run_the_python_function() -> None:
    assert jit.for_size(_limit_accel, 10) is _limit_accel.py_func
    assert jit.for_size(_limit_accel, jit.PYTHON_MAX_ITEMS + 1) is _limit_accel


@pytest.mark.slow
def test_helsinki_builds_the_same_with_compiled_kernels(monkeypatch: pytest.MonkeyPatch) -> None:
    python = build_map(helsinki_pbf())
    monkeypatch.setattr(jit, "PYTHON_MAX_ITEMS", -1)
    compiled = build_map(helsinki_pbf())
    _same_graph(python, compiled)
    assert python.meta["report"]["strong_components"] == compiled.meta["report"]["strong_components"]


def test_drive_is_the_same_with_the_compiled_speed_profile(monkeypatch: pytest.MonkeyPatch) -> None:
    g = parse_ascii_map(GRID, scale=25.0).graph
    python = demo_drive(g, length_km=1.5, outages="40:15", seed=5)
    monkeypatch.setattr(jit, "PYTHON_MAX_ITEMS", -1)
    compiled = demo_drive(g, length_km=1.5, outages="40:15", seed=5)
    assert python.fixes.equals(compiled.fixes)


def test_open_loop_filter_is_the_same_without_the_map_aided_update() -> None:
    """``aid=None`` compiles the filter without the map-aided update; no aid at every step
    (the closed loop's start) must give the same states."""
    g = parse_ascii_map(GRID, scale=25.0).graph
    drive = demo_drive(g, length_km=1.0, outages="30:10", seed=2)
    setup = filter_setup(drive.sensors)
    n = len(setup.t)
    outs = []
    for aid in (None, no_map_aid(n)):
        out = new_outputs(n)
        run_steps(setup, new_carry(setup.x0, setup.p0), aid, out, 0, n)
        outs.append(out)
    for name, a, b in zip(outs[0]._fields, outs[0], outs[1], strict=True):
        assert np.array_equal(a, b, equal_nan=True), name


def _child_env(cache: Path) -> dict[str, str]:
    return dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(ROOT))


@pytest.mark.slow
def test_background_compile_is_loaded_from_the_cache(tmp_path: Path) -> None:
    """Compiled in a child, the filter is then loaded, not compiled, by the process that waited;
    a second process finds the group cached and starts no child."""
    script = textwrap.dedent(
        """
        import sys
        import mapmatch.kernels as k
        from mapmatch.sim import kalman
        from graph.ascii import parse_ascii_map
        from mapmatch.sim.demo import demo_drive

        with k.compiling_in_background("simulator") as background:
            ran = background.wait()
            g = parse_ascii_map("a-------b-------c\\n|       |\\nd-------e", scale=25.0).graph
            demo_drive(g, length_km=0.3, outages="none", seed=1)
        print(ran, k.is_cached("simulator"), sum(kalman._ekf._cache_hits.values()),
              sum(kalman._ekf._cache_misses.values()))
        """
    )
    env = _child_env(tmp_path / "numba")
    first = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600
    )
    assert first.returncode == 0, first.stderr
    assert first.stdout.split() == ["True", "True", "1", "0"]
    again = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600
    )
    assert again.returncode == 0, again.stderr
    assert again.stdout.split() == ["False", "True", "1", "0"]


def test_a_failed_background_compile_leaves_the_compile_to_the_caller(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(kernels, "is_cached", lambda group: False)
    monkeypatch.setattr(sys, "executable", "/bin/false")
    with kernels.compiling_in_background("simulator") as background:
        assert background.wait() is False


def test_the_child_is_stopped_when_the_caller_gives_up(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    stub = tmp_path / "slow-python"
    pidfile = tmp_path / "pid"
    stub.write_text(f"#!/bin/sh\necho $$ > {pidfile}\nexec sleep 60\n")
    stub.chmod(0o755)
    monkeypatch.setattr(kernels, "is_cached", lambda group: False)
    monkeypatch.setattr(sys, "executable", str(stub))
    with pytest.raises(KeyError), kernels.compiling_in_background("simulator") as background:
        assert background.running()
        for _ in range(100):
            if pidfile.exists() and pidfile.read_text().strip():
                break
            subprocess.run(["sleep", "0.05"], check=True)
        raise KeyError("the caller failed")
    pid = int(pidfile.read_text())
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_the_demo_checks_its_extras_without_importing_them() -> None:
    from mapmatch.extras import MissingExtraError, require_installed

    require_installed("json", "pyrosm", extra="demo", needed_for="mapmatch demo")
    with pytest.raises(MissingExtraError, match=r"needs no_such_xyz, .*pip install 'mapmatch\[demo\]'"):
        require_installed("json", "no_such_xyz", extra="demo", needed_for="mapmatch demo")


@pytest.mark.slow  # compiles a group into a cold cache
def test_a_group_whose_cache_was_written_for_other_source_is_not_cached(tmp_path: Path) -> None:
    """A cache index written for another version of a kernel's file does not count: the kernel
    compiles again, so the "preparing compiled kernels" line must be printed."""
    (tmp_path / "probe_kernels.py").write_text(
        "from numba import njit\n\n@njit(cache=True)\ndef f(x):\n    return x + 1\n"
    )
    script = textwrap.dedent(
        """
        import mapmatch.kernels as k
        k.GROUPS["probe"] = ("probe_kernels",)
        before = k.is_cached("probe")
        import probe_kernels
        probe_kernels.f(1)
        print(before, k.is_cached("probe"))
        """
    )
    env = dict(_child_env(tmp_path / "numba"), PYTHONPATH=f"{ROOT}{os.pathsep}{tmp_path}")

    def run() -> list[str]:
        cmd = [sys.executable, "-c", script]
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr
        return out.stdout.split()

    assert run() == ["False", "True"]  # compiled once, then cached
    assert run() == ["True", "True"]
    (tmp_path / "probe_kernels.py").write_text(
        "from numba import njit\n\n@njit(cache=True)\ndef f(x):\n    return x + 2\n"
    )
    assert run() == ["False", "True"]  # the index is there, but for the old source


def test_a_compile_says_it_is_still_going_and_when_it_is_ready(monkeypatch: pytest.MonkeyPatch) -> None:
    import io

    import mapmatch.kernels as k

    answers = iter([False, False, True])
    monkeypatch.setattr(k, "is_cached", lambda group: next(answers, True))
    monkeypatch.setattr(k, "HEARTBEAT_SECONDS", 0.01)
    monkeypatch.setitem(k.COMPILE_SECONDS, "probe", 60.0)
    monkeypatch.setattr(k, "_announced", set())
    out = io.StringIO()
    assert k.announce("probe", stream=out) is True
    for t in list(threading.enumerate()):
        if t.name == "kernels-probe":
            t.join(10)
    lines = out.getvalue().splitlines()
    assert lines[0] == "preparing compiled kernels (probe), once, about 60 s"
    assert [x.split(":")[1].rsplit(" ", 2)[0] for x in lines[1:]] == [
        " still preparing, so far",
        " ready after",
    ]
    assert k.announce("probe", stream=out) is False  # once per process
