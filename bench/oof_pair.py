"""The out-of-fold verdict between two runs of the online bench: a change of the code (no
setting switches it) judged as ``ablate_online.py`` judges a rule.

Both files are ``bench_online_real.py --no-gps-only --json`` outputs (every track's drive with
the five outages) of the same tracks and rates, the code before (``OLD``) and after (``NEW``).
Per fold of ``bench/folds.py`` the version with the lower loss on the other four folds is
chosen (the old one first: a tie keeps it) and scored on the held fold; ``noise`` is the
bootstrap standard error over tracks of the all-track difference (paired).

    python bench/oof_pair.py OLD.json NEW.json            # loss live
    python bench/oof_pair.py OLD.json NEW.json --loss fin
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from ablate_online import Mechanism, table, verdict_row  # noqa: E402

Rows = list[dict[str, object]]


def by_track(path: Path) -> dict[str, Rows]:
    """A ``--json`` file's rows with the outages, per track."""
    out: dict[str, Rows] = {}
    for r in json.loads(path.read_text()):
        if int(r["outages"]) > 0:
            out.setdefault(str(r["track"]), []).append(r)
    return out


def main() -> int:
    """Read both runs and print the verdict row."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("old", type=Path)
    ap.add_argument("new", type=Path)
    ap.add_argument("--loss", choices=("live", "fin"), default="live")
    ap.add_argument("--name", default="the change")
    args = ap.parse_args()
    old, new = by_track(args.old), by_track(args.new)
    names = sorted(set(old) & set(new))
    if len(names) < 5 or set(old) != set(new):
        print("error: both runs must hold the same tracks (at least 5)", file=sys.stderr)
        return 2
    m = Mechanism(args.name, ("old",), loss=args.loss)
    print(table([verdict_row(m, {"defaults": new, "old": old}, names)]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
