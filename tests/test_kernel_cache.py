"""numba's kernel caches follow source changes in files other than the kernel's own."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from graph.kernel_cache import STAMP_NAME, refresh

ROOT = Path(__file__).resolve().parents[1]


def _tree(tmp_path: Path) -> tuple[Path, Path, Path]:
    src = tmp_path / "src"
    src.mkdir()
    kernel = src / "kernel.py"
    kernel.write_text("from numba import njit\n")
    plain = src / "plain.py"
    plain.write_text("X = 1\n")
    return src, kernel, plain


def test_only_a_change_of_content_deletes_the_cached_kernels(tmp_path: Path) -> None:
    src, _, plain = _tree(tmp_path)
    stamp = tmp_path / "cache" / STAMP_NAME
    pycache = src / "__pycache__"
    pycache.mkdir()

    def cached() -> list[Path]:
        names = ("kernel.f-3.py311.nbi", "kernel.f-3.py311.1.nbc", "other.g-1.py311.nbi")
        for name in names:
            (pycache / name).touch()
        return [pycache / name for name in names]

    files = cached()
    # no stamp yet: new caches, nothing to delete
    assert refresh([src], stamp) is False
    assert stamp.is_file()
    assert all(f.exists() for f in files)
    # touched, same content: the stamp is updated, nothing deleted
    os.utime(plain, ns=(2 * 10**18, 2 * 10**18))
    assert refresh([src], stamp) is False
    assert all(f.exists() for f in files)
    # a changed file without kernels: the cached kernels of the file with kernels go
    plain.write_text("X = 2\n")
    assert refresh([src], stamp) is True
    assert [f.exists() for f in files] == [False, False, True]
    files = cached()
    assert refresh([src], stamp) is False
    assert all(f.exists() for f in files)
    assert not list(stamp.parent.glob("*.tmp"))


def test_a_stamp_that_cannot_be_written_deletes_nothing(tmp_path: Path) -> None:
    src, _, plain = _tree(tmp_path)
    stamp = tmp_path / "cache" / STAMP_NAME
    assert refresh([src], stamp) is False
    (src / "__pycache__").mkdir()
    index = src / "__pycache__" / "kernel.f-3.py311.nbi"
    index.touch()
    # the stamp's temporary file cannot be written (a folder in its place; root ignores modes)
    stamp.with_name(f"{stamp.name}.{os.getpid()}.tmp").mkdir()
    plain.write_text("X = 2\n")
    assert refresh([src], stamp) is False
    assert index.exists()


@pytest.mark.slow
def test_a_cached_kernel_compiles_anew_when_a_kernel_it_calls_changes(tmp_path: Path) -> None:
    """numba checks a cached kernel against its own file only: ``caller`` keeps ``callee``'s old
    code after ``callee.py`` changes, unless :func:`refresh` runs first."""
    pkg = tmp_path / "kpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(
        textwrap.dedent(
            """
            import os
            from pathlib import Path
            from graph.kernel_cache import refresh

            if not os.environ.get("NO_REFRESH"):
                refresh([Path(__file__).parent], Path(os.environ["NUMBA_CACHE_DIR"]) / "kpkg.stamp")
            """
        )
    )
    callee = pkg / "callee.py"
    callee.write_text("from numba import njit\n\n@njit(cache=True)\ndef f():\n    return 1\n")
    (pkg / "caller.py").write_text(
        "from numba import njit\nfrom kpkg.callee import f\n\n@njit(cache=True)\ndef g():\n    return f()\n"
    )
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"), PYTHONPATH=f"{tmp_path}:{ROOT}")

    def run(**extra: str) -> str:
        out = subprocess.run(
            [sys.executable, "-c", "from kpkg.caller import g; print(g())"],
            env={**env, **extra}, capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert out.returncode == 0, out.stderr
        return out.stdout.strip()

    assert run() == "1"
    callee.write_text(callee.read_text().replace("return 1", "return 2"))
    assert run(NO_REFRESH="1") == "1"  # numba's own check: the stale caller
    assert run() == "2"
    assert run() == "2"
