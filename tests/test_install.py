"""The install tells the truth: a Python older than the pins need gets one line of ours,
and pyproject's lower bound is the one the setup script enforces."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_a_too_old_python_gets_one_line_naming_the_version(tmp_path):
    fake = tmp_path / "python3.10"  # answers as Python 3.10.13 would
    fake.write_text("#!/usr/bin/env bash\n"
                    "case \"$2\" in\n"
                    "  *version_info*) exit 1 ;;\n"
                    "  *python_version*) echo 3.10.13 ;;\n"
                    "esac\n")
    fake.chmod(0o755)
    venv = tmp_path / "venv"
    env = {**os.environ, "PYTHON": str(fake), "HEML_VENV": str(venv)}
    run = subprocess.run(["bash", str(ROOT / "scripts" / "test.sh")], env=env, capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 1
    lines = (run.stdout + run.stderr).strip().splitlines()
    assert len(lines) == 1 and "3.11 or newer" in lines[0] and "3.10.13" in lines[0]
    assert not venv.exists()  # nothing left behind


def test_requires_python_is_what_the_setup_script_enforces():
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert re.search(r'requires-python = ">=3\.11"', pyproject)
    assert "(3, 11)" in (ROOT / "scripts" / "setup_env.sh").read_text()
    assert sys.version_info >= (3, 11)
