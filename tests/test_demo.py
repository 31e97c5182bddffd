"""README's first command: `mapmatch demo` runs end to end through a real gRPC server."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest


@pytest.mark.slow
def test_demo_runs_and_draws(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    proc = subprocess.run(
        [sys.executable, "-m", "mapmatch", "demo", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert "is SERVING" in proc.stderr
    text = proc.stdout
    acc = float(re.search(r"intersection traversal accuracy\s+([\d.]+) %", text).group(1))  # type: ignore[union-attr]
    edge = float(re.search(r"correct edge, all fixes\s+([\d.]+) %", text).group(1))  # type: ignore[union-attr]
    assert acc >= 90.0 and edge >= 90.0, text
    for name in ("match.png", "match.html", "fixes.csv", "matched.csv", "truth.csv", "helsinki.map"):
        assert (out / name).stat().st_size > 0, name
        assert str(out / name) in text or name == "helsinki.map"
    img = mpimg.imread(out / "match.png")
    assert img.shape[0] > 500 and img.shape[1] > 500
    # the picture is not blank: many distinct colours (roads, route, fixes, markers)
    colours = np.unique((img[..., :3] * 255).astype(np.uint8).reshape(-1, 3), axis=0)
    assert len(colours) > 50
    assert "GPS outage" in (out / "match.html").read_text() or "outage" in (out / "match.html").read_text()


def test_demo_rejects_bad_length(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "mapmatch", "demo", "--out", str(tmp_path), "--length-km", "-1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1].startswith("mapmatch demo: error:")
    assert "Traceback" not in proc.stderr
