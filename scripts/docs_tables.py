"""Write the docs' option tables from the config dataclasses (``core.config_docs.options_table``).

    python scripts/docs_tables.py           # rewrite every table that is out of date
    python scripts/docs_tables.py --check   # list the out-of-date tables, exit 1 if any

A table sits in a Markdown file of ``docs/`` between two markers that name its class:

    <!-- options: gensplat_transforms.settings:GenSplatConfig -->
    ...generated...
    <!-- /options -->

The integrations' configs are imported too (``scripts/setup.sh`` installs them).
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys
from pathlib import Path

from gensplat_transforms.core.atomic import atomic_write
from gensplat_transforms.core.config_docs import options_table

DOCS = Path(__file__).resolve().parent.parent / "docs"
BLOCK = re.compile(r"^(<!-- options: ([\w.]+):(\w+) -->\n)(.*?)^(<!-- /options -->)", re.DOTALL | re.MULTILINE)


def render(text: str) -> str:
    """``text`` with every marked table regenerated."""

    def table(match: re.Match) -> str:
        cls = getattr(importlib.import_module(match[2]), match[3])
        return f"{match[1]}{options_table(cls)}\n{match[5]}"

    opened, closed = (len(re.findall(rf"^{m}", text, re.MULTILINE)) for m in ("<!-- options:", "<!-- /options -->"))
    if opened != closed or len(BLOCK.findall(text)) != opened:
        raise ValueError(f"{opened} '<!-- options: module:Class -->' markers and {closed} '<!-- /options -->': "
                         "each table needs both, on lines of their own")  # fmt: skip
    return BLOCK.sub(table, text)


def stale(docs: Path | None = None) -> dict[Path, str]:
    """The Markdown files under ``docs`` (default: the repository's) whose tables are out of
    date, with their new text; a file whose markers do not pair raises ValueError naming it."""
    out = {}
    for path in sorted((docs or DOCS).glob("*.md")):
        text = path.read_text()
        try:
            new = render(text)
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None
        if new != text:
            out[path] = new
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only list out-of-date files; exit 1 if any")
    args = parser.parse_args(argv)
    changed = stale()
    for path, text in changed.items():
        print(f"{'out of date' if args.check else 'wrote'}: {path.relative_to(DOCS.parent)}")
        if not args.check:
            atomic_write(path, lambda tmp, text=text: Path(tmp).write_text(text))
    return 1 if args.check and changed else 0


if __name__ == "__main__":
    sys.exit(main())
