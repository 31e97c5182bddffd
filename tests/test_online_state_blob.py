"""The session blob format, pinned: the fixed drives of :mod:`session_blobs` encode to the
stored blobs (the same keys, order and types; floats to the last bits a processor's SIMD path
may move), every stored blob decodes and re-encodes to the same bytes, and a decoded blob goes
on exactly as the live session did; the same states stored in version 2 decode to what version
3 holds."""

from __future__ import annotations

import ast
import base64
import json
from pathlib import Path

import numpy as np
from session_blobs import PINNED_V2, blob_difference, blobs, drives, pinned

from mapmatch.online import SessionState
from mapmatch.online.codec import to_bytes


def test_the_fixed_drives_encode_to_the_pinned_bytes() -> None:
    got, want = blobs(), pinned()
    assert [len(r) for r in got] == [len(r) for r in want]
    for run, (g, w) in enumerate(zip(got, want, strict=True)):
        for i, (a, b) in enumerate(zip(g, w, strict=True)):
            assert (d := blob_difference(a, b)) is None, f"drive {run}, fix {i}: the blob differs at {d}"


def test_a_blob_differing_beyond_the_last_bits_is_told_apart() -> None:
    blob = pinned()[0][-1]
    d = json.loads(blob)
    assert blob_difference(blob, blob) is None
    nudged = dict(d, odo_k=d["odo_k"] * (1 + 1e-15))
    assert blob_difference(json.dumps(nudged).encode(), blob) is None
    moved = dict(d, odo_k=d["odo_k"] + 1e-6)
    assert "odo_k" in (blob_difference(json.dumps(moved).encode(), blob) or "")
    renamed = {("odo" if k == "odo_k" else k): v for k, v in d.items()}
    assert "keys" in (blob_difference(json.dumps(renamed).encode(), blob) or "")


def test_every_pinned_blob_decodes_and_re_encodes_to_its_bytes() -> None:
    for run in pinned():
        for blob in run:
            assert SessionState.from_bytes(blob).to_bytes() == blob


def test_a_decoded_blob_goes_on_exactly_as_the_live_session_did() -> None:
    m, runs = drives()
    for fixes, run in zip(runs, blobs(), strict=True):
        for i in range(len(run) - 1):
            st = SessionState.from_bytes(run[i])
            m.update(st, fixes[i + 1])
            assert st.to_bytes() == run[i + 1], f"fix {i + 1}"


def test_a_decoded_pinned_blob_goes_on_as_the_live_session_did() -> None:
    m, runs = drives()
    for fixes, run in zip(runs, pinned(), strict=True):
        for i in range(len(run) - 1):
            st = SessionState.from_bytes(run[i])
            m.update(st, fixes[i + 1])
            assert (d := blob_difference(st.to_bytes(), run[i + 1])) is None, f"fix {i + 1}: {d}"


def test_version_2_blobs_of_the_same_states_decode_to_what_version_3_holds() -> None:
    old, new = pinned(PINNED_V2), pinned()
    assert [len(r) for r in old] == [len(r) for r in new]
    for run_old, run_new in zip(old, new, strict=True):
        for v2, v3 in zip(run_old, run_new, strict=True):
            assert json.loads(v2)["version"] == 2 and json.loads(v3)["version"] == 3
            st = SessionState.from_bytes(v2)
            assert st.to_bytes() == v3 and to_bytes(SessionState.from_bytes(v3), version=2) == v2


def test_each_key_of_the_blob_comes_from_its_record() -> None:
    blob = pinned()[1][-1]
    d = json.loads(blob)
    st = SessionState.from_bytes(blob)
    a, b, c, r = st.anchor, st.bias, st.crossings, st.region
    assert (a.odo_k, a.anc_odo, list(a.chain)) == (d["odo_k"], d["anc_odo"], d["chain"])
    assert (b.res_pos2, b.res_head2, b.drift_sigma) == (d["res_pos2"], d["res_head2"], d["drift_sigma"])
    assert b.vector._asdict() == d["bias"]
    headings = np.frombuffer(base64.b64decode(d["headings_f64"]), "<f8").reshape(-1, 2).tolist()
    assert st.headings == headings and len(st.headings) > 2
    times = np.cumsum(d["trail_time_ms"]) / 1000.0
    odos = np.cumsum(d["trail_odo_cm"]) / 100.0
    assert [[p.time, p.odo] for p in c.trail] == np.column_stack([times, odos]).tolist()
    assert len(c.trail) > 2 and len(c.back) == len(d["back"])
    assert (r.init_pending, r.init_odo, len(r.live)) == (d["init_pending"], d["init_odo"], len(d["live"]))
    assert (st.odo_k, st.chain, st.res_pos2, st.trail) == (a.odo_k, a.chain, b.res_pos2, c.trail)


# the modules that write each record of a session (assignments, deletions and list mutations
# of its fields, by any function of the module)
OWNERS = {
    "AnchorState": {"anchor.py"},
    "BiasState": {"bias.py"},
    "CrossingTrail": {"anchor.py"},
    "RegionState": {"region.py", "correction.py"},
}
_FIELD = {"anchor": "AnchorState", "bias": "BiasState", "crossings": "CrossingTrail", "region": "RegionState"}
_MUTATE = {"append", "extend", "insert", "pop", "remove", "clear"}


def _record(node: ast.expr, typed: dict[str, str]) -> str | None:
    """The record whose field ``node`` (an attribute, perhaps subscripted) is, if any."""
    while isinstance(node, ast.Subscript):
        node = node.value
    if not isinstance(node, ast.Attribute):
        return None
    base = node.value
    if isinstance(base, ast.Name) and base.id in typed:
        return typed[base.id]
    if isinstance(base, ast.Attribute) and base.attr in _FIELD:
        return _FIELD[base.attr]
    return None


def _targets(node: ast.AST) -> list[ast.expr]:
    """What ``node`` writes: assignment and deletion targets, the list a mutating call changes."""
    if isinstance(node, ast.Assign | ast.Delete):
        targets = node.targets
    elif isinstance(node, ast.AugAssign | ast.AnnAssign):
        targets = [node.target]
    elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in _MUTATE:
        targets = [node.func.value]
    else:
        return []
    return [one for t in targets for one in (t.elts if isinstance(t, ast.Tuple) else [t])]


def _writes(path: Path) -> set[str]:
    """The records whose fields the module at ``path`` writes: through ``<state>.<record>.<field>``
    or through a parameter annotated with the record's type."""
    out: set[str] = set()
    for fn in ast.walk(ast.parse(path.read_text())):
        if isinstance(fn, ast.FunctionDef):
            typed = {
                a.arg: ast.unparse(a.annotation)
                for a in [*fn.args.args, *fn.args.kwonlyargs]
                if a.annotation is not None and ast.unparse(a.annotation) in OWNERS
            }
            out |= {r for node in ast.walk(fn) for t in _targets(node) if (r := _record(t, typed))}
    return out


def test_each_record_is_written_only_by_its_own_modules() -> None:
    import mapmatch.online

    folder = Path(mapmatch.online.__file__).parent
    writers: dict[str, set[str]] = {name: set() for name in OWNERS}
    for path in sorted(folder.glob("*.py")):
        if path.name in ("state.py", "codec.py"):  # the records themselves; decoding builds them
            continue
        for rec in _writes(path):
            writers[rec].add(path.name)
    assert writers == OWNERS
