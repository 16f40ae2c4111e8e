"""Copy the benchmark tables (docs/benchmarks/*.md) into the prose docs.

Each doc marks where a table goes with ``<!-- BEGIN name -->`` and ``<!-- END name -->``;
this script replaces what is between them with ``docs/benchmarks/name.md``. Run it after
re-running benchmarks so the docs match the measurements.

    python benchmarks/update_docs.py
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import DOCS, RESULTS  # noqa: E402

PATTERN = re.compile(r"(<!-- BEGIN (\w+) -->\n)(.*?)(<!-- END \2 -->)", re.S)


def update(path: Path) -> list[str]:
    text = path.read_text()
    done = []

    def replace(m):
        table = RESULTS / f"{m.group(2)}.md"
        if not table.is_file():
            return m.group(0)
        done.append(m.group(2))
        # links relative to docs/benchmarks/ become relative to docs/, where the table lands
        text = table.read_text().rstrip().replace("](../img/", "](img/").replace("](../", "](")
        return m.group(1) + text + "\n" + m.group(4)

    new = PATTERN.sub(replace, text)
    if new != text:
        path.write_text(new)
    return done


if __name__ == "__main__":
    for doc in sorted(DOCS.glob("*.md")):
        names = update(doc)
        if names:
            print(f"{doc.relative_to(DOCS.parent)}: {', '.join(names)}")
