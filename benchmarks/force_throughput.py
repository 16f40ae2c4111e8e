"""Force-evaluation throughput (tets per second) of every force field vs mesh size.

For box meshes from about 1k to 1M tets, times ``field.forces(x, out=...)`` on a
deformed state, single thread and all Numba threads, median over repeated calls; the
thread counts alternate in 5 rounds (the machine is shared and its load drifts), and the
speed-up is the median of the per-round ratios.
Writes docs/benchmarks/force_throughput.json, .md and docs/img/force_throughput.png.

    python benchmarks/force_throughput.py [--quick]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numba
import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
import heml_gym as hg  # noqa: E402
from common import IMAGES, RESULTS, machine_info, markdown_table, median_time, write_json  # noqa: E402
from heml_gym import materials as M  # noqa: E402

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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small meshes only (a smoke run)")
    args = ap.parse_args(argv)
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
                per_round[threads].append(median_time(lambda: field.forces(x, out=out), min_reps=3,
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
    write_json("force_throughput.json", {"machine": machine_info(), "E": E, "nu": NU, "results": rows})
    write_report(rows, thread_counts)


def write_report(rows, thread_counts):
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
    (RESULTS / "force_throughput.md").write_text(markdown_table(header, table))
    print(markdown_table(header, table))


if __name__ == "__main__":
    main()
