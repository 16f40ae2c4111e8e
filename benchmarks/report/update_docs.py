"""Copy the benchmark tables (docs/benchmarks/*.md) into the prose docs and README.md.

Each doc marks where a table goes with ``<!-- BEGIN name -->`` and ``<!-- END name -->``;
this script replaces what is between them with ``docs/benchmarks/name.md``. Run it after
re-running benchmarks so the docs match the measurements.

    python benchmarks/report/update_docs.py
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from heml_gym.benchmarks.common import ROOT, current_tasks, markdown_table, parse_arguments

DOCS = ROOT / "docs"  # the checkout's docs, whatever HEML_BENCH_OUT says
RESULTS = DOCS / "benchmarks"

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


def stale_tasks(data: dict) -> dict[str, str]:
    """The tasks a stored result measured on another version than today's."""
    current = current_tasks()
    return {name: version for name, version in data.get("tasks", {}).items() if current.get(name) != version}


def stale_banner(stale: dict[str, str]) -> str:
    tasks = "; ".join(f"{name.split('/')[-1]} {version}" for name, version in stale.items())
    now = ", ".join(f"{name.split('/')[-1]}-{version}" for name, version in current_tasks().items()
                    if name in stale)
    return f"**Stale:** measured on a former task ({tasks}), not on today's {now}; kept as the record of that study.\n\n"


def mark_stale() -> list[str]:
    """Begin the table of every result measured on a former task with a ``**Stale:**``
    banner (unless it has one)."""
    marked = []
    for path in sorted(RESULTS.glob("*.json")):
        stale = stale_tasks(json.loads(path.read_text()))
        table = path.with_suffix(".md")
        if stale and table.is_file() and not table.read_text().startswith("**Stale:**"):
            table.write_text(stale_banner(stale) + table.read_text())
            marked.append(path.stem)
    return marked


def index() -> str:
    """docs/benchmarks/index.md: each stored result, the task versions it measured, its
    date and CPU."""
    rows = []
    for path in sorted(RESULTS.glob("*.json")):
        data = json.loads(path.read_text())
        machine = data.get("machine", {}) if isinstance(data.get("machine"), dict) else {}
        tasks = data.get("tasks", {})
        versions = ", ".join(f"{name.split('/')[-1]} {v}" for name, v in tasks.items()) or "none (physics only)"
        status = "stale (former task)" if stale_tasks(data) else "current"
        table = f"[{path.stem}]({path.stem}.md)" if path.with_suffix(".md").is_file() else path.stem
        cpu = f"{machine.get('cpu', '?')} ({machine.get('vector_isa', '?')})" if machine else "?"
        rows.append([table, versions, status, machine.get("date", "?"), cpu])
    return ("# Stored results\n\nEvery result under docs/benchmarks/, the version of each task it measured "
            "(`tasks` in its JSON), when and on which CPU. Written by `python benchmarks/report/update_docs.py`.\n\n"
            + markdown_table(["result", "tasks", "status", "date", "CPU"], rows))


if __name__ == "__main__":
    parse_arguments(__doc__)
    for name in mark_stale():
        print(f"docs/benchmarks/{name}.md: marked stale")
    (RESULTS / "index.md").write_text(index())
    for doc in [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]:
        names = update(doc)
        if names:
            print(f"{doc.relative_to(ROOT)}: {', '.join(names)}")
