"""Simulator speed: one implicit step on a tissue slab, explicit real-time factor on a kidney.

1. Implicit backward Euler at dt = 1/30 s on a LapGym-size slab (120 x 120 x 8 mm,
   512 vertices / 1350 tets, Neo-Hookean E = 27 kPa, nu = 0.43, rho = 1000 kg/m^3, one
   edge clamped, gravity): median wall time per step and Newton iterations for the
   default solver (PCG preconditioned by a lagged sparse Cholesky factor, Newton to 1e-3
   of the weight) and for variants (SuperLU preconditioner, direct SuperLU solves,
   tighter Newton tolerance, Newton capped at 1 iteration), each with its largest
   distance from a run solved to 1e-9 of the weight; and the time-discretisation error of
   dt = 1/30 s itself (against dt = 1/240 s), the scale those distances compare to.
2. Explicit symplectic Euler on a gmsh kidney (~600 vertices / 2400 tets, Neo-Hookean
   E = 5 kPa, nu = 0.45, lower fifth fixed, gravity): simulated seconds per wall second
   and tet-steps per second, at safety factors 0.5 (the default) and 0.9.

All on one Numba thread. Writes docs/benchmarks/simulation_speed.{json,md}.

    python benchmarks/speed/simulation_speed.py
"""

from __future__ import annotations

import os
import time

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core: BLAS too, not only Numba

import numba
import numpy as np
import heml_gym as hg
from heml_gym.benchmarks.common import parse_arguments, RESULTS, machine_info, markdown_table, write_json
from heml_gym import materials as M


DT = 1 / 30
STEPS = 60  # 2 s of simulated time
REPEATS = 3  # runs per implicit configuration, step times pooled


def slab_sim(linear_solver: str = "pcg", max_newton: int = 20, newton_tol: float = 1e-3,
             factorization: str = "cholesky") -> hg.Simulation:
    mesh = hg.box_mesh((0.12, 0.12, 0.008), (15, 15, 1))
    field = hg.HemlForce(mesh, M.NeoHookean(E=27e3, nu=0.43))
    fixed = np.flatnonzero(np.isclose(mesh.vertices[:, 0], 0.0))
    sim = hg.Simulation(field, 1000.0, fixed=fixed, integrator="implicit", linear_solver=linear_solver,
                        max_newton=max_newton, newton_tol=newton_tol)
    if linear_solver == "pcg":
        sim.solver.pcg[0].factorization = factorization
    return sim


def slab_trajectory(sim: hg.Simulation, dt: float = DT, steps: int = STEPS):
    """Run ``steps`` steps from rest: ``(positions (steps, n, 3) m, step times s, Newton its)``."""
    sim.step(dt)  # compile
    sim.reset()
    times, iterations, positions = [], [], []
    for _ in range(steps):
        t = time.perf_counter()
        stats = sim.step(dt)
        times.append(time.perf_counter() - t)
        iterations.append(stats.newton_iterations)
        positions.append(sim.x.copy())
    return np.array(positions), np.array(times), np.array(iterations)


def implicit_slab(label: str, reference: np.ndarray, repeats: int = REPEATS, **options) -> dict:
    """Time 60 implicit steps of 1/30 s of the slab sagging under gravity from rest, run
    ``repeats`` times from a fresh simulator (the step times of all runs pooled: the machine
    is shared and its load drifts).

    ``reference``: the positions of a run solved to 1e-9 of the weight, per step; the
    largest vertex distance from it (m) over the run is what the solver's shortcuts cost.
    """
    sims = [slab_sim(**options) for _ in range(repeats)]
    runs = [slab_trajectory(sim) for sim in sims]
    sim = sims[-1]
    positions, _, iterations = runs[-1]
    times = np.concatenate([run[1] for run in runs])
    sag = float(-(positions[:, :, 2] - sim.mesh.vertices[None, :, 2]).min())
    pcg = sim.linear_solver == "pcg"
    return {
        "label": label, "linear_solver": sim.linear_solver,
        "preconditioner": sim.solver.pcg[0].factorization if pcg else None, "newton_tol": sim.newton_tol,
        "max_newton": sim.max_newton, "n_vertices": sim.mesh.n_vertices,
        "n_tets": sim.mesh.n_tets, "median_step_ms": 1e3 * float(np.median(times)),
        "run_median_step_ms": [1e3 * float(np.median(run[1])) for run in runs],
        "p90_step_ms": 1e3 * float(np.percentile(times, 90)),
        "mean_newton_iterations": float(np.mean(iterations)),
        "factorizations": sim.solver.pcg[0].factorizations if pcg else int(np.sum(iterations)),
        "largest_sag_m": sag,
        "max_deviation_m": float(np.linalg.norm(positions - reference, axis=2).max()),
    }


def time_discretisation_error(reference: np.ndarray, refine: int = 8) -> float:
    """Largest vertex distance (m) of the tightly solved dt = 1/30 s run from one at dt/refine."""
    fine, _, _ = slab_trajectory(slab_sim(newton_tol=1e-9), DT / refine, STEPS * refine)
    return float(np.linalg.norm(reference - fine[refine - 1::refine], axis=2).max())


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
    reference, _, _ = slab_trajectory(slab_sim(newton_tol=1e-9))
    variants = {
        "default": {},
        "SuperLU preconditioner": {"factorization": "lu"},
        "Newton to 1e-6 of the weight": {"newton_tol": 1e-6},
        "direct SuperLU solves": {"linear_solver": "direct"},
        "one Newton iteration": {"max_newton": 1},
    }
    implicit = [implicit_slab(label, reference, **options) for label, options in variants.items()]
    discretisation = time_discretisation_error(reference)
    explicit = [explicit_kidney(s) for s in (0.5, 0.9)]
    write_json("simulation_speed.json", {"machine": machine_info(), "implicit_slab": implicit,
                                         "time_discretisation_error_m": discretisation,
                                         "explicit_kidney": explicit})
    slab = implicit[0]
    md = (f"Implicit step, dt = 1/30 s, LapGym-size slab ({slab['n_vertices']} vertices, {slab['n_tets']} "
          "tets) sagging under gravity from rest, 60 steps, one thread; each configuration run 3 times from a fresh "
          "simulator, the median over all 180 steps and each run's median. Deviation: the largest distance "
          "of any vertex over the 60 steps from a run solved to 1e-9 of the weight. For scale: the slab "
          f"sags {1e3 * slab['largest_sag_m']:.0f} mm, and dt = 1/30 s itself is "
          f"{1e3 * discretisation:.0f} mm away from dt = 1/240 s (backward Euler's numerical damping).\n\n"
          ) + markdown_table(
        ["solver", "linear solve", "preconditioner", "Newton tol (x weight)", "max Newton", "median ms/step",
         "median of each run", "p90 ms/step", "Newton its/step", "factorisations (60 steps)", "deviation (mm)"],
        [[r["label"], r["linear_solver"], r["preconditioner"] or "-", f"{r['newton_tol']:g}", r["max_newton"],
          f"{r['median_step_ms']:.1f}", " / ".join(f"{t:.1f}" for t in r["run_median_step_ms"]),
          f"{r['p90_step_ms']:.1f}", f"{r['mean_newton_iterations']:.1f}",
          r["factorizations"], f"{1e3 * r['max_deviation_m']:.3f}"] for r in implicit])
    md += "\nExplicit, kidney, E = 5 kPa (one thread):\n\n" + markdown_table(
        ["safety", "vertices", "tets", "critical dt (ms)", "sub-steps per s", "real-time factor", "M tet-steps/s"],
        [[r["safety"], r["n_vertices"], r["n_tets"], f"{r['critical_dt_ms']:.3f}", r["substeps"],
          f"{r['real_time_factor']:.2f}", f"{r['tet_steps_per_s'] / 1e6:.1f}"] for r in explicit])
    (RESULTS / "simulation_speed.md").write_text(md)
    print(md)


if __name__ == "__main__":
    parse_arguments(__doc__)
    main()
