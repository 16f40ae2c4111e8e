"""The docs say what their stored results say (benchmarks/report/check_docs.py): generated
blocks equal their stored tables, and every number quoted in the prose has a stored
source."""

from __future__ import annotations

from heml_gym.benchmarks.report import check_docs


def test_the_docs_match_their_stored_results():
    assert check_docs.check() == []


def test_the_check_finds_a_number_without_a_source_and_a_stale_block(tmp_path, monkeypatch):
    doc = tmp_path / "doc.md"
    doc.write_text("The flap ran at 123,457.5 env steps/s, about 1,000,001 in all.\n\n"
                   "<!-- BEGIN env_throughput -->\nan old table\n<!-- END env_throughput -->\n")
    monkeypatch.setattr(check_docs, "documents", lambda: [doc])
    failures = check_docs.check()
    assert any("123,457.5 has no stored source" in f for f in failures)
    assert not any("1,000,001" in f for f in failures)  # written as approximate
    assert any("block env_throughput differs" in f for f in failures)


def test_the_check_finds_a_sentence_over_sixty_words(tmp_path, monkeypatch):
    """Sentences are counted in the prose: code, tables, headings and HTML comments aside,
    split at . ! ? : ; before a capital, a backtick or a bracket."""
    def sentence(n: int) -> str:
        return "The " + " ".join(["tissue"] * (n - 2)) + " folds."

    long_doc, short_doc = tmp_path / "long.md", tmp_path / "short.md"
    long_doc.write_text("# A heading of a few words\n\nA short one. " + sentence(61) + "\n")
    short_doc.write_text("A short one; " + sentence(60) + "\n\n| a table row | " + sentence(70) + " |\n\n"
                         "```\n" + sentence(70) + "\n```\n\n<!-- " + sentence(70) + " -->\n\n- " + sentence(59) + "\n"
                         "- " + sentence(59) + "\n")  # (a bullet's marker counts as a word)
    monkeypatch.setattr(check_docs, "documents", lambda: [long_doc, short_doc])
    failures = check_docs.check()
    assert [f for f in failures if "words" in f] == [f"{long_doc}: line 3: a sentence of 61 words (at most 60): "
                                                     "The tissue tissue tissue tissue tissue tissue tissue ..."]
    assert [len(s.split()) for s in check_docs.sentences(short_doc.read_text())] == [3, 60, 60, 60]


def test_relative_links_in_the_readme_guides_studies_and_stored_results_resolve():
    """Every relative Markdown link (``[text](path)``, ``![chart](path)``) in README.md, the
    guides (docs/*.md), the studies (docs/studies/), the stored results (docs/benchmarks/,
    its archive included) and CHANGELOG.md names a file or folder that exists."""
    import re

    from heml_gym.benchmarks.common import ROOT

    docs = ROOT / "docs"
    files = [ROOT / "README.md", *docs.glob("*.md"), *(docs / "studies").glob("*.md"),
             *(docs / "benchmarks").rglob("*.md"), ROOT / "CHANGELOG.md"]
    def anchors(doc):  # GitHub's heading slugs
        text = re.sub(r"```.*?```", "", doc.read_text(), flags=re.S)
        return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
                for h in re.findall(r"^#+ (.*)$", text, flags=re.M)}

    broken = []
    for path in files:
        text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
        for target in re.findall(r"\]\(\s*<?([^)\s>]+)", text):
            if re.match(r"[a-z]+:|#", target):
                continue
            file, _, anchor = target.partition("#")
            linked = path.parent / file
            if not linked.exists():
                broken.append(f"{path.relative_to(ROOT)}: {target}")
            elif anchor and linked.suffix == ".md" and anchor not in anchors(linked):
                broken.append(f"{path.relative_to(ROOT)}: {target} (no such heading)")
    assert broken == []
