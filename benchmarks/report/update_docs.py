"""Copy the benchmark tables (docs/benchmarks/*.md) into the prose docs and README.md.

Each doc (README.md, docs/*.md, docs/studies/*.md) marks where a table goes with
``<!-- BEGIN name -->`` and ``<!-- END name -->``; this script replaces what is between
them with ``docs/benchmarks/name.md``. Run it after re-running benchmarks so the docs
match the measurements. It also writes docs/benchmarks/index.md: the current results,
then the archive (docs/benchmarks/archive/: results of former tasks, kept as records).

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
ARCHIVE = RESULTS / "archive"  # results of former tasks, kept as records (not quoted as findings)

PATTERN = re.compile(r"(<!-- BEGIN (\w+) -->\n)(.*?)(<!-- END \2 -->)", re.S)
LINK = re.compile(r"\]\((?!https?:|#|/)([^)#\s]+)")


def documents() -> list[Path]:
    """The docs that hold generated blocks and quote results: README.md, the guides
    (docs/*.md) and the studies (docs/studies/*.md)."""
    return [ROOT / "README.md", *sorted(DOCS.glob("*.md")), *sorted((DOCS / "studies").glob("*.md"))]


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
    for path in [*sorted(RESULTS.glob("*.json")), *sorted(ARCHIVE.glob("*.json"))]:
        stale = stale_tasks(json.loads(path.read_text()))
        table = path.with_suffix(".md")
        if stale and table.is_file() and not table.read_text().startswith("**Stale:**"):
            table.write_text(stale_banner(stale) + table.read_text())
            marked.append(path.stem)
    return marked


def banner_tasks(table: Path) -> str:
    """The former tasks a table's ``**Stale:**`` banner names (for a table without a JSON)."""
    m = re.match(r"\*\*Stale:\*\* measured on a former task \(([^)]*)\)", table.read_text())
    return m.group(1).replace(";", ",") if m else "?"


def index_rows(folder: Path) -> list[list[str]]:
    """One row per result in ``folder``: its JSON (or, for a table stored without one, its
    table), the task versions it measured, its status, date and CPU."""
    rows = []
    stems = sorted({p.stem for p in folder.glob("*.json")}
                   | ({p.stem for p in folder.glob("*.md")} if folder == ARCHIVE else set()))
    for stem in stems:
        path = folder / f"{stem}.json"
        table = f"[{stem}]({stem}.md)" if path.with_suffix(".md").is_file() else stem
        if not path.is_file():
            rows.append([table, banner_tasks(path.with_suffix(".md")), "stale (former task)", "?", "?"])
            continue
        data = json.loads(path.read_text())
        machine = data.get("machine", {}) if isinstance(data.get("machine"), dict) else {}
        tasks = data.get("tasks", {})
        versions = ", ".join(f"{name.split('/')[-1]} {v}" for name, v in tasks.items()) or "none (physics only)"
        status = "stale (former task)" if stale_tasks(data) else "current"
        cpu = f"{machine.get('cpu', '?')} ({machine.get('vector_isa', '?')})" if machine else "?"
        rows.append([table, versions, status, machine.get("date", "?"), cpu])
    return rows


def index() -> str:
    """docs/benchmarks/index.md: each stored result, the task versions it measured, its
    date and CPU; then the archive's."""
    header = ["result", "tasks", "status", "date", "CPU"]
    archive = [[re.sub(r"\]\(", "](archive/", row[0], count=1), *row[1:]] for row in index_rows(ARCHIVE)]
    return ("# Stored results\n\nEvery result under docs/benchmarks/, the version of each task it measured "
            "(`tasks` in its JSON), when and on which CPU. Written by `python benchmarks/report/update_docs.py`.\n\n"
            + markdown_table(header, index_rows(RESULTS))
            + "\n## Archive: results of former tasks, kept as records\n\nResults under docs/benchmarks/archive/, "
            "measured on former versions of the tasks. They are the record of their studies; "
            "the docs do not quote them as findings.\n\n"
            + markdown_table(header, archive))


if __name__ == "__main__":
    parse_arguments(__doc__)
    for name in mark_stale():
        print(f"docs/benchmarks/{name}.md: marked stale (a result of a former task: git mv it, its JSON and chart "
              "to docs/benchmarks/archive/, and take its numbers out of the prose)")
    (RESULTS / "index.md").write_text(index())
    for doc in documents():
        names = update(doc)
        if names:
            print(f"{doc.relative_to(ROOT)}: {', '.join(names)}")
