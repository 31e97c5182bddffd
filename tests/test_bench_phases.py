"""The robustness bench's phase-shifted runs (bench/peers_robust.py) start where the track starts.

The peers' ``score.py`` trims the true route only along its first arc, to a run's first fix: a
run that began at fix ``offset`` would be charged with the road driven before that fix.
"""

from __future__ import annotations

import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "bench"


def test_every_phase_run_goes_from_the_first_fix_to_the_last_every_s_th_fix_from_its_offset() -> None:
    sys.path.insert(0, str(BENCH))
    try:
        from peers_robust import phase_runs
    finally:
        sys.path.remove(str(BENCH))
    runs = list(phase_runs(100, [10, 30], 3))
    assert [(k["S"], k["offset"]) for k, _ in runs] == [(10, o) for o in (0, 3, 6, 9)] + [
        (30, o) for o in range(0, 30, 3)
    ]
    for key, idx in runs:
        s, off = key["S"], key["offset"]
        assert idx[0] == 0 and idx[-1] == 99
        assert idx == sorted(set(idx))
        inner = [i for i in idx if i not in (0, 99)]
        assert inner == [i for i in range(off, 99, s) if i != 0]
    # offset 0 is the main bench's draw: every S-th fix from fix 0, and the last
    assert runs[0][1] == [*range(0, 100, 10), 99]
