"""Helpers shared by the benchmark scripts: timing, machine description, output paths.

Results go to :data:`DOCS` (JSON and tables under ``benchmarks/``, charts under
``img/``): the folder named by ``HEML_BENCH_OUT`` (``heml-gym bench NAME --out DIR`` sets
it), else the checkout's ``docs/`` when the package runs from a source checkout, else
``./heml-gym-results`` in the working directory (an installed package).
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import numpy as np

#: The source checkout the benchmarks run from (its configs/ and docs/), when they do.
ROOT = Path(__file__).resolve().parents[1]
IN_CHECKOUT = (ROOT / "pyproject.toml").is_file() and (ROOT / "docs" / "benchmarks").is_dir()


def output_folder() -> Path:
    """Where results go: ``HEML_BENCH_OUT``, else the checkout's docs/, else ./heml-gym-results."""
    chosen = os.environ.get("HEML_BENCH_OUT")
    if chosen:
        return Path(chosen).expanduser().resolve()
    return ROOT / "docs" if IN_CHECKOUT else Path.cwd() / "heml-gym-results"


DOCS = output_folder()
RESULTS = DOCS / "benchmarks"
IMAGES = DOCS / "img"


def checkout_file(relative: str) -> Path:
    """A file of the source checkout (a config, a doc), or a one-line error saying the
    benchmark needs a checkout (or the path given explicitly)."""
    path = ROOT / relative
    if not path.exists():
        raise SystemExit(f"{relative}: not found (this benchmark reads the source checkout's {relative}; "
                         "run it from a clone of heml-gym, or give the path)")
    return path


def cpu_avx_flags() -> list[str]:
    """The CPU's AVX feature flags (``/proc/cpuinfo``), e.g. ``["avx", "avx2", "avx512f", ...]``."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return [f for f in line.split(":", 1)[1].split() if f.startswith("avx")]
    except OSError:
        pass
    return []


def vector_isa(flags: list[str] | None = None) -> str:
    """``"AVX-512"``, ``"AVX2 only"`` or ``"no AVX2"``: what the vectorised kernels can use.
    The same Numba kernel runs up to 3-4x faster with AVX-512, so every result records it."""
    flags = cpu_avx_flags() if flags is None else flags
    if any(f.startswith("avx512") for f in flags):
        return "AVX-512"
    return "AVX2 only" if "avx2" in flags else "no AVX2"


#: The vector width each codegen target compiles for (see :func:`codegen_target`).
TARGET_ISA = {"x86-64": "SSE2", "nehalem": "SSE4.2", "sandybridge": "AVX", "haswell": "AVX2", "broadwell": "AVX2",
              "skylake": "AVX2", "znver1": "AVX2", "znver2": "AVX2", "znver3": "AVX2", "skylake-avx512": "AVX-512",
              "cascadelake": "AVX-512", "icelake-server": "AVX-512", "sapphirerapids": "AVX-512",
              "znver4": "AVX-512", "generic": "SSE2"}


def codegen_target() -> dict:
    """What the Numba kernels are compiled for: ``cpu`` (the LLVM CPU name: the host's, or
    ``NUMBA_CPU_NAME``), ``features`` (``"host"``: the host's instruction flags, as Numba
    adds them unless ``NUMBA_CPU_FEATURES`` is set; ``"target"``: the named CPU's own) and
    ``isa`` (the vector width that gives). ``NUMBA_CPU_NAME=haswell`` alone on an AVX-512
    host still compiles AVX-512 code: scripts/cpu_matrix.sh sets ``NUMBA_CPU_FEATURES=""``."""
    import llvmlite.binding as ll
    import numba

    name = numba.config.CPU_NAME
    features = numba.config.CPU_FEATURES
    if name is None:
        return {"cpu": ll.get_host_cpu_name(), "features": "host", "isa": vector_isa(), "set_by": "host"}
    if features is None:
        return {"cpu": name, "features": "host", "isa": vector_isa(), "set_by": "NUMBA_CPU_NAME"}
    isa = TARGET_ISA.get(name.lower(), "?")
    if features:
        isa = "AVX-512" if "+avx512f" in features else "AVX2" if "+avx2" in features else isa
    return {"cpu": name, "features": features or "target", "isa": isa, "set_by": "NUMBA_CPU_NAME"}


def machine_info() -> dict:
    """CPU, core count, the Numba codegen target and library versions, stored beside
    every result."""
    import numba

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "vector_isa": vector_isa(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": numba.__version__,
        "numba_threads": numba.config.NUMBA_NUM_THREADS,
        "codegen": codegen_target(),
        "date": time.strftime("%Y-%m-%d"),
    }


def median_time(fn, min_reps: int = 5, max_reps: int = 200, budget_s: float = 1.0) -> dict:
    """Median wall time (s) of ``fn()`` over repeated calls after one warm-up call.

    Repeats at least ``min_reps`` times and until ``budget_s`` seconds are spent (at most
    ``max_reps``). Returns the median, the interquartile range and the repeat count.
    """
    fn()
    times = []
    start = time.perf_counter()
    while len(times) < max_reps and (len(times) < min_reps or time.perf_counter() - start < budget_s):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    q1, med, q3 = np.percentile(times, [25, 50, 75])
    return {"median_s": float(med), "iqr_s": float(q3 - q1), "reps": len(times)}


def parse_arguments(doc: str, flags: dict[str, str] | None = None, argv=None):
    """Command-line arguments of a study that takes none but ``flags`` (``{"--name":
    help}``, each a switch): ``--help`` shows ``doc``, anything else is a one-line error."""
    import argparse

    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    for flag, help_text in (flags or {}).items():
        ap.add_argument(flag, action="store_true", help=help_text)
    return ap.parse_args(argv)


#: The ``--envs`` names of the accuracy studies that take some of the tasks' scenes.
SHORT_ENVS = {"tissue": "heml_gym/TissueRetraction-v1", "organ": "heml_gym/OrganRetraction-v2"}


def add_envs_option(ap, default: str) -> None:
    """``--envs``: comma-separated :data:`SHORT_ENVS` names (read back by :func:`env_ids`)."""
    ap.add_argument("--envs", default=default, help=f"comma-separated, of {', '.join(SHORT_ENVS)}")


def env_ids(ap, value: str) -> list[str]:
    """The env ids that ``--envs value`` names; a one-line ``ap.error`` for an unknown name."""
    names = [e for e in value.split(",") if e]
    if not names or any(e not in SHORT_ENVS for e in names):
        ap.error(f"--envs: give names among {', '.join(SHORT_ENVS)}, got {value!r}")
    return [SHORT_ENVS[e] for e in names]


def command_line(module: str, ap, args, leave_out=("from_json",)) -> str:
    """The command that ran ``module`` (``python -m``) with ``args`` (parsed by ``ap``):
    the options whose values differ from their defaults, for a stored result's header."""
    parts = [f"python -m {module}"]
    for key, value in vars(args).items():
        if key in leave_out or value == ap.get_default(key):
            continue
        flag = "--" + key.replace("_", "-")
        parts.append(flag if value is True else f"{flag} {value:g}" if isinstance(value, float) else f"{flag} {value}")
    return " ".join(parts)


def current_tasks() -> dict[str, str]:
    """The registered version of each task, ``{"heml_gym/TissueRetraction": "v1", ...}``."""
    from heml_gym.envs import ENV_IDS

    return dict(env_id.rsplit("-", 1) for env_id in ENV_IDS)


def with_tasks(data: dict, envs=None) -> dict:
    """``data`` with ``"tasks"`` first: the version of each task the result measured, from
    ``envs`` (env ids or names) or, when None, the versioned env ids written in ``data``
    (none: a physics-only result, ``{}``). Stored results say which task they are on, so a
    task's next version leaves them recognisably stale (docs/benchmarks/index.md)."""
    if "tasks" in data:
        return data
    current = current_tasks()
    text = json.dumps(data) if envs is None else " ".join(envs)
    tasks = {name: version for name, version in current.items() if name.split("/")[-1] in text}
    return {"tasks": tasks, **data}


def write_json(name: str, data: dict, envs=None, folder: Path | None = None) -> Path:
    """Store a result as ``folder / name`` (default docs/benchmarks/), labelled with the
    task versions it measured (:func:`with_tasks`)."""
    folder = RESULTS if folder is None else Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_text(json.dumps(with_tasks(data, envs), indent=1) + "\n")
    return path


def store_and_report(name: str, data: dict | None, report, envs=None) -> dict:
    """A study's last step: ``data`` stored as ``name.json`` (with its task versions), or,
    when None (``--from-json``), the stored ``name.json`` read back; then ``report(data)``
    (markdown) written to ``name.md`` and printed. Returns the data."""
    if data is None:
        data = json.loads((RESULTS / f"{name}.json").read_text())
    else:
        write_json(f"{name}.json", data, envs)
    text = report(data).rstrip() + "\n"
    (RESULTS / f"{name}.md").write_text(text)
    print(text)
    return data


def markdown_table(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def throughput_rows(rows: list[dict], **match) -> list[dict]:
    """The rows of an ``env_throughput`` result whose fields equal ``match`` (``env``,
    ``actions``, ``num_envs``, ``threads``, ...). ``omp_wait_policy`` defaults to
    ``"PASSIVE"`` (the main rows); ``None`` keeps every policy."""
    policy = match.pop("omp_wait_policy", "PASSIVE")
    found = [r for r in rows if all(r.get(k) == v for k, v in match.items())]
    if policy is not None:
        found = [r for r in found if r.get("omp_wait_policy", "PASSIVE").upper() == policy.upper()]
    return found


def throughput_rate(rows: list[dict], **match) -> float | None:
    """The median env steps/s of the first row :func:`throughput_rows` finds, else None."""
    found = throughput_rows(rows, **match)
    return found[0]["median_steps_per_s"] if found else None
