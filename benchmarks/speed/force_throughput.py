"""Force-evaluation throughput (tets per second) of every force field vs mesh size.

For box meshes from about 1k to 1M tets, times ``field.forces(x, out=...)`` on a
deformed state, single thread and all Numba threads, median over repeated calls; the
thread counts alternate in 5 rounds (the machine is shared and its load drifts), and the
speed-up is the median of the per-round ratios.
Then the laws on one core at 105 k tets, natively and compiled for an AVX2-only target
(``NUMBA_CPU_NAME=haswell`` with its own ``NUMBA_CACHE_DIR``), each in 5 fresh child
processes, interleaved (a process's rate varies by up to 1.5x from one to the next on
these VMs; the medians over processes are reported): what
users of laptops and cloud VMs without AVX-512 get, and the Neo-Hookean / StVK ratio,
which must stay >= 1 (Neo-Hookean's spring part is constant). A Neo-Hookean kernel that
stops vectorising on AVX2 shows there at once.
Writes docs/benchmarks/force_throughput.json, .md and docs/img/force_throughput.png.

    python benchmarks/speed/force_throughput.py [--quick]
"""

from __future__ import annotations

import argparse
import sys

import numba
import numpy as np
from tqdm import tqdm
import heml_gym as hg
from heml_gym.benchmarks.common import IMAGES, RESULTS, cpu_avx_flags, machine_info, markdown_table, median_time, write_json
from heml_gym import materials as M

E, NU = 5e3, 0.45
FIELDS = {
    "HEML Neo-Hookean": lambda mesh: hg.HemlForce(mesh, M.NeoHookean(E=E, nu=NU)),
    "HEML StVK": lambda mesh: hg.HemlForce(mesh, M.StVenantKirchhoff(E=E, nu=NU)),
    "F-FEM Neo-Hookean": lambda mesh: hg.FemForce(mesh, M.NeoHookean(E=E, nu=NU)),
    "F-FEM StVK": lambda mesh: hg.FemForce(mesh, M.StVenantKirchhoff(E=E, nu=NU)),
    "Mass-tensor StVK": lambda mesh: hg.MassTensorForce(mesh, M.StVenantKirchhoff(E=E, nu=NU)),
    "Mass-spring": lambda mesh: hg.MassSpringForce(mesh, M.NeoHookean(E=E, nu=NU)),
}
CELLS = [6, 10, 16, 26, 38, 55]  # 6 c^3 tets: 1.3k ... 1.0M
ROUNDS = 5  # interleaved rounds per case


def deformed(mesh: hg.TetMesh) -> np.ndarray:
    rng = np.random.default_rng(0)
    h = mesh.min_edge_length
    return mesh.vertices * np.array([1.1, 0.95, 0.97]) + 0.05 * h * rng.standard_normal(mesh.vertices.shape)


LAW_CELLS = 26  # 105,456 tets
LAW_FIELDS = ("HEML Neo-Hookean", "HEML StVK")


def law_rates(cells: int = LAW_CELLS) -> dict:
    """Tets per second (one thread, median) of :data:`LAW_FIELDS` on a ``cells``^3 box."""
    numba.set_num_threads(1)
    mesh = hg.box_mesh((0.1, 0.1, 0.1), cells)
    x = deformed(mesh)
    out = np.empty_like(x)
    rates = {}
    for name in LAW_FIELDS:
        field = FIELDS[name](mesh)
        field.parallel_min_elements = 10**12
        rates[name] = mesh.n_tets / median_time(lambda: field.forces(x, out=out), min_reps=9, budget_s=2.0)["median_s"]
    return {"n_tets": mesh.n_tets, "tets_per_s": rates}


#: child processes per target: the rate of one process varies by up to 1.5x between
#: processes on these VMs (where its arrays land), more than within one
LAW_PROCESSES = 5


def law_rates_by_process(processes: int = LAW_PROCESSES) -> dict:
    """:func:`law_rates` in ``processes`` fresh child processes per target, the targets
    interleaved: ``"native"`` (this CPU) and ``"avx2_target"`` (compiled for an AVX2-only
    CPU, ``NUMBA_CPU_NAME=haswell`` with its own ``NUMBA_CACHE_DIR``). Per target: each
    process's rates, their medians, and the median of the per-process Neo-Hookean / StVK
    ratios (a ratio taken within one process)."""
    import json
    import os
    import subprocess
    import tempfile

    nh, stvk = LAW_FIELDS
    with tempfile.TemporaryDirectory() as cache:
        envs = {"native": dict(os.environ),
                "avx2_target": dict(os.environ, NUMBA_CPU_NAME="haswell", NUMBA_CACHE_DIR=cache)}
        runs = {key: [] for key in envs}
        for _ in tqdm(range(processes), desc="law rates (child processes)", unit="round"):
            for key, env in envs.items():
                out = subprocess.run([sys.executable, __file__, "--law-rates-json"], env=env, capture_output=True,
                                     text=True, check=True)
                runs[key].append(json.loads(out.stdout.strip().splitlines()[-1]))
    result = {}
    for key, rs in runs.items():
        rates = {name: [r["tets_per_s"][name] for r in rs] for name in LAW_FIELDS}
        result[key] = {"n_tets": rs[0]["n_tets"], "processes": len(rs),
                       "tets_per_s": {name: float(np.median(v)) for name, v in rates.items()},
                       "per_process_tets_per_s": rates,
                       "nh_over_stvk": float(np.median(np.array(rates[nh]) / np.array(rates[stvk])))}
    return result


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small meshes only (a smoke run)")
    ap.add_argument("--law-rates-json", action="store_true", help="internal: print law_rates() as JSON")
    args = ap.parse_args(argv)
    if args.law_rates_json:
        import json

        print(json.dumps(law_rates()))
        return
    cells = CELLS[:3] if args.quick else CELLS
    all_threads = numba.config.NUMBA_NUM_THREADS
    thread_counts = sorted({1, all_threads})
    rows = []
    jobs = [(c, name) for c in cells for name in FIELDS]
    for c, name in tqdm(jobs, desc="force throughput", unit="case"):
        mesh = hg.box_mesh((0.1, 0.1, 0.1), c)
        field = FIELDS[name](mesh)
        x = deformed(mesh)
        out = np.empty_like(x)
        # thread counts interleaved in rounds, so that every count sees the same machine
        # load; the speed-up is the median of the per-round ratios
        per_round = {threads: [] for threads in thread_counts}
        for _ in range(ROUNDS):
            for threads in thread_counts:
                numba.set_num_threads(threads)
                per_round[threads].append(median_time(lambda f=field: f.forces(x, out=out), min_reps=3,
                                                      budget_s=1.0 / ROUNDS)["median_s"])
        for threads in thread_counts:
            med = float(np.median(per_round[threads]))
            ratio = np.array(per_round[1]) / np.array(per_round[threads])
            rows.append({
                "field": name, "n_tets": mesh.n_tets, "n_vertices": mesh.n_vertices,
                "threads": threads, "median_s": med, "round_medians_s": per_round[threads],
                "tets_per_s": mesh.n_tets / med, "speedup_vs_1": float(np.median(ratio)),
            })
        numba.set_num_threads(all_threads)
        del field
    laws = {**law_rates_by_process(), "cpu_avx_flags": cpu_avx_flags()}
    numba.set_num_threads(all_threads)
    write_json("force_throughput.json", {"machine": machine_info(), "E": E, "nu": NU, "results": rows, "laws": laws})
    write_report(rows, thread_counts, laws)


def write_report(rows, thread_counts, laws=None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    for i, name in enumerate(FIELDS):
        for threads, style in zip(thread_counts, ["-", "--"]):
            pts = [(r["n_tets"], r["tets_per_s"]) for r in rows if r["field"] == name and r["threads"] == threads]
            if pts:
                n, tps = zip(*pts)
                ax.plot(n, tps, style, marker="o", color=f"C{i}",
                        label=f"{name}, {threads} thread{'s' if threads > 1 else ''}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("mesh size (tets)")
    ax.set_ylabel("force evaluations: tets per second")
    ax.set_title("Force-field throughput (box meshes, median of repeated calls)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    IMAGES.mkdir(parents=True, exist_ok=True)
    fig.savefig(IMAGES / "force_throughput.png", dpi=120)

    header = ["field", "tets"] + [f"M tets/s, {t} thr" for t in thread_counts]
    if len(thread_counts) > 1:
        header.append("speed-up")
    table = []
    for name in FIELDS:
        for n in sorted({r["n_tets"] for r in rows}):
            mine = {r["threads"]: r for r in rows if r["field"] == name and r["n_tets"] == n}
            if not mine:
                continue
            row = [name, f"{n:,}"] + [f"{mine[t]['tets_per_s'] / 1e6:.1f}" for t in thread_counts]
            if len(thread_counts) > 1:
                last = mine[thread_counts[-1]]
                row.append(f"{last.get('speedup_vs_1', last['tets_per_s'] / mine[1]['tets_per_s']):.2f}x")
            table.append(row)
    text = markdown_table(header, table)
    if laws:
        nh, stvk = LAW_FIELDS
        lines = []
        for key, label in (("native", "this CPU (" + ", ".join(laws["cpu_avx_flags"]) + ")"),
                           ("avx2_target", "compiled for AVX2 only (`NUMBA_CPU_NAME=haswell`)")):
            r, spread = laws[key]["tets_per_s"], laws[key].get("per_process_tets_per_s")
            span = (f" ({min(spread[nh]) / 1e6:.1f}-{max(spread[nh]) / 1e6:.1f})" if spread else "")
            lines.append([label, f"{laws[key]['n_tets']:,}", laws[key].get("processes", 1),
                          f"{r[nh] / 1e6:.1f}{span}", f"{r[stvk] / 1e6:.1f}",
                          f"{laws[key].get('nh_over_stvk', r[nh] / r[stvk]):.2f}"])
        text += ("\nOne thread, HEML Neo-Hookean against StVK (Neo-Hookean must not be the slower: its spring "
                 "part is constant). Each target is timed in several fresh processes, interleaved (one process's "
                 "rate varies by up to 1.5x between processes on these VMs); rates are the medians over the "
                 "processes (Neo-Hookean's range in brackets), NH / StVK the median of the ratios taken within "
                 "each process:\n\n" + markdown_table(
                     ["target", "tets", "processes", "Neo-Hookean M tets/s", "StVK M tets/s", "NH / StVK"], lines))
    (RESULTS / "force_throughput.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
