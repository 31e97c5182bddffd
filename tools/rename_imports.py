"""Rewrite ``graph.``/``service.`` module references to ``mapmatch.graph.``/``mapmatch.service.``.

The folders ``graph/`` and ``service/`` are installed as ``mapmatch.graph`` and
``mapmatch.service`` (setuptools package-dir, see pyproject.toml), so every import and every
dotted reference to their modules names them so. Run from anywhere, as often as you like (a
second run changes nothing)::

    python tools/rename_imports.py            # rewrite in place, list the files changed
    python tools/rename_imports.py --check    # exit 1 if any file still needs it

It rewrites the Python files of the repository (code, tests, bench, tools) and README.md:

- ``from graph.x import``/``import graph.x``/``"graph.x.y"`` → ``mapmatch.graph.x...`` (same for
  service), for the modules that exist in those folders;
- ``from graph import ...``/``from service import ...`` → ``from mapmatch.graph import ...``;
- symbolic links ``mapmatch/graph -> ../graph`` and ``mapmatch/service -> ../service``, so
  a source tree has the installed layout too (type checkers, plain ``PYTHONPATH``);
- the generated stubs' old package ``service.gen.mapmatch.v1`` → ``mapmatch.service.gen``,
  and the old stub folder ``service/gen/mapmatch/`` is removed (``python -m
  mapmatch.service.gen_proto`` writes the stubs flat into ``service/gen/``).

Names that merely start with the words (``service_util``, ``graph_opts``, ``self.graph.x``) are
left alone: a match needs a module name of the folder right after the dot, and no word
character or dot before.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("graph", "service")
SKIP = ("service/gen/", ".venv", "build/", ".git/")


def _modules(folder: str) -> list[str]:
    d = ROOT / folder
    names = {p.stem for p in d.glob("*.py") if p.stem != "__init__"}
    names |= {p.name for p in d.iterdir() if p.is_dir() and not p.name.startswith(("_", "."))}
    return sorted(names, key=len, reverse=True)


def rules() -> list[tuple[re.Pattern[str], str]]:
    out = [(re.compile(r"(?<![\w.])service\.gen\.mapmatch\.v1\b"), "mapmatch.service.gen")]
    for folder in FOLDERS:
        mods = "|".join(map(re.escape, _modules(folder)))
        out.append((re.compile(rf"(?<![\w.]){folder}\.(?=(?:{mods})\b)"), f"mapmatch.{folder}."))
        out.append((re.compile(rf"^(\s*)from {folder} import\b"), rf"\1from mapmatch.{folder} import"))
        out.append((re.compile(rf"^(\s*)import {folder}$"), rf"\1import mapmatch.{folder} as {folder}"))
    return out


LINE_LENGTH = 110  # ruff's line-length (pyproject.toml)


def rewrite(text: str, patterns: list[tuple[re.Pattern[str], str]]) -> str:
    """The text with every reference rewritten; a line of prose or a string that the longer name
    would push over the line length keeps its old wording (imports are re-wrapped by ruff)."""
    out = []
    for line in text.splitlines(keepends=True):
        new = line
        for pat, repl in patterns:
            new = pat.sub(repl, new)
        code = new.lstrip().startswith(("from ", "import "))
        too_long = len(new.rstrip("\n")) > LINE_LENGTH >= len(line.rstrip("\n"))
        out.append(line if (too_long and not code) else new)
    return "".join(out)


def files() -> list[Path]:
    found = [p for p in ROOT.rglob("*.py") if not any(s in p.relative_to(ROOT).as_posix() for s in SKIP)]
    found = [p for p in found if p.resolve() != Path(__file__).resolve()]
    return sorted(found) + [ROOT / "README.md"]


def _ruff(paths: list[Path]) -> None:
    """Re-sort the imports of the changed files and re-wrap lines the longer names pushed over."""
    ruff = shutil.which("ruff") or str(Path(sys.executable).with_name("ruff"))
    if not paths or not Path(ruff).exists():
        return
    rel = [str(p) for p in paths]
    subprocess.run([ruff, "check", "--select", "I", "--fix", "-q", *rel], cwd=ROOT, check=False)
    subprocess.run([ruff, "format", "-q", *rel], cwd=ROOT, check=False)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--check", action="store_true", help="only report; exit 1 when a file needs rewriting")
    ap.add_argument(
        "--no-ruff", action="store_true", help="do not re-sort imports and re-format changed files"
    )
    args = ap.parse_args(argv)
    patterns = rules()
    changed = []
    for path in files():
        old = path.read_text(encoding="utf-8")
        new = rewrite(old, patterns)
        if new != old:
            changed.append(path)
            if not args.check:
                path.write_text(new, encoding="utf-8")
    for folder in FOLDERS:  # the source tree's mapmatch/graph, mapmatch/service (mypy, plain imports)
        link = ROOT / "mapmatch" / folder
        if not link.exists() and not link.is_symlink():
            changed.append(link)
            if not args.check:
                link.symlink_to(Path("..") / folder, target_is_directory=True)
    old_stubs = ROOT / "service" / "gen" / "mapmatch"
    if old_stubs.is_dir():
        changed.append(old_stubs)
        if not args.check:
            shutil.rmtree(old_stubs)
    if changed and not args.check and not args.no_ruff:
        _ruff([p for p in changed if p.suffix == ".py" and p.exists()])
    for p in changed:
        print(p.relative_to(ROOT))
    return 1 if (args.check and changed) else 0


if __name__ == "__main__":
    sys.exit(main())
