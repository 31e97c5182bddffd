"""The session blob format, pinned byte for byte: the fixed drives of :mod:`session_blobs`
encode to the stored blobs, every stored blob decodes and re-encodes to the same bytes, and a
decoded blob goes on exactly as the live session did."""

from __future__ import annotations

from session_blobs import blobs, drives, pinned

from mapmatch.online import SessionState


def test_the_fixed_drives_encode_to_the_pinned_bytes() -> None:
    got, want = blobs(), pinned()
    assert [len(r) for r in got] == [len(r) for r in want]
    for run, (g, w) in enumerate(zip(got, want, strict=True)):
        for i, (a, b) in enumerate(zip(g, w, strict=True)):
            assert a == b, f"drive {run}, fix {i}: the blob differs"


def test_every_pinned_blob_decodes_and_re_encodes_to_its_bytes() -> None:
    for run in pinned():
        for blob in run:
            assert SessionState.from_bytes(blob).to_bytes() == blob


def test_a_decoded_pinned_blob_goes_on_as_the_live_session_did() -> None:
    m, runs = drives()
    for fixes, run in zip(runs, pinned(), strict=True):
        for i in range(len(run) - 1):
            st = SessionState.from_bytes(run[i])
            m.update(st, fixes[i + 1])
            assert st.to_bytes() == run[i + 1], f"fix {i + 1}"
