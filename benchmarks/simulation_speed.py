"""Simulator speed: one implicit step on a tissue slab, explicit real-time factor on a kidney.

1. Implicit backward Euler at dt = 1/30 s on a LapGym-size slab (120 x 120 x 8 mm,
   512 vertices / 1350 tets, Neo-Hookean E = 27 kPa, nu = 0.43, rho = 1000 kg/m^3, one
   edge clamped, gravity): median wall time per step, Newton iterations, for both linear
   solvers, and with the Newton iterations capped at 2 and 1 per step (with the distance
   of the capped runs from the full-Newton one).
2. Explicit symplectic Euler on a gmsh kidney (~600 vertices / 2400 tets, Neo-Hookean
   E = 5 kPa, nu = 0.45, lower fifth fixed, gravity): simulated seconds per wall second
   and tet-steps per second, at safety factors 0.5 (the default) and 0.9.

All on one Numba thread. Writes docs/benchmarks/simulation_speed.{json,md}.

    python benchmarks/simulation_speed.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import heml_gym as hg  # noqa: E402
from common import RESULTS, machine_info, markdown_table, write_json  # noqa: E402
from heml_gym import materials as M  # noqa: E402


def slab_sim(linear_solver: str, max_newton: int = 20) -> hg.Simulation:
    mesh = hg.box_mesh((0.12, 0.12, 0.008), (15, 15, 1))
    field = hg.HemlForce(mesh, M.NeoHookean(E=27e3, nu=0.43))
    fixed = np.flatnonzero(np.isclose(mesh.vertices[:, 0], 0.0))
    return hg.Simulation(field, 1000.0, fixed=fixed, integrator="implicit", linear_solver=linear_solver,
                         max_newton=max_newton)


def implicit_slab(linear_solver: str, max_newton: int = 20, steps: int = 60, reference=None) -> dict:
    """Time ``steps`` implicit steps of 1/30 s of the slab sagging under gravity from rest.

    With ``reference`` (the positions of a full-Newton run, per step) the largest vertex
    distance from it (m) over the run measures what capping the Newton iterations costs.
    """
    sim = slab_sim(linear_solver, max_newton)
    sim.step(1 / 30)  # compile
    sim.reset()
    times, iterations, positions = [], [], []
    for _ in range(steps):
        t = time.perf_counter()
        stats = sim.step(1 / 30)
        times.append(time.perf_counter() - t)
        iterations.append(stats.newton_iterations)
        positions.append(sim.x.copy())
    positions = np.array(positions)
    sag = float(-(positions[:, :, 2] - sim.mesh.vertices[None, :, 2]).min())
    return {
        "linear_solver": linear_solver, "max_newton": max_newton, "n_vertices": sim.mesh.n_vertices,
        "n_tets": sim.mesh.n_tets, "median_step_ms": 1e3 * float(np.median(times)),
        "p90_step_ms": 1e3 * float(np.percentile(times, 90)),
        "mean_newton_iterations": float(np.mean(iterations)),
        "factorizations": sim._pcg.factorizations if linear_solver == "pcg" else int(np.sum(iterations)),
        "largest_sag_m": sag,
        "max_deviation_m": (None if reference is None
                            else float(np.linalg.norm(positions - reference, axis=2).max())),
        "positions": positions,
    }


def explicit_kidney(safety: float, seconds: float = 1.0) -> dict:
    mesh = hg.organs.kidney_mesh()
    field = hg.HemlForce(mesh, M.NeoHookean(E=5e3, nu=0.45))
    z = mesh.vertices[:, 2]
    fixed = np.flatnonzero(z < z.min() + 0.2 * np.ptp(z))
    sim = hg.Simulation(field, 1000.0, fixed=fixed, integrator="explicit", safety=safety, damping=1.0)
    sim.step(1 / 30)
    sim.reset()
    frames = int(round(seconds * 30))
    substeps = 0
    t = time.perf_counter()
    for _ in range(frames):
        substeps += sim.step(1 / 30).substeps
    wall = time.perf_counter() - t
    return {
        "safety": safety, "n_vertices": mesh.n_vertices, "n_tets": mesh.n_tets,
        "critical_dt_ms": 1e3 * sim.critical_dt(), "substeps": substeps, "wall_s": wall,
        "real_time_factor": sim.time / wall, "tet_steps_per_s": mesh.n_tets * substeps / wall,
    }


def main():
    numba.set_num_threads(1)
    full = implicit_slab("pcg")
    implicit = [full, implicit_slab("direct", reference=full["positions"])]
    implicit += [implicit_slab("pcg", n, reference=full["positions"]) for n in (2, 1)]
    full["max_deviation_m"] = 0.0
    for r in implicit:
        del r["positions"]
    explicit = [explicit_kidney(s) for s in (0.5, 0.9)]
    write_json("simulation_speed.json", {"machine": machine_info(), "implicit_slab": implicit,
                                         "explicit_kidney": explicit})
    md = ("Implicit step, dt = 1/30 s, LapGym-size slab sagging under gravity from rest, 60 steps (one "
          "thread). `max_newton` caps the Newton iterations per step (1: one line-searched Newton step "
          "on the incremental potential, the linearly implicit Euler of interactive simulators); the "
          "deviation is the largest distance of any vertex from the full-Newton run over the 60 steps, "
          "against the largest sag:\n\n") + markdown_table(
        ["linear solver", "max_newton", "vertices", "tets", "median ms/step", "p90 ms/step", "Newton its/step",
         "factorisations", "largest sag (mm)", "deviation from full Newton (mm)"],
        [[r["linear_solver"], r["max_newton"], r["n_vertices"], r["n_tets"], f"{r['median_step_ms']:.1f}",
          f"{r['p90_step_ms']:.1f}", f"{r['mean_newton_iterations']:.1f}", r["factorizations"],
          f"{1e3 * r['largest_sag_m']:.1f}", f"{1e3 * r['max_deviation_m']:.3f}"] for r in implicit])
    md += "\nExplicit, kidney, E = 5 kPa (one thread):\n\n" + markdown_table(
        ["safety", "vertices", "tets", "critical dt (ms)", "sub-steps per s", "real-time factor", "M tet-steps/s"],
        [[r["safety"], r["n_vertices"], r["n_tets"], f"{r['critical_dt_ms']:.3f}", r["substeps"],
          f"{r['real_time_factor']:.2f}", f"{r['tet_steps_per_s'] / 1e6:.1f}"] for r in explicit])
    (RESULTS / "simulation_speed.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
