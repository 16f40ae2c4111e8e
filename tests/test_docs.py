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
