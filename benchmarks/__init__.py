"""The studies behind docs/: each a script that measures and stores its result (JSON, a
Markdown table, a chart), grouped by what it answers:

* ``speed``: how fast (env steps/s, force evaluations, rendering, Ray scale-out);
* ``accuracy``: how close to a fine model or the peers (convergence, speed vs accuracy);
* ``reliability``: where and how often things fail (soaks, stability maps, solver paths);
* ``learning``: what agents learn (seed sweeps, RLlib, the scripted baselines);
* ``report``: the docs written from the stored results (tables, README lines, checks).

Run one with ``heml-gym bench NAME [--out DIR] [-- ARGS]`` (``heml-gym bench`` lists
them), ``python -m heml_gym.benchmarks.GROUP.NAME``, or, in a checkout,
``python benchmarks/GROUP/NAME.py``. Results go to the checkout's docs/ or to ``--out``
(:mod:`heml_gym.benchmarks.common`).
"""

from __future__ import annotations

import ast
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

GROUPS = ("speed", "accuracy", "reliability", "learning", "report")
#: Modules of the package that are not studies (helpers run by one).
HELPERS = {"common", "op_count_worker"}


def studies() -> dict[str, tuple[str, str]]:
    """Every study: ``{name: (group, first line of its docstring)}``, without importing them."""
    found = {}
    for group in GROUPS:
        for path in sorted((Path(__file__).parent / group).glob("*.py")):
            if path.stem.startswith("_") or path.stem in HELPERS:
                continue
            doc = ast.get_docstring(ast.parse(path.read_text())) or ""
            found[path.stem] = (group, doc.strip().splitlines()[0] if doc.strip() else "")
    return found


def listing() -> str:
    """The studies by group, one line each."""
    lines, known = [], studies()
    for group in GROUPS:
        lines.append(f"{group}:")
        lines += [f"  {name:24s} {line}" for name, (g, line) in known.items() if g == group]
    return "\n".join(lines)


def run(name: str, args: list[str] | None = None, out: str | os.PathLike | None = None) -> int:
    """Run study ``name`` with command-line ``args`` in a fresh Python process (its own
    Numba threads and caches), results under ``out`` (default: see the module docstring).
    Returns its exit status; an unknown name is a ``ValueError`` listing the known ones."""
    known = studies()
    if name not in known:
        raise ValueError(f"unknown benchmark {name!r} (known: {', '.join(known)})")
    module = f"{__name__}.{known[name][0]}.{name}"
    if importlib.util.find_spec(module) is None:  # pragma: no cover - a broken install
        raise ValueError(f"benchmark {name!r}: module {module} not importable")
    env = dict(os.environ)
    if out is not None:
        env["HEML_BENCH_OUT"] = str(Path(out).expanduser().resolve())
    return subprocess.call([sys.executable, "-m", module, *(args or [])], env=env)
