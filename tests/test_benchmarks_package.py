"""The benchmarks are a package (``heml_gym.benchmarks``): importable by name without
``sys.path`` edits, grouped, runnable with ``heml-gym bench NAME --out DIR``, results where
the user says."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

from heml_gym import benchmarks
from heml_gym.agents.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_every_study_imports_by_name_in_its_group():
    known = benchmarks.studies()
    assert {group for group, _ in known.values()} == set(benchmarks.GROUPS)
    for name, (group, line) in known.items():
        module = importlib.import_module(f"heml_gym.benchmarks.{group}.{name}")
        assert Path(module.__file__).resolve() == (ROOT / "benchmarks" / group / f"{name}.py").resolve()
        assert line, f"{name}: no docstring to list it by"


def test_no_study_edits_sys_path_or_reaches_into_private_names():
    for path in (ROOT / "benchmarks").rglob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr == "path" and getattr(node.value, "id", "") == "sys":
                pytest.fail(f"{path.relative_to(ROOT)}: edits sys.path")
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("heml_gym"):
                private = [a.name for a in node.names if a.name.startswith("_")]
                assert not private, f"{path.relative_to(ROOT)} imports private {private} from {node.module}"


def test_bench_lists_runs_into_out_and_refuses_unknown_names(tmp_path, capsys):
    assert main(["bench"]) == 0
    listed = capsys.readouterr().out
    assert all(f"{group}:" in listed for group in benchmarks.GROUPS) and "env_throughput" in listed

    assert main(["bench", "env_thruput", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "unknown benchmark 'env_thruput'" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()

    stored = ROOT / "docs" / "benchmarks"
    archived = stored / "archive" / "env_throughput_comparison.md"  # the stored comparison, of a former task
    before = archived.stat().st_mtime_ns
    args = [str(stored / "env_throughput.json"), str(stored / "env_throughput_avx2.json")]
    assert main(["bench", "compare_env_throughput", "--out", str(tmp_path / "o"), "--extra", *args]) == 0
    table = (tmp_path / "o" / "benchmarks" / "env_throughput_comparison.md").read_text()
    assert "| env | actions | N | threads |" in table
    assert not (stored / "env_throughput_comparison.md").exists()  # the checkout's docs untouched
    assert archived.stat().st_mtime_ns == before


def test_learning_reports_quote_an_iqm_only_from_enough_seeds():
    """With fewer seeds than SEEDS_FOR_AN_IQM the reports list each seed and quote no IQM
    (with 2 the IQM is their plain mean); with enough they quote it."""
    import json

    from heml_gym.agents.stats import SEEDS_FOR_AN_IQM
    from heml_gym.benchmarks.common import RESULTS
    from heml_gym.benchmarks.learning import quick_sweep, rllib_learning
    from heml_gym.benchmarks.report import readme_results

    assert SEEDS_FOR_AN_IQM == 3
    rllib = json.loads((RESULTS / "rllib_learning.json").read_text())
    sweep = json.loads((RESULTS / "quick_sweep.json").read_text())
    assert min(len(rllib["seeds"]), len(sweep["seeds"])) >= SEEDS_FOR_AN_IQM
    for n, quoted in [(SEEDS_FOR_AN_IQM - 1, False), (SEEDS_FOR_AN_IQM, True)]:
        few = {**rllib, "seeds": rllib["seeds"][:n]}
        assert ("IQM" in rllib_learning.report(few)) is quoted
        assert ("IQM" in readme_results.rllib(few)) is quoted
        few = {**sweep, "seeds": sweep["seeds"][:n], "seeds_finished": n}
        assert ("IQM of the final success" in quick_sweep.table(few)) is quoted
