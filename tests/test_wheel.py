"""The wheel: the three packages as their folders are named, the .proto as data, and the version."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # builds the wheel and installs it into a new environment

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"  # a copy: building writes build/ and *.egg-info next to the sources
    shutil.copytree(
        ROOT, src, ignore=shutil.ignore_patterns(".git", ".venv", "__pycache__", "build", "*.egg-info", "out")
    )
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         "-w", str(tmp), str(src)],
        check=True, capture_output=True,
    )  # fmt: skip
    (whl,) = tmp.glob("mapmatch-*.whl")
    return whl


def test_wheel_has_the_three_packages_and_the_proto(wheel: Path) -> None:
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/", 1)[0] for n in names}
    assert {t for t in tops if not t.endswith((".dist-info", ".data"))} == {"graph", "mapmatch", "service"}, (
        tops
    )
    for need in (
        "graph/artifact.py",
        "graph/py.typed",
        "service/server.py",
        "service/gen/mapmatch_pb2.py",
        "service/gen/mapmatch_pb2_grpc.py",
        "mapmatch/cli.py",
        "mapmatch/py.typed",
        "mapmatch/static/leaflet/leaflet.js",  # the HTML map works offline: Leaflet ships inside
        "mapmatch/static/leaflet/leaflet.css",
        "mapmatch/static/leaflet/LICENSE",
    ):
        assert need in names, need
    assert any(n.endswith(".data/data/share/mapmatch/proto/mapmatch/v1/mapmatch.proto") for n in names)
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names), "the MIT licence text"
    assert not any(n.startswith(("mapmatch/graph/", "mapmatch/service/")) for n in names)
    assert not any("/gen/mapmatch/" in n for n in names), "stubs in a package named mapmatch"
    entry = next(n for n in names if n.endswith("entry_points.txt"))
    assert "mapmatch = mapmatch.cli:main" in zipfile.ZipFile(wheel).read(entry).decode()


def test_installed_wheel_imports_and_has_a_version(wheel: Path, tmp_path: Path) -> None:
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)  # a pure-Python wheel installs by unpacking
    code = (
        "import importlib.util, mapmatch, graph.artifact, service.gen.mapmatch_pb2 as pb;"
        "print(mapmatch.__version__); print(mapmatch.__file__); print(graph.artifact.__file__);"
        "print(pb.DESCRIPTOR.name); print(mapmatch.load_map.__module__)"
    )
    env = dict(os.environ, PYTHONPATH=str(site))
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, check=True
    ).stdout.split()
    version = wheel.name.split("-")[1]
    assert out[0] == version
    assert out[1].startswith(str(site)) and out[2].startswith(str(site / "graph"))
    assert out[3] == "mapmatch/v1/mapmatch.proto" and out[4] == "graph.artifact"
