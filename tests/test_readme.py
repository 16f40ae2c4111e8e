"""The README's front door holds: its Python examples run as written, its test command is
the one CI runs, its task table names every registered task, and it stays short."""

from __future__ import annotations

import re
import runpy
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
EXAMPLES = re.findall(r"```python\n(.*?)```", README, re.S)


def test_the_readme_has_a_gym_and_a_physics_example():
    assert len(EXAMPLES) == 2
    assert "gym.make(" in EXAMPLES[0] and "make_solver(" in EXAMPLES[1]
    assert all(len(code.strip().splitlines()) <= 12 for code in EXAMPLES)


@pytest.mark.parametrize("index", range(len(EXAMPLES)))
def test_each_readme_example_runs_as_written(index, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    script = tmp_path / "example.py"
    script.write_text(EXAMPLES[index])
    runpy.run_path(str(script), run_name="__main__")
    printed = capsys.readouterr().out
    assert printed.strip() and "nan" not in printed.lower()


def test_the_readme_test_command_is_what_ci_runs():
    command = "bash scripts/test.sh"
    assert f"```bash\n{command}\n```" in README
    assert command in (ROOT / ".ci" / "run").read_text()


def test_the_task_table_names_every_registered_task():
    import heml_gym.envs as envs

    table = README.split("<!-- BEGIN readme_tasks -->")[1].split("<!-- END readme_tasks -->")[0]
    for env_id in envs.ENV_IDS:
        assert f"`{env_id}`" in table


def test_the_readme_is_short_and_has_an_animation_licence_and_citation():
    assert len(README.splitlines()) <= 150
    words = len(README.split())
    assert words <= 1500
    gif = re.search(r"!\[[^\]]*\]\((docs/img/[^)]+\.gif)\)", README)
    assert gif and (ROOT / gif.group(1)).stat().st_size < 5 * 2**20
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
    citation = (ROOT / "CITATION.cff").read_text()
    assert "cff-version: 1.2.0" in citation and "Goulette" in citation
