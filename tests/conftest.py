"""Shared fixtures: where the real data lives (``MAPMATCH_SHARED``, :mod:`shared_data`), and skips
naming that setting when it is absent."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import settings
from shared_data import KUBICKA, OSM_DIR, ROOT, SHARED, helsinki_pbf, reason

# Property tests replay the same examples on every run, so that a run fails for the code, not by
# the luck of the draw; `pytest --hypothesis-profile=explore` draws new examples to hunt for bugs.
settings.register_profile("default", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile("default")

__all__ = ["KUBICKA", "OSM_DIR", "ROOT", "SHARED", "helsinki_pbf"]


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        pytest.skip(reason(SHARED))
    return SHARED


@pytest.fixture(scope="session")
def kubicka_dir(shared_dir: Path) -> Path:
    if not KUBICKA.is_dir():
        pytest.skip(reason(KUBICKA))
    return KUBICKA


@pytest.fixture(scope="session")
def osm_dir(shared_dir: Path) -> Path:
    if not OSM_DIR.is_dir():
        pytest.skip(reason(OSM_DIR))
    return OSM_DIR
