"""The documentation: README stays the short front door, and README and the site's pages link
only to files and headings that exist. The site's own build (``mkdocs build --strict``) runs in
CI; these checks also cover README, which the site does not build."""

from __future__ import annotations

import dataclasses
import re
import unicodedata
from pathlib import Path

import pytest

from mapmatch.cli import SUBCOMMANDS
from mapmatch.config import MatchConfig
from tests.bench_modules import bench_module

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"

SETUP_AND_DEMO = (
    "python3 -m venv .venv && .venv/bin/pip install --no-compile -c requirements/constraints.txt"
    " -e '.[demo]' && .venv/bin/mapmatch demo"
)
TESTS = ".venv/bin/pip install -c requirements/constraints.txt -e '.[dev]' && .venv/bin/python -m pytest -q"

FENCE = re.compile(r"^(```|~~~).*?^\1[^\n]*$", re.M | re.S)
CODE_SPAN = re.compile(r"(`+).+?\1", re.S)
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HEADING = re.compile(r"^#{1,6}\s+(.+?)\s*#*\s*$", re.M)
EXPLICIT_ID = re.compile(r"\{[^}]*#([\w-]+)[^}]*\}\s*$")


def pages() -> list[Path]:
    return sorted(DOCS.rglob("*.md"))


def prose(text: str) -> str:
    """Markdown without fenced code blocks and code spans (links and headings there are code)."""
    return CODE_SPAN.sub("", FENCE.sub("", text))


def slug(heading: str) -> str:
    """The anchor of a heading, as Python-Markdown's toc extension makes it (and GitHub, for
    the plain ASCII headings these pages use)."""
    m = EXPLICIT_ID.search(heading)
    if m:
        return m.group(1)
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text
    text = re.sub(r"[`*]", "", text)  # code and emphasis marks are not in the rendered text
    text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode("ascii")
    text = re.sub(r"[^\w\s-]", "", text).strip().lower()
    return re.sub(r"[-\s]+", "-", text)


def anchors(path: Path) -> set[str]:
    text = FENCE.sub("", path.read_text(encoding="utf-8"))
    return {slug(h) for h in HEADING.findall(text)}


def links(path: Path) -> list[str]:
    return [t for t in LINK.findall(prose(path.read_text(encoding="utf-8"))) if not re.match(r"\w+:", t)]


def broken_links(path: Path, base: Path, *, inside: Path | None = None) -> list[str]:
    """The relative links of ``path`` (resolved from ``base``) whose file or heading is missing;
    with ``inside``, also those that leave that folder."""
    bad = []
    for target in links(path):
        file_part, _, anchor = target.partition("#")
        dest = (base / file_part).resolve() if file_part else path
        if not dest.is_file():
            bad.append(f"{target}: no such file")
        elif inside is not None and not dest.is_relative_to(inside.resolve()):
            bad.append(f"{target}: outside {inside.name}/")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            bad.append(f"{target}: no heading #{anchor} in {dest.name}")
    return bad


def test_readme_is_the_short_front_door() -> None:
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 250, f"README.md has {len(lines)} lines; the rest belongs in docs/"
    text = "\n".join(lines)
    assert not re.search(r"\bsession \d+", text, re.I), "history belongs in CHANGELOG.md"


def test_readme_keeps_the_two_commands_verbatim() -> None:
    text = README.read_text(encoding="utf-8")
    section = text.split("\n## The two commands\n", 1)[1].split("\n## ", 1)[0]
    blocks = [b.strip() for b in re.findall(r"^```[^\n]*\n(.*?)^```", section, re.M | re.S)]
    assert SETUP_AND_DEMO in blocks, blocks
    assert TESTS in blocks, blocks


def test_first_minute_bench_times_readmes_installs() -> None:
    """bench/bench_first_minute.py installs what README's two commands install."""
    bench = bench_module("bench_first_minute")
    for command, install in ((SETUP_AND_DEMO, bench.FIRST_INSTALL), (TESTS, bench.SECOND_INSTALL)):
        pip = command.split("pip install ", 1)[1].split(" && ", 1)[0].replace("'", "")
        assert pip == install, (pip, install)


def test_readme_links_resolve() -> None:
    assert links(README), "README links into the site"
    assert broken_links(README, ROOT) == []


@pytest.mark.parametrize("page", pages(), ids=lambda p: str(p.relative_to(DOCS)))
def test_site_links_resolve(page: Path) -> None:
    # bench/report.py's fragments sit beside the benchmarks page that includes them, so their
    # links, too, resolve from their own folder
    assert broken_links(page, page.parent, inside=DOCS) == []


def test_the_link_check_finds_a_broken_link_and_anchor(tmp_path: Path) -> None:
    (tmp_path / "a.md").write_text("# Title\n\n## Some `code` heading (x)\n", encoding="utf-8")
    page = tmp_path / "p.md"
    page.write_text(
        "[ok](a.md#some-code-heading-x) [file](nope.md) [anchor](a.md#nothing) "
        "`[code](nope.md)` [web](https://example.org/x.md)\n"
        "```\n[fenced](nope.md)\n```\n",
        encoding="utf-8",
    )
    assert broken_links(page, tmp_path) == [
        "nope.md: no such file",
        "a.md#nothing: no heading #nothing in a.md",
    ]


def test_snippets_exist() -> None:
    for page in pages():
        for name in re.findall(r'^--8<-- "([^"]+)"', page.read_text(encoding="utf-8"), re.M):
            assert (DOCS / name).is_file(), f"{page.name} includes {name}, which does not exist"


def test_grpc_page_documents_every_rpc_and_message() -> None:
    proto = (ROOT / "proto" / "mapmatch" / "v1" / "mapmatch.proto").read_text(encoding="utf-8")
    proto = proto.replace("{}", "{\n}")  # an empty message's braces, each on its line
    page = (DOCS / "grpc.md").read_text(encoding="utf-8")
    rpcs = re.findall(r"^\s*rpc (\w+)\(", proto, re.M)
    types = re.findall(r"^(?:message|enum) (\w+)", proto, re.M)
    assert rpcs and types
    headings = set(HEADING.findall(page))
    assert [r for r in rpcs if f"| `{r}` |" not in page] == []
    assert [t for t in types if t not in headings] == []
    for m in re.finditer(r"^(?:message|enum) (\w+) \{(.*?)^\}", proto, re.M | re.S):
        section = page.split(f"\n### {m.group(1)}\n", 1)[1].split("\n### ", 1)[0]
        field = r"^\s*(?:repeated |optional )?[\w.]+ (\w+) = \d+;|^\s*(\w+) = \d+;"
        fields = re.findall(field, m.group(2), re.M)
        for name in (a or b for a, b in fields):
            assert f"`{name}`" in section, f"{m.group(1)}.{name} is not on the gRPC page"


def test_cli_page_has_every_command() -> None:
    headings = set(HEADING.findall((DOCS / "cli.md").read_text(encoding="utf-8")))
    assert [c for c in SUBCOMMANDS if f"`mapmatch {c}`" not in headings] == []


def _documented(option: str, text: str) -> bool:
    return re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", text) is not None


def test_cli_page_has_every_flag() -> None:
    """Every option of every command is named in its section of docs/cli.md, or among the common
    options; `serve`'s may be in Deployment's settings table instead (cli.md points there). A
    ``--no-X`` negation counts as documented with ``--X`` (and ``--[no-]X`` names both)."""
    import argparse

    from mapmatch.cli import build_parser

    page = (DOCS / "cli.md").read_text(encoding="utf-8")
    common = page.split("## Common options", 1)[1].split("\n## ", 1)[0]
    subs = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    missing = []
    for name, parser in subs.choices.items():
        section = page.split(f"## `mapmatch {name}`", 1)[1].split("\n## ", 1)[0]
        if name == "serve":
            section += (DOCS / "deployment.md").read_text(encoding="utf-8")
        section = section.replace("--[no-]", "--")
        for action in parser._actions:
            opts = [o for o in action.option_strings if o not in ("-h", "--help")]
            opts += [o.replace("--no-", "--", 1) for o in opts if o.startswith("--no-")]
            if opts and not any(_documented(o, section) or _documented(o, common) for o in opts):
                missing.append(f"{name} {'/'.join(action.option_strings)}")
    assert missing == []


def _config_sections(section: object, path: str) -> dict[str, object]:
    """Every section and sub-section under ``section`` by its dotted path."""
    out: dict[str, object] = {}
    for f in dataclasses.fields(section):  # type: ignore[arg-type]
        v = getattr(section, f.name)
        if dataclasses.is_dataclass(v):
            full = f"{path}.{f.name}" if path else f.name
            out[full] = v
            out |= _config_sections(v, full)
    return out


def test_tuning_page_has_every_config_field() -> None:
    """A heading per section and sub-section (``## online:``, ``### online.region:``) and a table
    row per field, under its own section's heading."""
    page = (DOCS / "tuning.md").read_text(encoding="utf-8")
    sections = _config_sections(MatchConfig(), "")
    heads = {s: re.search(rf"^#+ {re.escape(s)}:", page, re.M) for s in sections}
    assert [s for s, m in heads.items() if m is None] == []
    misplaced = []
    for s, sec in sections.items():
        start = heads[s].end()  # type: ignore[union-attr]
        nxt = re.search(r"^#+ ", page[start:], re.M)
        body = page[start : start + nxt.start()] if nxt else page[start:]
        for f in dataclasses.fields(sec):  # type: ignore[arg-type]
            if not dataclasses.is_dataclass(getattr(sec, f.name)) and f"| `{f.name}` |" not in body:
                misplaced.append(f"{s}.{f.name}")
    assert misplaced == []
