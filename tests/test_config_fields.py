"""The configuration's fields by class: those that change a result, those that bound work or
memory, those that bound what a caller may send; docs/tuning.md counts them and gives each field
that changes a result its out-of-fold gain (or says how its value is estimated or chosen)."""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path

import pytest

from mapmatch.config import BOUND, RESULT, SERVICE, field_kinds
from mapmatch.errors import ConfigError

TUNING = Path(__file__).resolve().parents[1] / "docs" / "tuning.md"
GAIN = re.compile(r"^([+-]\d+\.\d+|estimated from data|model constant|not measured)")
"""How a gain cell starts: a signed figure, or how the value is chosen where no switch measures it."""


def _section(page: str, title: str) -> str:
    """The text under the heading ``title`` (any level) up to the next heading of that level or
    higher."""
    head = re.search(rf"^(#+) {re.escape(title)}\s*$", page, re.M)
    assert head, f"docs/tuning.md has no heading {title!r}"
    level = len(head.group(1))
    nxt = re.search(rf"^#{{1,{level}}} ", page[head.end() :], re.M)
    return page[head.end() : head.end() + nxt.start()] if nxt else page[head.end() :]


def _rows(text: str) -> dict[str, list[str]]:
    """Table rows whose first cell is a code span: its text, and the other cells."""
    out = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        m = re.fullmatch(r"`([\w.]+)`", cells[0]) if line.startswith("|") else None
        if m:
            out[m.group(1)] = cells[1:]
    return out


def test_every_field_has_one_class() -> None:
    kinds = field_kinds()
    assert set(kinds.values()) <= {RESULT, BOUND, SERVICE}
    assert kinds["model.search_radius"] == BOUND and kinds["model.beta"] == RESULT
    assert kinds["online.corrections.max_path_edges"] == SERVICE
    # every field of a section is classed, by its full name
    assert all(name.count(".") >= 1 for name in kinds)


def test_a_class_of_a_field_that_does_not_exist_is_an_error(monkeypatch: pytest.MonkeyPatch) -> None:
    import mapmatch.config as config

    monkeypatch.setattr(config, "_BOUNDS", config._BOUNDS | {"batch.route.no_such_field"})
    with pytest.raises(ConfigError, match=r"batch\.route\.no_such_field"):
        config.field_kinds()


def test_tuning_page_counts_the_classes() -> None:
    """The page's sentence of counts is the registry's."""
    counts = Counter(field_kinds().values())
    page = TUNING.read_text(encoding="utf-8")
    sentence = (
        r"Of the (\d+) fields, (\d+) change a result, (\d+) bound work or memory and (\d+) bound"
        r" what a caller may send"
    )
    m = re.search(sentence.replace(" ", r"\s+"), page)
    assert m, "docs/tuning.md states no counts of the classes"
    assert [int(x) for x in m.groups()] == [
        sum(counts.values()),
        counts[RESULT],
        counts[BOUND],
        counts[SERVICE],
    ]


def test_tuning_page_gives_every_result_field_its_out_of_fold_gain() -> None:
    """One row per field that changes a result, with its gain out of fold (a signed figure) or
    how its value is chosen; one row per bound, none for a field of another class."""
    kinds = field_kinds()
    page = TUNING.read_text(encoding="utf-8")
    result = _rows(_section(page, "Fields that change a result"))
    bounds = _rows(_section(page, "Fields that bound work, memory or input"))
    want_result = {n for n, k in kinds.items() if k == RESULT}
    assert sorted(want_result - set(result)) == [], "fields that change a result without a row"
    assert sorted(set(result) - want_result) == [], "rows of fields that change no result"
    no_gain = [n for n, cells in result.items() if len(cells) < 2 or not GAIN.match(cells[0])]
    assert no_gain == [], "rows without an out-of-fold gain or how the value is chosen"
    assert all(cells[1] for cells in result.values()), "a row without its loss or evidence"
    assert set(bounds) == {n for n, k in kinds.items() if k != RESULT}
