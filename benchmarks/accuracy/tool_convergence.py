"""A capsule pressed into a slab, on meshes from coarse to fine: how far the default-size
mesh's contact force is from the finest.

A slab 60 x 30 x 8 mm (E 5 kPa, nu 0.45, on the frictionless plane z = 0, its end x = 0
fixed) under gravity; a rigid bar (a capsule of radius 8 mm, its axis along y) lowered
across its middle, 1 mm into it over 1 s, then held for 2 s; quasi_newton in 0.05 s steps,
tool_stiffness 100, the floor as stiff (contact_stiffness 1e6). For each mesh (hex cells
of 6 tets): the bar's force at the end (N) and its difference from the finest mesh's.

    python benchmarks/accuracy/tool_convergence.py    # docs/benchmarks/tool_convergence.{json,md}
"""

from __future__ import annotations

import time

import numpy as np

import heml_gym as hg
from heml_gym import materials as M
from heml_gym.benchmarks.common import generated_by, markdown_table, study_main
from heml_gym.control import rotation

MESHES = ((6, 3, 2), (12, 6, 4), (24, 12, 8), (36, 18, 12))
DEPTH, RADIUS, DT = 0.001, 0.008, 0.05


def press(cells) -> dict:
    mesh = hg.box_mesh((0.06, 0.03, 0.008), cells)
    model = hg.Model(mesh, M.NeoHookean(E=5e3, nu=0.45), density=950.0, damping=2.0,
                     fixed=np.flatnonzero(mesh.vertices[:, 0] == 0.0), supports=[hg.PlaneSupport(height=0.0)],
                     tools=[hg.Capsule(RADIUS, 0.03)])
    solver = hg.QuasiNewtonSolver(model, newton_tol=1e-5, contact_stiffness=1e6)
    state, control = model.state(), model.control()
    along_y = rotation(np.array([1.0, 0.0, 0.0]), np.pi / 2)
    t0, iterations = time.perf_counter(), 0
    for k in range(60):
        depth = DEPTH * min(k + 1, 20) / 20
        control.pose_tool(0, 0, (0.03, 0.015, 0.008 + RADIUS - depth), along_y)
        stats = solver.step(state, state, control, DT)
        if not stats.converged.all():
            raise RuntimeError(f"cells {cells}: {stats.messages[0]}")
        iterations += int(stats.newton_iterations[0])
    return {"cells": list(cells), "tets": int(mesh.n_tets), "force": stats.tool_force[0, 0].tolist(),
            "iterations_per_step": iterations / 60, "wall_s": time.perf_counter() - t0}


def report(data: dict) -> str:
    rows = data["rows"]
    finest = np.array(rows[-1]["force"])
    table = []
    for r in rows:
        f = np.array(r["force"])
        diff = np.linalg.norm(f - finest) / np.linalg.norm(finest)
        table.append([" x ".join(map(str, r["cells"])), f"{r['tets']:,}", f"{-f[2]:.4f}", f"{f[0]:.4f}",
                      f"{100 * diff:.1f} %", f"{r['iterations_per_step']:.0f}"])
    return "\n".join([f"{generated_by(data)}.\n",
                      "A slab 60 x 30 x 8 mm (E 5 kPa, nu 0.45) on the plane z = 0, its end x = 0 fixed; a bar "
                      f"of radius {RADIUS * 1e3:.0f} mm across its middle, lowered {DEPTH * 1e3:.0f} mm into it over "
                      "1 s and held 2 s (quasi_newton, 0.05 s steps, tool_stiffness 100). The bar's force at the end, "
                      "and its distance from the finest mesh's (the vector's, relative).\n",
                      markdown_table(["cells", "tets", "push down (N)", "push along x (N)", "from the finest",
                                      "L-BFGS iterations per step"], table)]) + "\n"


def main(argv=None):
    study_main("tool_convergence", __doc__, lambda: {"command": "python benchmarks/accuracy/tool_convergence.py",
                                                     "rows": [press(cells) for cells in MESHES]}, report, argv)


if __name__ == "__main__":
    main()
