"""A user's first minute: cold and warm CPU and wall to the first answer of every command, and
the size of each install.

Cold = a fresh copy of the source tree (its tracked files as they are now: no ``__pycache__``,
so neither Python bytecode nor compiled kernels, exactly as on a fresh clone), with numba's
default cache (``__pycache__`` in that copy; ``NUMBA_CACHE_DIR`` is unset); warm = the same
commands again in the same copy. The commands run one after the other, each as its own
process, in a user's order: ``prep`` (Monaco), ``simulate`` (a 1,000-fix drive on it),
``replay`` and ``match`` of that drive, ``serve`` to SERVING and on to its online kernels
running compiled (on a cold start it answers interpreted while they compile), and ``demo``
(timed to its table and to its exit). A command's kernels shared with an earlier one are
already compiled when it runs. Commands run in the default kernel mode, ``auto`` (a small
job whose kernels are not compiled yet runs them interpreted), or the one ``--kernels``
gives; the table says how each step's kernels ran, cold and warm (``interpreted`` when the
command printed its one-line notice, or the server answered before its kernels were
compiled): a job run interpreted compiles nothing, so its warm run is interpreted too.
``--install`` also times ``pip install -c requirements/constraints.txt`` of the core and of
``[prep]`` into new virtual environments, README's first command (its install of the ``demo``
extra and the demo) and its second command's install of the ``dev`` extra (pip's cache as it
is), and measures their sizes (the whole environment, and what the install added to a new one).
Prints a Markdown table with the machine's load average, which decides the wall times on a
shared machine.

    python bench/bench_first_minute.py [--monaco PATH.osm.pbf] [--skip-demo] [--install]
                                       [--kernels auto|compiled|interpreted]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from shared_data import OSM_DIR  # noqa: E402  (MAPMATCH_SHARED)

MONACO = OSM_DIR / "monaco.osm.pbf"
KERNELS: str | None = None
"""The kernel mode the commands run in (``--kernels``; None: the default, auto)."""
NOTICE = "running interpreted"
"""What a command's one-line notice says when ``auto`` runs it interpreted."""


def _env(cache: Path | None, tree: Path = ROOT) -> dict[str, str]:
    """The environment of a step: ``tree`` on the path; numba's cache in ``cache``, or (None)
    numba's default, ``__pycache__`` next to the tree's sources. Steps run with ``tree`` as
    their working folder too: ``python -m`` puts the working folder first on the path, so run
    from another clone it would import (and time) that clone's warm kernels."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    env.pop("NUMBA_CACHE_DIR", None)
    env.pop("PYTHONPYCACHEPREFIX", None)
    env.pop("NUMBA_DISABLE_JIT", None)
    env.pop("MAPMATCH_KERNELS", None)
    if KERNELS is not None:
        env["MAPMATCH_KERNELS"] = KERNELS
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    return env


def fresh_tree(dst: Path) -> Path:
    """Copy the source tree's tracked files (working-tree contents, links kept) to ``dst``."""
    files = (
        subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True)
        .stdout.decode()
        .split("\0")
    )
    for name in filter(None, files):
        src, out = ROOT / name, dst / name
        if not src.is_symlink() and not src.exists():
            continue  # deleted in the working tree
        out.parent.mkdir(parents=True, exist_ok=True)
        if src.is_symlink():
            out.symlink_to(os.readlink(src))
        else:
            shutil.copy2(src, out)
    return dst


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def _mode(stderr: str) -> str:
    """How a command's kernels ran, from its stderr."""
    if NOTICE in stderr or KERNELS == "interpreted":
        return "interpreted"
    return "compiled"


def demo(tree: Path, out: Path) -> tuple[float, float, float, str]:
    """Seconds (wall to the table, wall to the exit, CPU) of `mapmatch demo` run from ``tree``,
    and how its kernels ran."""
    c0, t0 = _children_cpu(), time.perf_counter()
    err = out.with_name(out.name + ".stderr")
    with open(err, "w") as err_f:
        proc = subprocess.Popen(
            [sys.executable, "-m", "mapmatch", "demo", "--out", str(out)],
            env=_env(None, tree), cwd=tree, stdout=subprocess.PIPE, stderr=err_f, text=True,
        )  # fmt: skip
        return _demo_table(proc, t0, c0, err)


def _demo_table(
    proc: subprocess.Popen[str], t0: float, c0: float, err: Path
) -> tuple[float, float, float, str]:
    assert proc.stdout is not None
    table = float("nan")
    lines = []
    for line in proc.stdout:
        if line.startswith("---") and table != table:
            table = time.perf_counter() - t0
        lines.append(line)
    if proc.wait() != 0:
        raise RuntimeError(f"mapmatch demo exited with {proc.returncode}")
    assert any("route mismatch fraction" in x for x in lines), "".join(lines)
    return table, time.perf_counter() - t0, _children_cpu() - c0, _mode(err.read_text())


def _cpu(pid: int, *, children: bool = False) -> float:
    """CPU seconds of process ``pid`` so far (with ``children``: and of its ended children)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    ticks = sum(int(x) for x in fields[11 : 15 if children else 13])
    return ticks / os.sysconf("SC_CLK_TCK")


SERVED_INTERPRETED = False
"""Whether the last :func:`serve` answered interpreted at SERVING (its kernels compiling)."""
SWITCH_TIMEOUT = 900.0
"""Seconds the bench waits for a cold server to switch to its compiled kernels."""


def serve(cache: Path | None, map_path: Path, tree: Path = ROOT) -> tuple[float, float, float, float]:
    """Seconds from starting `mapmatch serve`: wall and CPU (the server's) to health SERVING,
    and wall and CPU (the server's and its compile child's) to health
    ``mapmatch.v1.MapMatch.Compiled`` SERVING (its online kernels run compiled; on a cold
    start they compile in a child process while the server answers interpreted)."""
    import socket

    from mapmatch.healthcheck import check
    from service.server import KERNELS_HEALTH

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "mapmatch", "serve", "--map", f"mco={map_path}",
         "--address", f"127.0.0.1:{port}"],
        env=_env(cache, tree), cwd=tree, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        while check(f"127.0.0.1:{port}", timeout=0.5)[0] != 0:
            if proc.poll() is not None:
                raise RuntimeError(f"serve exited with {proc.returncode}")
            time.sleep(0.05)
        wall, cpu = time.perf_counter() - t0, _cpu(proc.pid)
        global SERVED_INTERPRETED
        SERVED_INTERPRETED = check(f"127.0.0.1:{port}", KERNELS_HEALTH, timeout=5)[0] != 0
        while check(f"127.0.0.1:{port}", KERNELS_HEALTH, timeout=0.5)[0] != 0:
            if proc.poll() is not None or time.perf_counter() - t0 > SWITCH_TIMEOUT:
                raise RuntimeError("serve did not switch to its compiled kernels")
            time.sleep(0.05)
        return wall, cpu, time.perf_counter() - t0, _cpu(proc.pid, children=True)
    finally:
        proc.terminate()
        proc.wait(30)


def timed(tree: Path, *argv: str) -> tuple[float, float, str]:
    """Seconds (wall, CPU) of ``python -m mapmatch ARGV`` run from ``tree`` to its exit, and
    how its kernels ran."""
    c0, t0 = _children_cpu(), time.perf_counter()
    cmd = [sys.executable, "-m", "mapmatch", *argv]
    proc = subprocess.run(cmd, env=_env(None, tree), cwd=tree, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"mapmatch {argv[0]} exited with {proc.returncode}: {proc.stderr[-2000:]}")
    return time.perf_counter() - t0, _children_cpu() - c0, _mode(proc.stderr)


Step = tuple[str, str, float, float, str]
"""A step's name, load average, wall and CPU seconds, and how its kernels ran."""


def commands(tree: Path, work: Path, source: Path, label: str) -> list[Step]:
    """``(command, load, wall, CPU, kernels)`` of prep, simulate, replay, match and serve, in
    that order."""
    out: list[Step] = []
    d = work / label
    d.mkdir()
    m = d / "city.map"
    steps: list[tuple[str, list[str]]] = [
        ("prep", ["prep", str(source), "-o", str(m), "-q"]),
        ("simulate", ["simulate", "--map", str(m), "--random-route", "--length-km", "10", "--seed", "1",
                      "-o", str(d / "fixes.csv")]),
        ("replay", ["replay", "--map", str(m), str(d / "fixes.csv"), "-o", str(d / "online.csv")]),
        ("match", ["match", "--map", str(m), str(d / "fixes.csv"), "--id-col", "vehicle_id",
                   "-o", str(d / "points.csv"), "--workers", "1", "--no-progress"]),
    ]  # fmt: skip
    for name, argv in steps:
        load = _load()
        wall, cpu, mode = timed(tree, *argv)
        if name == "simulate":
            n = len((d / "fixes.csv").read_text().splitlines()) - 1
            name = f"simulate ({n:,} fixes)"
        out.append((name, load, wall, cpu, "" if name == "prep" else mode))
    load = _load()
    wall, cpu, c_wall, c_cpu = serve(None, m, tree)
    out.append(("serve to SERVING", load, wall, cpu, "interpreted" if SERVED_INTERPRETED else "compiled"))
    out.append(("serve to its online kernels compiled", load, c_wall, c_cpu, "compiled"))
    return out


def _size(folder: Path) -> int:
    """The bytes of the files under ``folder`` (links not followed)."""
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file() and not f.is_symlink())


# the installs of README's two commands (tests/test_docs.py checks README gives these)
FIRST_INSTALL = "--no-compile -c requirements/constraints.txt -e .[demo]"
SECOND_INSTALL = "-c requirements/constraints.txt -e .[dev]"


def _pip(venv: Path, tree: Path, spec: str) -> None:
    subprocess.run(
        [str(venv / "bin" / "pip"), "install", "-q", *spec.split()], cwd=tree, check=True,
        stdout=subprocess.DEVNULL,
    )  # fmt: skip


def installs(work: Path, tree: Path) -> list[tuple[str, str, float, float, int, int]]:
    """``(install, load, wall, CPU, MB, MB added)`` of the core and ``[prep]`` (pip and the
    constraints file, each into a new virtual environment), of README's first command (a new
    virtual environment, its install and ``mapmatch demo``) and of the install of README's
    second command into that environment; "added" leaves out what a new virtual environment
    holds before the install (pip, and on Python 3.11 setuptools)."""
    empty = work / "venv-empty"
    subprocess.run([sys.executable, "-m", "venv", str(empty)], check=True)
    base = _size(empty)
    steps = (
        ("core", "venv-core", "-c requirements/constraints.txt ."),
        ("`[prep]`", "venv-prep", "-c requirements/constraints.txt .[prep]"),
        ("README's first command: `-e '.[demo]'` and the demo", "venv-readme", FIRST_INSTALL),
        ("README's second command's install: `-e '.[dev]'` added", "venv-readme", SECOND_INSTALL),
    )
    out = []
    for name, folder, spec in steps:
        venv = work / folder
        load = _load()
        c0, t0 = _children_cpu(), time.perf_counter()
        if not venv.exists():
            subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
        _pip(venv, tree, spec)
        if spec == FIRST_INSTALL:
            subprocess.run(
                [str(venv / "bin" / "mapmatch"), "demo", "--out", str(work / "demo-readme")], cwd=tree,
                check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )  # fmt: skip
        wall, cpu = time.perf_counter() - t0, _children_cpu() - c0
        size = _size(venv)
        out.append((name, load, wall, cpu, size >> 20, (size - base) >> 20))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--monaco", type=Path, default=MONACO, help="the OSM source prepared first")
    ap.add_argument("--skip-demo", action="store_true")
    ap.add_argument("--install", action="store_true", help="also time the installs and measure them")
    ap.add_argument(
        "--kernels", choices=("auto", "compiled", "interpreted"), help="kernel mode (default: auto)"
    )
    args = ap.parse_args()
    global KERNELS
    KERNELS = args.kernels
    if not args.monaco.is_file():
        print(f"error: no {args.monaco} (set MAPMATCH_SHARED or give --monaco)", file=sys.stderr)
        return 2
    print(f"kernel mode: {args.kernels or 'auto (the default)'}\n")
    print(
        "| step | kernels (cold, warm) | cold wall (s) | cold CPU (s) | warm wall (s) | warm CPU (s) "
        "| load (1, 5, 15 min) |"
    )
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="first-minute-") as tmp:
        work = Path(tmp)
        tree = fresh_tree(work / "tree")
        cold = commands(tree, work, args.monaco, "cold")
        warm = commands(tree, work, args.monaco, "warm")
        for (name, load, cw, cc, mode), (_, _, ww, wc, wmode) in zip(cold, warm, strict=True):
            mode = mode if mode == wmode else f"{mode}, {wmode}"
            print(f"| {name} | {mode} | {cw:.1f} | {cc:.1f} | {ww:.1f} | {wc:.1f} | {load} |", flush=True)
        load = _load()
        wall, cpu, c_wall, c_cpu = serve(None, work / "cold" / "city.map", fresh_tree(work / "tree-serve"))
        mode = "interpreted" if SERVED_INTERPRETED else "compiled"
        print(f"| serve to SERVING, alone in a fresh copy | {mode} | {wall:.1f} | {cpu:.1f} | | | {load} |")
        name = "serve to its online kernels compiled, alone in a fresh copy"
        print(f"| {name} | compiled | {c_wall:.1f} | {c_cpu:.1f} | | | {load} |")
        if not args.skip_demo:
            runs = []
            demo_tree = fresh_tree(work / "tree-demo")  # cold: none of the kernels compiled above
            for label in ("cold", "warm"):
                load = _load()
                runs.append((load, *demo(demo_tree, work / f"demo-{label}")))
            (load, ct, cw, cc, mode), (_, wt, ww, wc, wmode) = runs
            mode = mode if mode == wmode else f"{mode}, {wmode}"
            print(f"| demo, to its table | {mode} | {ct:.1f} | | {wt:.1f} | | {load} |")
            print(
                f"| demo, to its exit | {mode} | {cw:.1f} | {cc:.1f} | {ww:.1f} | {wc:.1f} | {load} |",
                flush=True,
            )
        if args.install:
            print()
            print("| install | wall (s) | CPU (s) | venv (MB) | added (MB) | load (1, 5, 15 min) |")
            print("|---|---|---|---|---|---|")
            for name, load, wall, cpu, mb, added in installs(work, tree):
                print(f"| {name} | {wall:.1f} | {cpu:.1f} | {mb:,} | {added:,} | {load} |", flush=True)
    print(f"\n{os.cpu_count()} cores; targets: demo cold <= 20 s wall and <= 15 s CPU; first match of "
          "a 1,000-point track <= 15 s CPU; serve cold <= 10 s; core install <= 350 MB; README's "
          "first command <= 90 s")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
