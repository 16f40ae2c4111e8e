"""Copy the benchmark tables (docs/benchmarks/*.md) into the prose docs and README.md.

Each doc marks where a table goes with ``<!-- BEGIN name -->`` and ``<!-- END name -->``;
this script replaces what is between them with ``docs/benchmarks/name.md``. Run it after
re-running benchmarks so the docs match the measurements.

    python benchmarks/update_docs.py
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import DOCS, RESULTS, ROOT  # noqa: E402

PATTERN = re.compile(r"(<!-- BEGIN (\w+) -->\n)(.*?)(<!-- END \2 -->)", re.S)
LINK = re.compile(r"\]\((?!https?:|#|/)([^)#\s]+)")


def relink(text: str, into: Path) -> str:
    """Links written relative to docs/benchmarks/, rewritten relative to the folder ``into``."""
    return LINK.sub(lambda m: "](" + Path(os.path.relpath(RESULTS / m.group(1), into)).as_posix(), text)


def update(path: Path) -> list[str]:
    text = path.read_text()
    done = []

    def replace(m):
        table = RESULTS / f"{m.group(2)}.md"
        if not table.is_file():
            return m.group(0)
        done.append(m.group(2))
        text = relink(table.read_text().rstrip(), path.parent)
        return m.group(1) + text + "\n" + m.group(4)

    new = PATTERN.sub(replace, text)
    if new != text:
        path.write_text(new)
    return done


if __name__ == "__main__":
    for doc in [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]:
        names = update(doc)
        if names:
            print(f"{doc.relative_to(ROOT)}: {', '.join(names)}")
