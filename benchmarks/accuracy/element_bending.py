"""Bending on coarse meshes: linear (4-node) vs quadratic (10-node) tetrahedra.

The cantilever of benchmarks/accuracy/speed_accuracy.py (100 x 20 x 20 mm, E 50 kPa, nu
0.45, 1000 kg/m^3, clamped at x = 0, sagging under gravity) solved to static
equilibrium on n x n/5 x n/5 cubic cells (6 tets per cell) with linear tets (F-FEM,
``heml_gym.FemForce``) and with quadratic tets (``heml_gym.forces.quadratic``) on the
same cells, by the same Newton (speed_accuracy's ``newton_equilibrium``, load ramped in
8 steps from the straight beam). Truth: the mesh-converged tip deflection that
speed_accuracy extrapolated from linear tets on 50-80 cells (stored in
docs/benchmarks/speed_accuracy_reference.json, with its uncertainty); the quadratic
ladder's own extrapolation is an independent check of it.

Tip deflection: the mean z-displacement of the mesh vertices on the x = L face (for
quadratic tets, of the corner nodes: the same material points). Wall time: one thread,
assembly and factorisation included, Numba compilation excluded (a warm-up solve first).

Writes docs/benchmarks/element_bending.{json,md} and docs/img/element_bending.png.

    python benchmarks/accuracy/element_bending.py [--note TEXT] [--from-json]     # ~2 min on one core
"""

from __future__ import annotations

import argparse
import json
import time

import numba
import numpy as np
from tqdm import tqdm

import heml_gym as hg
from heml_gym.benchmarks.accuracy.speed_accuracy import (GRAVITY, HEIGHT, LAWS, LENGTH, RHO, WIDTH, E, NU, cells,
                                                         fit_power, newton_equilibrium)
from heml_gym.benchmarks.common import IMAGES, RESULTS, machine_info, markdown_table, store_and_report
from heml_gym.forces.quadratic import QuadraticFemForce, QuadraticTetMesh

LAW = "Neo-Hookean"
#: cells along the length (the other two axes get a fifth of it)
LINEAR_LEVELS = (5, 10, 20, 30, 40)
QUADRATIC_LEVELS = (5, 10, 15, 20)
LOAD_STEPS = 8


def solve(n: int, element: str) -> dict:
    """Static equilibrium of the cantilever on ``n`` cells with ``element`` tets."""
    linear = hg.box_mesh((LENGTH, WIDTH, HEIGHT), cells(n))
    if element == "linear":
        field, rest = hg.FemForce(linear, LAWS[LAW]()), linear.vertices
        load = (RHO * linear.vertex_volumes[:, None] * GRAVITY).ravel()
    else:
        mesh = QuadraticTetMesh.from_linear(linear)
        field, rest = QuadraticFemForce(mesh, LAWS[LAW]()), mesh.vertices
        load = (RHO * mesh.load_volumes[:, None] * GRAVITY).ravel()  # consistent body force
    free = rest[:, 0] > 1e-12 * LENGTH
    tip = np.flatnonzero(linear.vertices[:, 0] > LENGTH * (1 - 1e-12))  # corner nodes keep their indices
    tol = 1e-9 * RHO * LENGTH * WIDTH * HEIGHT * abs(GRAVITY[2])
    t0 = time.perf_counter()
    x, iterations = rest.copy(), 0
    for k in range(1, LOAD_STEPS + 1):
        x, its, residual = newton_equilibrium(field, x, free, load * k / LOAD_STEPS, tol)
        iterations += its
    wall = time.perf_counter() - t0
    return {"element": element, "n": n, "cells": list(cells(n)), "n_elements": linear.n_tets,
            "n_nodes": len(rest), "dofs": 3 * int(free.sum()),
            "tip_z": float(np.mean(x[tip, 2] - rest[tip, 2])), "newton_iterations": iterations,
            "residual_N": residual, "wall_s": wall}


def measure(note: str | None = None) -> dict:
    numba.set_num_threads(1)
    reference = json.loads((RESULTS / "speed_accuracy_reference.json").read_text())
    truth = reference["static"][LAW]
    solve(5, "quadratic")  # compile
    solve(5, "linear")
    rows = []
    runs = [("linear", n) for n in LINEAR_LEVELS] + [("quadratic", n) for n in QUADRATIC_LEVELS]
    for element, n in tqdm(runs, desc="cantilever", unit="solve"):
        row = solve(n, element)
        row["error"] = row["tip_z"] / truth["tip_z"] - 1.0
        rows.append(row)
    quadratic = [r for r in rows if r["element"] == "quadratic"]
    v0, _, p = fit_power([r["n"] for r in quadratic[-3:]], [r["tip_z"] for r in quadratic[-3:]])
    return {"machine": machine_info(), "law": LAW, "E_Pa": E, "nu": NU, "density": RHO,
            "size_m": [LENGTH, WIDTH, HEIGHT], "load_steps": LOAD_STEPS,
            "truth": {"tip_z": truth["tip_z"], "uncertainty_m": truth["uncertainty_m"],
                      "from": "docs/benchmarks/speed_accuracy_reference.json (linear tets on 50-80 cells, "
                              "extrapolated)"},
            "quadratic_extrapolated": {"tip_z": v0, "order_p": p, "levels": [r["n"] for r in quadratic[-3:]]},
            "results": rows, **({"note": note} if note else {})}


def chart(data: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for element, color in (("linear", "C0"), ("quadratic", "C1")):
        rs = [r for r in data["results"] if r["element"] == element]
        err = [100 * abs(r["error"]) for r in rs]
        axes[0].loglog([r["n_nodes"] for r in rs], err, "o-", color=color, label=f"{element} tets")
        axes[1].loglog([r["wall_s"] for r in rs], err, "o-", color=color, label=f"{element} tets")
        for r, e in zip(rs, err):
            axes[0].annotate(f"{r['n']}", (r["n_nodes"], e), textcoords="offset points", xytext=(4, 4), fontsize=8)
    unc = 100 * data["truth"]["uncertainty_m"] / abs(data["truth"]["tip_z"])
    for ax in axes:
        ax.axhline(unc, color="grey", ls=":", label="truth's uncertainty")
        ax.set_ylabel("tip deflection error (%)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    axes[0].set_xlabel("nodes (labels: cells along the length)")
    axes[1].set_xlabel("wall time to equilibrium, one thread (s)")
    fig.suptitle("Cantilever under gravity: linear vs quadratic tets on the same cells")
    fig.tight_layout()
    IMAGES.mkdir(parents=True, exist_ok=True)
    fig.savefig(IMAGES / "element_bending.png", dpi=110)
    plt.close(fig)


def report(data: dict) -> str:
    m, t = data["machine"], data["truth"]
    chart(data)
    head = (f"Generated by `benchmarks/accuracy/element_bending.py` on {m['cpu']} ({m['vector_isa']}, one thread), "
            f"{m['date']}. The speed_accuracy cantilever ({data['law']}, E {data['E_Pa'] / 1e3:g} kPa, nu {data['nu']}) "
            f"at static equilibrium; truth: tip deflection {1e3 * t['tip_z']:.2f} mm ± {1e3 * t['uncertainty_m']:.2f} mm, "
            f"from {t['from']}. Method: the script's docstring." + (f" {data['note']}" if data.get("note") else "")
            + "\n\n")
    rows = [[f"{r['element']}", "x".join(str(c) for c in r["cells"]), f"{r['n_nodes']:,}", f"{1e3 * r['tip_z']:.2f}",
             f"{100 * r['error']:+.1f} %", r["newton_iterations"], f"{r['wall_s']:.2f}"] for r in data["results"]]
    q = data["quadratic_extrapolated"]
    lin = {r["n"]: r for r in data["results"] if r["element"] == "linear"}
    quad = {r["n"]: r for r in data["results"] if r["element"] == "quadratic"}
    summary = (f"\nQuadratic tets extrapolated from {', '.join(map(str, q['levels']))} cells: "
               f"{1e3 * q['tip_z']:.2f} mm ({100 * (q['tip_z'] / t['tip_z'] - 1):+.1f} % from the linear tets' "
               f"extrapolation). On the same 5 x 1 x 1 cells quadratic tets are {100 * quad[5]['error']:+.1f} % off, "
               f"linear ones {100 * lin[5]['error']:+.1f} %; quadratic tets on 10 x 2 x 2 cells "
               f"({quad[10]['n_nodes']:,} nodes, {100 * quad[10]['error']:+.1f} %) are "
               f"{'closer than' if abs(quad[10]['error']) < abs(lin[40]['error']) else 'farther off than'} linear "
               f"tets on 40 x 8 x 8 ({lin[40]['n_nodes']:,} nodes, {100 * lin[40]['error']:+.1f} %).\n")
    chart_md = "\n![tip deflection error vs nodes and vs wall time](../img/element_bending.png)\n"
    return head + markdown_table(["tets", "cells", "nodes", "tip deflection (mm)", "error", "Newton its",
                                  "wall s"], rows) + summary + chart_md


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--from-json", action="store_true", help="rewrite the table and chart from the stored JSON")
    ap.add_argument("--note", help="a sentence stored with the result (e.g. what else ran on the machine)")
    args = ap.parse_args(argv)
    store_and_report("element_bending", None if args.from_json else measure(args.note), report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
