"""Check that the docs say what their stored results say.

Three checks over README.md, the guides (docs/*.md) and the studies (docs/studies/*.md),
each failure printed with its file and line:

1. **Generated blocks are current.** Every ``<!-- BEGIN name -->`` ... ``<!-- END name -->``
   block holds exactly ``docs/benchmarks/name.md`` (as ``update_docs.py`` copies it):
   a benchmark re-run whose tables were not copied into the prose docs fails.
2. **Every quoted number has a source.** In the hand-written text (outside the
   generated blocks, code and links), each number that looks like a measurement (a
   decimal, a percentage, or an integer of three digits or more; years and numbers
   written as approximate, ``~`` or ``about``, aside) must equal, at the precision it is
   written with, a value stored in ``docs/benchmarks/*.json`` or ``*.md``, in the
   shipped configs (``configs/**.yaml``) or a constant of the code (a setting, a test's
   parameter). A number typed from memory, or left behind when its result was
   re-measured, has none.
3. **No sentence runs over 60 words.** Prose (code blocks, tables, headings and HTML
   comments aside; generated blocks included) is split into sentences: bullets and
   paragraphs apart, and a sentence ends at ``.``, ``!``, ``?``, ``:`` or ``;`` followed
   by a space and a capital, a backtick, a parenthesis, a bracket or ``*``. A longer
   sentence fails with its word count.

Stored results of former tasks live in ``docs/benchmarks/archive/``: they need their
``**Stale:**`` banner like any other, and they are no source for a number in the prose.

The second check is a necessary condition (a stored value that happens to round to the
same digits passes), not proof that a sentence quotes the right result; it catches
numbers with no stored source at all, the usual way prose drifts from results.

    python benchmarks/report/check_docs.py          # exit status 1 and a list when something fails
"""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path

import numpy as np
import yaml

from heml_gym.benchmarks.common import parse_arguments, ROOT

RESULTS = ROOT / "docs" / "benchmarks"  # the checkout's stored results, whatever HEML_BENCH_OUT says
BLOCK = re.compile(r"(<!-- BEGIN (\w+) -->\n)(.*?)(<!-- END \2 -->)", re.S)
LONGEST_SENTENCE = 60  # words
NUMBER = re.compile(r"(?<![\w.,\-/^])(\d{1,3}(?:,\d{3})+(?:\.\d+)?|\d+\.\d+|\d+)(?![\w.]*\d)(\s*%)?")
APPROXIMATE = re.compile(r"(~|about |approximately |roughly |around |Python |version )$")


def shown(path: Path) -> str:
    """``path`` relative to the checkout where it is in it."""
    try:
        return str(path.relative_to(ROOT))
    except ValueError:
        return str(path)


def documents() -> list[Path]:
    """README.md, the guides (docs/*.md) and the studies (docs/studies/*.md): the docs
    ``update_docs.py`` writes blocks into."""
    from heml_gym.benchmarks.report import update_docs

    return update_docs.documents()


def stale_blocks(doc: Path) -> list[str]:
    """The generated blocks of ``doc`` that differ from their stored table."""
    from heml_gym.benchmarks.report.update_docs import relink

    failures = []
    text = doc.read_text()
    for m in BLOCK.finditer(text):
        table = RESULTS / f"{m.group(2)}.md"
        if not table.is_file():
            failures.append(f"block {m.group(2)}: no stored table {shown(table)}")
            continue
        expected = relink(table.read_text().rstrip(), doc.parent) + "\n"
        if m.group(3) != expected:
            line = text[:m.start()].count("\n") + 1
            failures.append(f"line {line}: block {m.group(2)} differs from {shown(table)} "
                            "(run python benchmarks/report/update_docs.py)")
    return failures


def stored_values() -> tuple[np.ndarray, set[str]]:
    """Every number in the stored results and the shipped configs: as values, and as the
    strings the generated tables print."""
    values: list[float] = []

    def walk(obj):
        if isinstance(obj, dict):
            for v in obj.values():
                walk(v)
        elif isinstance(obj, (list, tuple)):
            for v in obj:
                walk(v)
        elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
            values.append(float(obj))

    for path in RESULTS.glob("*.json"):
        walk(json.loads(path.read_text()))
    for path in (ROOT / "configs").rglob("*.yaml"):
        walk(yaml.safe_load(path.read_text()))
    for folder in ("heml_gym", "envs", "agents", "benchmarks", "tests", "scripts"):
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Constant):
                    walk(node.value)
    printed = set()
    for path in RESULTS.glob("*.md"):
        printed.update(m.group(1) for m in NUMBER.finditer(path.read_text()))
    return np.unique(np.array(values)), printed


def has_source(token: str, percent: bool, values: np.ndarray, printed: set[str]) -> bool:
    if token in printed:
        return True
    x = float(token.replace(",", ""))
    decimals = len(token.split(".")[1]) if "." in token else 0
    half = 0.5 * 10.0 ** -decimals
    candidates = [(x, half), (x / 1000.0, half / 1000.0), (x * 1000.0, half * 1000.0)]  # (mm / ms / kPa: SI stored)
    candidates += [(x / 100.0, half / 100.0)] if percent else []
    for value, tolerance in candidates:
        i = np.searchsorted(values, value - tolerance - 1e-12)
        if i < len(values) and values[i] <= value + tolerance + 1e-12:
            return True
    return False


def prose(text: str) -> str:
    """``text`` with generated blocks, code, link targets and HTML comments blanked (lines kept)."""
    def blank(m):
        return re.sub(r"[^\n]", " ", m.group(0))

    for pattern in (BLOCK, re.compile(r"```.*?```", re.S), re.compile(r"`[^`]*`"), re.compile(r"\]\([^)\n]*\)"),
                    re.compile(r"<!--.*?-->", re.S), re.compile(r"!\[[^\]]*\]")):
        text = pattern.sub(blank, text)
    return text


def unsourced_numbers(doc: Path, values: np.ndarray, printed: set[str]) -> list[str]:
    failures = []
    text = prose(doc.read_text())
    for m in NUMBER.finditer(text):
        token, percent = m.group(1), bool(m.group(2))
        if not ("." in token or "," in token or percent or len(token) >= 3):
            continue  # small integers: counts, sizes, indices
        if re.fullmatch(r"(19|20)\d\d", token) or APPROXIMATE.search(text[max(0, m.start() - 14):m.start()]):
            continue
        if not has_source(token, percent, values, printed):
            line = text[:m.start()].count("\n") + 1
            failures.append(f"line {line}: {token}{'%' if percent else ''} has no stored source")
    return failures


def sentences(text: str) -> list[str]:
    """The sentences of Markdown prose (the project's prose-length rule): code blocks and
    HTML comments dropped, table rows and headings skipped, paragraphs and
    list items apart, each split after ``. ! ? : ;`` followed by a space and a capital,
    ``*``, a backtick, ``(`` or ``[``."""
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    text = re.sub(r"<!--.*?-->", "", text, flags=re.S)
    out = []
    for para in re.split(r"\n\s*\n|\n(?=\s*[-*] |\s*\d+\. |#)", text):
        lines = [line for line in para.split("\n") if not line.strip().startswith(("|", "#"))]
        block = re.sub(r"\s+", " ", " ".join(lines)).strip()
        if block:
            out += [s for s in re.split(r"(?<=[.!?:;])\s+(?=[A-Z*`(\[])", block) if s.strip()]
    return out


def where(sentence: str, text: str) -> int:
    """The line of ``text`` where ``sentence`` starts (approximate: its first words found)."""
    words = sentence.split()
    for n in (8, 4, 1):
        m = re.search(r"\s+".join(re.escape(w) for w in words[:n]), text)
        if m:
            return text[:m.start()].count("\n") + 1
    return 0


def long_sentences(doc: Path) -> list[str]:
    """The sentences of ``doc`` longer than LONGEST_SENTENCE words."""
    text = doc.read_text()
    return [f"line {where(s, text)}: a sentence of {len(s.split())} words (at most {LONGEST_SENTENCE}): "
            f"{' '.join(s.split()[:8])} ..."
            for s in sentences(text) if len(s.split()) > LONGEST_SENTENCE]


def unlabelled_results() -> list[str]:
    """Stored results (docs/benchmarks/ and its archive/) that do not say which task
    versions they measured, whose stale banner is missing (every table in the archive
    needs one), or an index (docs/benchmarks/index.md) that is not current."""
    from heml_gym.benchmarks.report import update_docs

    failures = []
    for path in [*sorted(RESULTS.glob("*.json")), *sorted(update_docs.ARCHIVE.glob("*.json"))]:
        data = json.loads(path.read_text())
        if not isinstance(data.get("tasks"), dict):
            failures.append(f"{shown(path)}: no 'tasks' (the task versions it measured)")
        elif update_docs.stale_tasks(data) and path.with_suffix(".md").is_file() \
                and not path.with_suffix(".md").read_text().startswith("**Stale:**"):
            failures.append(f"{shown(path.with_suffix('.md'))}: measured on a former task, no **Stale:** banner")
    for table in sorted(update_docs.ARCHIVE.glob("*.md")):
        if not table.read_text().startswith("**Stale:**"):
            failures.append(f"{shown(table)}: in the archive of former tasks, no **Stale:** banner")
    index = RESULTS / "index.md"
    if not index.is_file() or index.read_text() != update_docs.index():
        failures.append(f"{shown(index)}: not current (python benchmarks/report/update_docs.py)")
    return failures


def check() -> list[str]:
    values, printed = stored_values()
    failures = unlabelled_results()
    for doc in documents():
        for failure in stale_blocks(doc) + unsourced_numbers(doc, values, printed) + long_sentences(doc):
            failures.append(f"{shown(doc)}: {failure}")
    return failures


def main() -> int:
    failures = check()
    for failure in failures:
        print(failure)
    print(f"{len(failures)} problem(s) in {len(documents())} documents" if failures
          else f"the docs match their stored results ({len(documents())} documents)")
    return 1 if failures else 0


if __name__ == "__main__":
    parse_arguments(__doc__)
    raise SystemExit(main())
