"""The seed's operation-count table, reproduced: HEML vs mass-tensor, counted and timed.

For the seed's mesh family (coarse and fine regular cube, irregular cube, kidney, uterus;
the organs meshed with gmsh at the seed's scale) counts the exact + - x / operations of
one force evaluation by running each force kernel's own source with counting scalars
(benchmarks/speed/op_count_worker.py, in a subprocess with NUMBA_DISABLE_JIT=1), and times the
compiled kernels on one thread. Writes docs/benchmarks/op_counts.{json,md} and
docs/img/op_counts.png.

    python benchmarks/speed/op_counts.py
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numba
import numpy as np
from tqdm import tqdm

HERE = Path(__file__).resolve().parent
import heml_gym as hg
from heml_gym.benchmarks.common import parse_arguments, IMAGES, RESULTS, machine_info, markdown_table, median_time, write_json
from heml_gym import materials as M
from heml_gym import organs

# The seed's table (thousands of + x operations, as we read it; see docs), in this order.
SEED = {
    "Reg. Cube1": {"mass_tensor": 2999, "heml": 70, "gain": 43.0},
    "Reg. Cube2": {"mass_tensor": 36198, "heml": 787, "gain": 46.0},
    "Irreg. Cube": {"mass_tensor": 3935, "heml": 89, "gain": 44.3},
    "Kidney": {"mass_tensor": 96292, "heml": 449, "gain": 214.3},
    "Uterus": {"mass_tensor": 318707, "heml": 2500, "gain": 127.5},
}


def mesh_family() -> dict[str, hg.TetMesh]:
    return {
        "Reg. Cube1": hg.box_mesh((0.1, 0.1, 0.1), 4),
        "Reg. Cube2": hg.box_mesh((0.1, 0.1, 0.1), 9),
        "Irreg. Cube": organs.irregular_cube_mesh(),
        "Kidney": organs.kidney_mesh(),
        "Uterus": organs.uterus_mesh(),
    }


def count(mesh: hg.TetMesh) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "mesh.npz"
        np.savez(path, vertices=mesh.vertices, tets=mesh.tets)
        env = dict(os.environ, NUMBA_DISABLE_JIT="1")
        res = subprocess.run([sys.executable, "-m", "heml_gym.benchmarks.speed.op_count_worker", str(path)],
                             env=env, capture_output=True, text=True, check=True)
    return json.loads(res.stdout)


def timings(mesh: hg.TetMesh) -> dict:
    rng = np.random.default_rng(0)
    x = mesh.vertices * 1.05 + 1e-3 * mesh.min_edge_length * rng.standard_normal(mesh.vertices.shape)
    out = np.empty_like(x)
    fields = {
        "heml_stvk": hg.HemlForce(mesh, M.StVenantKirchhoff(E=5e3, nu=0.45)),
        "heml_neo_hookean": hg.HemlForce(mesh, M.NeoHookean(E=5e3, nu=0.45)),
        "mass_tensor": hg.MassTensorForce(mesh, M.StVenantKirchhoff(E=5e3, nu=0.45)),
    }
    numba.set_num_threads(1)
    try:
        return {name: median_time(lambda f=f: f.forces(x, out=out), min_reps=20, budget_s=1.0)
                for name, f in fields.items()}
    finally:
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)


def main():
    rows = []
    for name, mesh in tqdm(mesh_family().items(), desc="op counts", unit="mesh"):
        rows.append({
            "mesh": name, "n_vertices": mesh.n_vertices, "n_tets": mesh.n_tets,
            "n_edges": len(mesh.edges), "counts": count(mesh), "times": timings(mesh),
            "seed": SEED[name],
        })
    write_json("op_counts.json", {"machine": machine_info(), "results": rows})
    header = ["mesh", "vertices", "tets", "mass-tensor k-ops", "HEML-StVK k-ops", "count gain",
              "seed MT", "seed HEML", "seed gain", "time MT (ms)", "time HEML-StVK (ms)",
              "time gain", "HEML-NH k-ops", "time HEML-NH (ms)"]
    table = []
    for r in rows:
        c, t, s = r["counts"], r["times"], r["seed"]
        mt, hs, hn = (c[k]["add_mul"] for k in ("mass_tensor", "heml_stvk", "heml_neo_hookean"))
        tm, ths, thn = (t[k]["median_s"] * 1e3 for k in ("mass_tensor", "heml_stvk", "heml_neo_hookean"))
        table.append([r["mesh"], r["n_vertices"], r["n_tets"], f"{mt / 1e3:,.0f}", f"{hs / 1e3:,.0f}",
                      f"{mt / hs:.1f}", f"{s['mass_tensor']:,}", f"{s['heml']:,}", f"{s['gain']}",
                      f"{tm:.3f}", f"{ths:.3f}", f"{tm / ths:.1f}", f"{hn / 1e3:,.0f}", f"{thn:.3f}"])
    md = markdown_table(header, table)
    (RESULTS / "op_counts.md").write_text(md)
    print(md)
    plot(rows)


def plot(rows):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [r["mesh"] for r in rows]
    def gain(kind, field):
        return [r[kind]["mass_tensor"][("add_mul" if kind == "counts" else "median_s")]
                / r[kind][field][("add_mul" if kind == "counts" else "median_s")] for r in rows]

    series = [
        ([r["seed"]["gain"] for r in rows], "seed (2009): op-count gain"),
        (gain("counts", "heml_stvk"), "ours: op-count gain over HEML-StVK (same law)"),
        (gain("counts", "heml_neo_hookean"), "ours: op-count gain over HEML-Neo-Hookean"),
        (gain("times", "heml_stvk"), "ours: measured time gain over HEML-StVK (1 thread)"),
        (gain("times", "heml_neo_hookean"), "ours: measured time gain over HEML-Neo-Hookean"),
    ]
    xs = np.arange(len(rows))
    width = 0.17
    fig, ax = plt.subplots(figsize=(9, 4.8))
    for i, (vals, label) in enumerate(series):
        bars = ax.bar(xs + (i - 2) * width, vals, width, label=label)
        ax.bar_label(bars, fmt="%.0f", fontsize=7)
    ax.set_xticks(xs, [f"{n}\n{r['n_tets']} tets" for n, r in zip(names, rows)])
    ax.set_ylabel("mass-tensor cost / HEML cost")
    ax.set_yscale("log")
    ax.set_title("Cost of one force evaluation: mass-tensor over HEML")
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    IMAGES.mkdir(parents=True, exist_ok=True)
    fig.savefig(IMAGES / "op_counts.png", dpi=120)


if __name__ == "__main__":
    if parse_arguments(__doc__, {"--plot-only": "redraw the chart from the stored JSON"}).plot_only:
        plot(json.loads((RESULTS / "op_counts.json").read_text())["results"])
    else:
        main()
