"""Speed vs accuracy on a gravity-loaded cantilever, over force field, mesh, integrator and step.

Scene: box 0.10 x 0.02 x 0.02 m (``box_mesh`` with ``(n, n/5, n/5)`` cubic cells, 6 tets
each), every vertex with x = 0 fixed, gravity (0, 0, -9.81) m/s^2, rho = 1000 kg/m^3,
E = 50 kPa, nu = 0.45. The measured output is the tip deflection: the mean z-displacement
of the vertices on the x = L face.

* Static: error of the equilibrium tip deflection (``Simulation.solve_static``) against a
  mesh-converged reference, vs wall time to equilibrium.
* Dynamic: released straight and at rest, no damping, 1 s: RMS over time of the tip-z
  difference to a converged reference trajectory, relative to the reference's peak
  deflection, vs wall time per simulated second.

References (same law, HEML forces, which are the P1 energy shared by HEML, F-FEM and
mass-tensor): Newton equilibria and small-step explicit runs on a ladder of refinements,
extrapolated to zero mesh size (Richardson); see ``compute_reference`` and
docs/studies/speed_accuracy.md. The reference is cached in
docs/benchmarks/speed_accuracy_reference.json and reused while its settings match.

    python benchmarks/accuracy/speed_accuracy.py [--quick] [--stage all|reference|sweep|report]
                                        [--cap-s 45] [--recompute-reference]

Writes docs/benchmarks/speed_accuracy.json and .md, docs/img/speed_accuracy_*.png
(``--quick``: a small smoke run written under /tmp/speed_accuracy_quick/).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import scipy.sparse.linalg as spla
from scipy.interpolate import RegularGridInterpolator
from tqdm import tqdm
import heml_gym as hg
from heml_gym.benchmarks.common import IMAGES, RESULTS, machine_info, markdown_table, write_json
from heml_gym import materials as M
from heml_gym.mesh import signed_volumes

# ----------------------------------------------------------------------------- scene
LENGTH, WIDTH, HEIGHT = 0.10, 0.02, 0.02  # m
RHO = 1000.0  # kg/m^3
GRAVITY = np.array([0.0, 0.0, -9.81])  # m/s^2
E, NU = 50e3, 0.45  # Pa, -
DURATION = 1.0  # s simulated in the dynamic runs
REF_RATE = 960  # Hz: the reference trajectories are stored at 1/960 s

LAWS = {
    "Neo-Hookean": lambda: M.NeoHookean(E=E, nu=NU),
    "StVK": lambda: M.StVenantKirchhoff(E=E, nu=NU),
    "Mooney-Rivlin": lambda: M.MooneyRivlin(E=E, nu=NU),
    # the law of NVIDIA Newton's tet FEM, for benchmarks/accuracy/peers.py
    "Stable Neo-Hookean": lambda: M.StableNeoHookean(E=E, nu=NU),
}
FIELDS = {
    "HEML": hg.HemlForce,
    "F-FEM": hg.FemForce,
    "Mass-tensor": hg.MassTensorForce,  # StVK only
    "Mass-spring": hg.MassSpringForce,  # uses E only: one run serves every law
}
FIELD_COLORS = {"HEML": "C0", "F-FEM": "C1", "Mass-tensor": "C2", "Mass-spring": "C3",
                "Newton semi-implicit": "C4", "Newton VBD": "C5", "MuJoCo flex": "C6"}


def full_config() -> dict:
    return {
        "meshes": [10, 20, 30, 40],
        "static_laws": ["Neo-Hookean", "StVK", "Mooney-Rivlin"],
        "dynamic_laws": ["Neo-Hookean", "StVK"],
        "explicit_safety": [0.5, 0.9],
        "implicit_dt": [1 / 30, 1 / 60, 1 / 120, 1 / 240],
        "explicit_frame": 1 / 240,
        "duration": DURATION,
        # tried in turn until one converges; failed attempts count in the cost
        "static_load_steps": [1, 2, 4, 8, 16],
        # reference ladders (cells along x; the extra finest level validates the extrapolation)
        "ref_static": {"Neo-Hookean": [20, 30, 40, 50, 60, 80], "StVK": [20, 30, 40, 50, 60],
                       "Mooney-Rivlin": [20, 30, 40, 50, 60], "Stable Neo-Hookean": [20, 30, 40, 50, 60]},
        "ref_dynamic": {"Neo-Hookean": [30, 40, 60, 80], "StVK": [30, 40, 60],
                        "Stable Neo-Hookean": [30, 40, 60]},
        "ref_safety": 0.5,
        "ref_time_check": 0.25,  # the coarsest dynamic level is also run at this safety
    }


def quick_config() -> dict:
    return {
        "meshes": [5, 10],
        "static_laws": ["Neo-Hookean", "StVK"],
        "dynamic_laws": ["Neo-Hookean", "StVK"],
        "explicit_safety": [0.5],
        "implicit_dt": [1 / 30, 1 / 60],
        "explicit_frame": 1 / 240,
        "duration": 0.5,
        "static_load_steps": [1, 2, 4, 8, 16],
        "ref_static": {k: [10, 15, 20] for k in LAWS},
        "ref_dynamic": {k: [10, 15, 20] for k in LAWS},
        "ref_safety": 0.5,
        "ref_time_check": 0.25,
    }


def cells(n: int) -> tuple[int, int, int]:
    if n % 5:
        raise ValueError(f"cells along x must be a multiple of 5 (cubic cells), got {n}")
    return (n, n // 5, n // 5)


class Cantilever:
    """Mesh, clamped vertices and tip face of the cantilever with ``n`` cells along x."""

    def __init__(self, n: int):
        self.n = n
        self.cells = cells(n)
        self.mesh = hg.box_mesh((LENGTH, WIDTH, HEIGHT), self.cells)
        x = self.mesh.vertices[:, 0]
        self.fixed = np.flatnonzero(x < 1e-12 * LENGTH)
        self.tip = np.flatnonzero(x > LENGTH * (1 - 1e-12))
        self.free = np.ones(self.mesh.n_vertices, dtype=bool)
        self.free[self.fixed] = False
        self._volumes = self.mesh.volumes

    def tip_z(self, x) -> float:
        """Mean z-displacement (m) of the x = L face."""
        return float(np.mean(x[self.tip, 2] - self.mesh.vertices[self.tip, 2]))

    def min_j(self, x) -> float:
        """Smallest volume ratio J = V / V0 over the tets (J <= 0: an inverted element)."""
        return float(np.min(signed_volumes(x, self.mesh.tets) / self._volumes))

    def grid_axes(self):
        return [np.linspace(0.0, s, c + 1) for s, c in zip((LENGTH, WIDTH, HEIGHT), self.cells)]

    def displacement_interpolator(self, x):
        """Trilinear interpolant of the displacement ``x - X`` over the structured grid."""
        axes = self.grid_axes()
        u = (x - self.mesh.vertices).reshape(len(axes[0]), len(axes[1]), len(axes[2]), 3)
        return RegularGridInterpolator(axes, u)

    def simulation(self, field, **kw) -> hg.Simulation:
        return hg.Simulation(field, RHO, gravity=GRAVITY, fixed=self.fixed, damping=None, **kw)


# ------------------------------------------------------------------------ reference
def newton_equilibrium(field, x, free, load, tol, max_iter=60):
    """Static equilibrium by Newton from ``x`` (reference solver, not the one benchmarked).

    Same potential as ``Simulation.solve_static`` (elastic energy minus load work), exact
    Hessian with the projected one as fallback, backtracking line search; the sparse
    factorisation uses the minimum-degree ordering on A^T + A, about twice as fast as
    scipy's default COLAMD on these matrices. Returns ``(x, iterations, residual N)``.
    """
    fr = np.repeat(free, 3)

    def potential(y):
        return field.energy(y) - float(load @ y.ravel())

    def gradient(y):
        return -field.forces(y).ravel() - load

    g = gradient(x)
    it = 0
    while True:
        gnorm = float(np.linalg.norm(g[fr]))
        if gnorm < tol or it >= max_iter:
            break
        it += 1
        for project in (False, True):
            a = field.hessian(x, project=project)[fr][:, fr].tocsc()
            dx = spla.splu(a, permc_spec="MMD_AT_PLUS_A").solve(-g[fr])
            slope = float(g[fr] @ dx)
            if np.all(np.isfinite(dx)) and slope < 0:
                break
        phi0, step = potential(x), 1.0
        while True:
            y = x.copy()
            y.reshape(-1)[fr] += step * dx
            phi = potential(y)
            if np.isfinite(phi):
                if phi <= phi0 + 1e-4 * step * slope:
                    break
                gy = gradient(y)
                if np.linalg.norm(gy[fr]) < gnorm:
                    break
            step *= 0.5
            if step < 1e-12:
                raise RuntimeError("reference Newton: line search failed")
        x = y
        g = gradient(x)
    if gnorm >= tol:
        raise RuntimeError(f"reference Newton did not converge: residual {gnorm:.3e} N")
    return x, it, gnorm


def static_ladder(law: str, levels, progress) -> list[dict]:
    """Equilibrium tip deflection on each refinement level (finer levels start from the coarser one)."""
    out, guess = [], None
    for n in levels:
        cant = Cantilever(n)
        field = hg.HemlForce(cant.mesh, LAWS[law]())
        mass = RHO * cant.mesh.vertex_volumes
        load = (mass[:, None] * GRAVITY).ravel()
        tol = 1e-9 * float(np.abs(load).sum())
        t0 = time.perf_counter()
        its = 0
        if guess is None:  # load ramp from the straight beam
            x = cant.mesh.vertices.copy()
            for k in range(1, 9):
                x, it, res = newton_equilibrium(field, x, cant.free, load * k / 8, tol)
                its += it
        else:
            x = cant.mesh.vertices + guess(cant.mesh.vertices)
            x[cant.fixed] = cant.mesh.vertices[cant.fixed]
            x, its, res = newton_equilibrium(field, x, cant.free, load, tol)
        out.append({"n": n, "cells": cant.cells, "n_tets": cant.mesh.n_tets, "tip_z": cant.tip_z(x),
                    "newton_iterations": its, "residual_N": res, "wall_s": time.perf_counter() - t0})
        guess = cant.displacement_interpolator(x)
        progress.update(1)
    return out


def fit_power(ns, values, p=None):
    """Fit ``v(n) = v0 + c n^-p`` (free ``p`` with three or more levels). Returns ``(v0, c, p)``."""
    n = np.asarray(ns, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    if p is not None:
        a = np.stack([np.ones_like(n), n ** -p], axis=1)
        v0, c = np.linalg.lstsq(a, v, rcond=None)[0]
        return float(v0), float(c), float(p)
    from scipy.optimize import least_squares

    v0, c, p = least_squares(lambda q: q[0] + q[1] * n ** -q[2] - v, [v[-1], (v[0] - v[-1]) * n[0] ** 2, 2.0]).x
    return float(v0), float(c), float(p)


def extrapolate_static(ladder: list[dict]) -> dict:
    """Richardson-type extrapolation of the tip deflection to zero mesh size, with its uncertainty.

    Estimate: ``v0 + c n^-p`` fitted (free ``p``) through the three finest levels.
    Uncertainty: the largest deviation from two alternatives, the same fit one level
    coarser and the two finest levels with the asymptotic P1 order ``p = 2``.
    """
    ns = [r["n"] for r in ladder]
    vs = [r["tip_z"] for r in ladder]
    v0, c, p = fit_power(ns[-3:], vs[-3:])
    alt_coarser = fit_power(ns[-4:-1], vs[-4:-1])[0] if len(ns) >= 4 else v0
    alt_p2 = fit_power(ns[-2:], vs[-2:], p=2.0)[0]
    unc = max(abs(v0 - alt_coarser), abs(v0 - alt_p2))
    return {"tip_z": v0, "order_p": p, "coefficient": c, "uncertainty_m": unc,
            "relative_uncertainty": unc / abs(v0), "fit_levels": ns[-3:],
            "alt_fit_one_coarser": alt_coarser, "alt_richardson_p2": alt_p2,
            "finest_level_error": abs(vs[-1] - v0) / abs(v0)}


def explicit_trajectory(law: str, n: int, safety: float, duration: float) -> tuple[np.ndarray, float]:
    """Tip z (m) at 1/REF_RATE s intervals (first entry t = 0), HEML explicit at ``safety``."""
    cant = Cantilever(n)
    sim = cant.simulation(hg.HemlForce(cant.mesh, LAWS[law]()), integrator="explicit", safety=safety)
    sim.critical_dt()
    frames = round(duration * REF_RATE)
    z = np.zeros(frames + 1)
    t0 = time.perf_counter()
    for k in range(frames):
        sim.step(1.0 / REF_RATE)
        z[k + 1] = cant.tip_z(sim.x)
    return z, time.perf_counter() - t0


def richardson(z_coarse, z_fine, n_coarse, n_fine, p):
    return z_fine + (z_fine - z_coarse) / ((n_fine / n_coarse) ** p - 1.0)


def rms_rel(a, b, amplitude):
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)) / amplitude)


def dynamic_reference(law: str, levels, p: float, cfg: dict, progress) -> dict:
    """Pointwise-in-time Richardson extrapolation of small-step explicit runs on a mesh ladder.

    The two finest levels are extrapolated with the order ``p`` fitted to the static
    deflection of the same law. Reported alongside: the time-step check (coarsest level at
    a smaller safety), the size of the extrapolation correction, and the uncertainty,
    taken as the RMS difference between the extrapolations from the two finest and from
    the next pair down (a pessimistic bound: the coarser pair is less accurate).
    """
    duration = cfg["duration"]
    runs = {}
    walls = {}
    for n in levels:
        runs[n], walls[n] = explicit_trajectory(law, n, cfg["ref_safety"], duration)
        progress.update(1)
    check, _ = explicit_trajectory(law, levels[0], cfg["ref_time_check"], duration)
    progress.update(1)
    nf, nc = levels[-1], levels[-2]
    z_ref = richardson(runs[nc], runs[nf], nc, nf, p)
    amp = float(np.max(np.abs(z_ref)))
    alt = richardson(runs[levels[-3]], runs[nc], levels[-3], nc, p) if len(levels) >= 3 else runs[nf]
    alt_p2 = richardson(runs[nc], runs[nf], nc, nf, 2.0)
    return {
        "levels": levels, "order_p": p, "rate_hz": REF_RATE, "duration_s": duration,
        "tip_z": z_ref.tolist(), "amplitude_m": amp,
        "level_tip_z": {str(n): runs[n].tolist() for n in levels},
        "level_wall_s": {str(n): walls[n] for n in levels},
        "level_error_rel": {str(n): rms_rel(runs[n], z_ref, amp) for n in levels},
        "time_step_error_rel": rms_rel(check, runs[levels[0]], amp),
        "time_step_check": {"n": levels[0], "safety": [cfg["ref_time_check"], cfg["ref_safety"]]},
        "correction_rel": rms_rel(z_ref, runs[nf], amp),
        "alt_pair_rel": rms_rel(z_ref, alt, amp),
        "alt_p2_rel": rms_rel(z_ref, alt_p2, amp),
        "uncertainty_rel": max(rms_rel(z_ref, alt, amp), rms_rel(z_ref, alt_p2, amp)),
    }


def compute_reference(cfg: dict, laws_static, laws_dynamic, ref: dict | None = None) -> dict:
    """Static ladders for ``laws_static`` and dynamic references for ``laws_dynamic`` that
    ``ref`` does not hold yet (a dynamic reference needs its law's static fit for ``p``)."""
    if ref is None:
        ref = {"settings": reference_settings(cfg), "static": {}, "dynamic": {}, "wall_s": {}}
    need_static = [law for law in dict.fromkeys([*laws_static, *laws_dynamic]) if law not in ref["static"]]
    need_dynamic = [law for law in laws_dynamic if law not in ref["dynamic"]]
    total = sum(len(cfg["ref_static"][law]) for law in need_static)
    total += sum(len(cfg["ref_dynamic"][law]) + 1 for law in need_dynamic)
    with tqdm(total=total, desc="reference", unit="run") as bar:
        for law in need_static:
            t0 = time.perf_counter()
            ladder = static_ladder(law, cfg["ref_static"][law], bar)
            ref["static"][law] = {"ladder": ladder, **extrapolate_static(ladder)}
            ref["wall_s"][f"static {law}"] = time.perf_counter() - t0
        for law in need_dynamic:
            t0 = time.perf_counter()
            p = ref["static"][law]["order_p"]
            ref["dynamic"][law] = dynamic_reference(law, cfg["ref_dynamic"][law], p, cfg, bar)
            ref["wall_s"][f"dynamic {law}"] = time.perf_counter() - t0
    return ref


def reference_settings(cfg: dict) -> dict:
    return {"length": LENGTH, "width": WIDTH, "height": HEIGHT, "rho": RHO, "gravity": GRAVITY.tolist(),
            "E": E, "nu": NU, "duration": cfg["duration"], "rate_hz": REF_RATE,
            "ref_static": cfg["ref_static"], "ref_dynamic": cfg["ref_dynamic"],
            "ref_safety": cfg["ref_safety"], "ref_time_check": cfg["ref_time_check"]}


def load_reference(path: Path, cfg: dict, laws_static, laws_dynamic, recompute: bool = False) -> dict:
    """The cached reference (``path``) if it was computed with these settings, completed with
    the laws it lacks; recomputed from scratch if the settings differ or ``recompute``."""
    import json

    ref = None
    if path.exists() and not recompute:
        cached = json.loads(path.read_text())
        if cached.get("settings") == json.loads(json.dumps(reference_settings(cfg))):
            ref = cached
    missing = ref is None or any(law not in ref["static"] for law in [*laws_static, *laws_dynamic]) or any(
        law not in ref["dynamic"] for law in laws_dynamic)
    if not missing:
        print(f"using cached reference {path}")
        return ref
    ref = compute_reference(cfg, laws_static, laws_dynamic, ref)
    ref["machine"] = machine_info()
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path.name, ref, envs=(), folder=path.parent)
    return ref


# ---------------------------------------------------------------------------- sweep
def warm_up(laws):
    """Compile every Numba kernel the sweep uses, so no timing includes JIT compilation."""
    cant = Cantilever(5)
    for law in laws:
        for name, cls in FIELDS.items():
            if name == "Mass-tensor" and law != "StVK":
                continue
            field = cls(cant.mesh, LAWS[law]())
            for integrator in ("explicit", "implicit"):
                sim = cant.simulation(field, integrator=integrator)
                sim.step(1e-3)
            sim = cant.simulation(field)
            sim.solve_static(load_steps=4)
            x = cant.mesh.vertices * 1.01
            field.energy(x)
            field.forces(x)
            field.hessian(x, project=False)


def run_static(field_name: str, law: str, n: int, cfg: dict) -> dict:
    cant = Cantilever(n)
    t0 = time.perf_counter()
    field = FIELDS[field_name](cant.mesh, LAWS[law]())
    sim = cant.simulation(field)
    setup = time.perf_counter() - t0

    def solve():
        attempts = []
        t = time.perf_counter()
        for ls in cfg["static_load_steps"]:
            sim.reset()
            try:
                stats = sim.solve_static(load_steps=ls)
                attempts.append({"load_steps": ls, "converged": True, "newton_iterations": stats.newton_iterations})
                return time.perf_counter() - t, attempts, stats
            except (RuntimeError, hg.SimulationDiverged) as exc:
                attempts.append({"load_steps": ls, "converged": False, "message": str(exc)[:200]})
        return time.perf_counter() - t, attempts, None

    wall, attempts, stats = solve()
    row = {"kind": "static", "field": field_name, "law": law, "n": n, "cells": cant.cells,
           "n_tets": cant.mesh.n_tets, "n_vertices": cant.mesh.n_vertices, "setup_s": setup,
           "attempts": attempts, "converged": stats is not None}
    if stats is None:
        return {**row, "wall_s": wall}
    tip = cant.tip_z(sim.x)
    walls = [wall]
    if wall < 2.0:  # short: median of three
        walls += [solve()[0] for _ in range(2)]
    return {**row, "wall_s": float(np.median(walls)), "wall_all_s": walls, "tip_z": tip, "min_J": cant.min_j(sim.x),
            "load_steps": attempts[-1]["load_steps"], "newton_iterations": stats.newton_iterations,
            "residual_N": stats.residual}


def run_dynamic(field_name: str, law: str, n: int, integrator: str, cfg: dict, cap_s: float,
                safety: float | None = None, dt: float | None = None) -> dict:
    """One 1 s run; aborted (and its projected cost recorded) if it would exceed ``cap_s``."""
    cant = Cantilever(n)
    duration = cfg["duration"]
    t0 = time.perf_counter()
    field = FIELDS[field_name](cant.mesh, LAWS[law]())
    kw = {"safety": safety} if integrator == "explicit" else {}
    sim = cant.simulation(field, integrator=integrator, **kw)
    dt_c = sim.critical_dt() if integrator == "explicit" else None
    setup = time.perf_counter() - t0
    frame = cfg["explicit_frame"] if integrator == "explicit" else dt
    frames = round(duration / frame)
    row = {"kind": "dynamic", "field": field_name, "law": law, "n": n, "cells": cant.cells,
           "n_tets": cant.mesh.n_tets, "n_vertices": cant.mesh.n_vertices, "integrator": integrator,
           "safety": safety, "dt": frame if integrator == "implicit" else None, "frame_dt": frame,
           "critical_dt": dt_c, "setup_s": setup}

    def simulate(check_cap: bool):
        sim.reset()
        z = np.zeros(frames + 1)
        substeps = newton = 0
        elapsed, min_j, inverted_at = 0.0, 1.0, None
        for k in range(frames):
            t = time.perf_counter()
            try:
                stats = sim.step(frame)
            except hg.SimulationDiverged as exc:
                return {"status": "diverged", "diverged_at_s": k * frame, "message": str(exc)[:200],
                        "wall_s": elapsed + time.perf_counter() - t}
            z[k + 1] = cant.tip_z(sim.x)
            elapsed += time.perf_counter() - t
            substeps += stats.substeps
            newton += stats.newton_iterations
            j = cant.min_j(sim.x)  # untimed bookkeeping
            min_j = min(min_j, j)
            if j <= 0 and inverted_at is None:
                inverted_at = (k + 1) * frame
            if check_cap and elapsed > 2.0 and elapsed / (k + 1) * frames > cap_s:
                return {"status": "over_cap", "projected_wall_s": elapsed / (k + 1) * frames,
                        "simulated_s": (k + 1) * frame, "wall_s": elapsed}
        return {"status": "ok", "wall_s": elapsed, "z": z, "substeps": substeps, "newton_iterations": newton,
                "min_J": min_j, "inverted_at_s": inverted_at}

    res = simulate(check_cap=True)
    if res["status"] != "ok":
        return {**row, **res}
    walls = [res["wall_s"]]
    if res["wall_s"] < 1.0:
        walls += [simulate(False)["wall_s"] for _ in range(2)]
    z = res.pop("z")
    return {**row, **res, "wall_s": float(np.median(walls)), "wall_all_s": walls,
            "wall_per_sim_s": float(np.median(walls)) / duration, "tip_z": z.tolist()}


def add_errors(rows, ref):
    """Relative error of every finished row against its law's reference."""
    for r in rows:
        if r["kind"] == "static" and r.get("converged"):
            z0 = ref["static"][r["law"]]["tip_z"]
            r["error"] = abs(r["tip_z"] - z0) / abs(z0)
            r["cost_s"] = r["wall_s"]
        elif r["kind"] == "dynamic" and r.get("status") == "ok":
            d = ref["dynamic"][r["law"]]
            zr = np.asarray(d["tip_z"])
            z = np.asarray(r["tip_z"])
            stride = round(r["frame_dt"] * d["rate_hz"])
            if abs(stride - r["frame_dt"] * d["rate_hz"]) > 1e-9:
                raise ValueError("frame rate must divide the reference rate")
            zr = zr[::stride][: len(z)]
            r["error"] = rms_rel(z[1:], zr[1:], d["amplitude_m"])
            r["cost_s"] = r["wall_per_sim_s"]
            # oscillation kept: peak-to-peak tip motion over the second half, relative to the
            # reference's (backward Euler's numerical damping shows here, not in the RMS error)
            half = len(z) // 2
            r["amplitude_ratio"] = float(np.ptp(z[half:]) / np.ptp(zr[half:]))
    return rows


def expand_mass_spring(rows, laws):
    """Mass-spring ignores the law: its runs (made under the first law) count for every law."""
    out = []
    for r in rows:
        if r["field"] == "Mass-spring":
            for law in laws[r["kind"]]:
                out.append({**r, "law": law})
        else:
            out.append(r)
    return out


def sweep(cfg: dict, cap_s: float, kinds=("static", "dynamic")) -> list[dict]:
    jobs = []
    ms_law = cfg["static_laws"][0]
    for law in cfg["static_laws"] if "static" in kinds else []:
        for name in FIELDS:
            if (name == "Mass-tensor" and law != "StVK") or (name == "Mass-spring" and law != ms_law):
                continue
            jobs += [("static", name, law, n, None, None) for n in cfg["meshes"]]
    ms_law = cfg["dynamic_laws"][0]
    for law in cfg["dynamic_laws"] if "dynamic" in kinds else []:
        for name in FIELDS:
            if (name == "Mass-tensor" and law != "StVK") or (name == "Mass-spring" and law != ms_law):
                continue
            for n in cfg["meshes"]:
                jobs += [("explicit", name, law, n, s, None) for s in cfg["explicit_safety"]]
                jobs += [("implicit", name, law, n, None, dt) for dt in cfg["implicit_dt"]]
    rows = []
    for kind, name, law, n, safety, dt in tqdm(jobs, desc="sweep", unit="run"):
        if kind == "static":
            rows.append(run_static(name, law, n, cfg))
        else:
            rows.append(run_dynamic(name, law, n, kind, cfg, cap_s, safety=safety, dt=dt))
    return expand_mass_spring(rows, {"static": cfg["static_laws"], "dynamic": cfg["dynamic_laws"]})


# --------------------------------------------------------------------------- report
def pareto(points, rel_tol=1e-6):
    """Indices of the points that no other point beats: at most the cost and at most the error,
    and strictly better in one. Errors within ``rel_tol`` count as equal (HEML, F-FEM and
    mass-tensor give the same error to rounding; then only the cheapest is on the front)."""
    keep = []
    for i, (c, e) in enumerate(points):
        if not any(c2 <= c and e2 <= e * (1 + rel_tol) and (c2 < c or e2 < e * (1 - rel_tol))
                   for j, (c2, e2) in enumerate(points) if j != i):
            keep.append(i)
    return sorted(keep, key=lambda i: points[i][0])


def config_label(r) -> str:
    if r["kind"] == "static":
        return "static"
    if r["integrator"] == "explicit":
        return f"explicit s={r['safety']:g}"
    return f"implicit dt=1/{round(1 / r['dt'])}"


MARKERS = {"static": "o", "explicit s=0.5": "o", "explicit s=0.9": "D", "explicit s=0.25": "h",
           "implicit dt=1/30": "v", "implicit dt=1/60": "^", "implicit dt=1/120": "<", "implicit dt=1/240": ">",
           "peer": "*"}


def plot_panel(ax, rows, title, xlabel, ref_unc=None, label_points=True):
    """One log-log speed-vs-accuracy panel: colour = force field, marker = integrator setting,
    text = cells along x; Pareto front outlined and joined."""
    pts = [r for r in rows if "error" in r and r["error"] > 0]
    series = {}
    for r in pts:
        series.setdefault((r["field"], config_label(r)), []).append(r)
    for (field, conf), rs in series.items():
        rs = sorted(rs, key=lambda r: r["n"])
        ax.plot([r["cost_s"] for r in rs], [r["error"] for r in rs], "-", lw=0.6, alpha=0.5,
                color=FIELD_COLORS.get(field, "k"))
        ax.scatter([r["cost_s"] for r in rs], [r["error"] for r in rs], s=22,
                   marker=MARKERS.get(conf, "*"), color=FIELD_COLORS.get(field, "k"), zorder=3)
        if label_points:
            for r in rs:
                ax.annotate(str(r["n"]), (r["cost_s"], r["error"]), fontsize=5, xytext=(2, 2),
                            textcoords="offset points", color=FIELD_COLORS.get(field, "k"))
    front = pareto([(r["cost_s"], r["error"]) for r in pts])
    if front:
        fx = [pts[i]["cost_s"] for i in front]
        fy = [pts[i]["error"] for i in front]
        ax.step(fx, fy, where="post", color="k", lw=1.0, ls="--", zorder=2)
        ax.scatter(fx, fy, s=70, facecolors="none", edgecolors="k", lw=1.0, zorder=4)
    if ref_unc:
        ax.axhspan(1e-12, ref_unc, color="0.85", zorder=0)
        ax.text(0.99, 0.01, "reference uncertainty", transform=ax.transAxes, fontsize=6,
                ha="right", va="bottom", color="0.4")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("relative error of the tip deflection")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.25)
    lo = min((r["error"] for r in pts), default=1e-3)
    ax.set_ylim(min(lo, ref_unc or lo) * 0.5, max((r["error"] for r in pts), default=1) * 2)
    return [pts[i] for i in front]


def legend_handles(fields, confs):
    from matplotlib.lines import Line2D

    h = [Line2D([], [], color=FIELD_COLORS.get(f, "k"), marker="s", ls="", label=f) for f in fields]
    h += [Line2D([], [], color="0.3", marker=MARKERS.get(c, "*"), ls="", label=c) for c in confs]
    h += [Line2D([], [], color="k", marker="o", mfc="none", ls="--", label="Pareto front")]
    return h


def write_report(data: dict, out_dir: Path, img_dir: Path, stem: str = "speed_accuracy"):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, ref = data["results"], data["reference"]
    img_dir.mkdir(parents=True, exist_ok=True)
    fronts = {}
    for kind, laws, xlabel in [("static", data["config"]["static_laws"], "wall time to equilibrium (s)"),
                               ("dynamic", data["config"]["dynamic_laws"], "wall time per simulated second (s)")]:
        fig, axes = plt.subplots(1, len(laws), figsize=(5.2 * len(laws), 4.6), squeeze=False)
        present_fields, present_confs = [], []
        for ax, law in zip(axes[0], laws):
            rs = [r for r in rows if r["kind"] == kind and r["law"] == law]
            unc = (ref["static"][law]["relative_uncertainty"] if kind == "static"
                   else ref["dynamic"][law]["uncertainty_rel"])
            title = f"{kind}: {law}"
            if unc > 0.1:
                title += f"\nreference NOT converged (±{100 * unc:.0f} %): errors below the band mean nothing"
            fronts[(kind, law)] = plot_panel(ax, rs, title, xlabel, unc)
            for r in rs:
                if "error" in r:
                    if r["field"] not in present_fields:
                        present_fields.append(r["field"])
                    if config_label(r) not in present_confs:
                        present_confs.append(config_label(r))
        present_confs.sort(key=lambda c: list(MARKERS).index(c) if c in MARKERS else 99)
        fig.legend(handles=legend_handles(present_fields, present_confs), loc="lower center",
                   ncol=min(8, len(present_fields) + len(present_confs) + 1), fontsize=7, frameon=False)
        fig.suptitle(f"Cantilever speed vs accuracy, {kind} (labels: cells along x; mesh (n, n/5, n/5))",
                     fontsize=10)
        fig.tight_layout(rect=(0, 0.07, 1, 0.96))
        fig.savefig(img_dir / f"{stem}_{kind}.png", dpi=130)
        plt.close(fig)
    plot_reference(ref, img_dir / f"{stem}_reference.png")

    lines = [f"# Speed vs accuracy on the cantilever ({data['machine']['cpu']}, "
             f"{data['machine']['cores']} cores, numba threads {data['machine']['numba_threads']}, "
             f"{data['machine']['date']})\n",
             "Generated by `benchmarks/accuracy/speed_accuracy.py`; prose in `docs/studies/speed_accuracy.md`. "
             "Error: relative to the extrapolated reference of the same law. "
             "★ = on the Pareto front of its law's chart.\n"]
    lines.append("## Reference\n")
    hdr = ["law", "static tip z ref (mm)", "±", "order p", "finest level error",
           "dynamic peak (mm)", "dyn. ref uncertainty", "finest level dyn. error"]
    trows = []
    for law, s in ref["static"].items():
        d = ref["dynamic"].get(law)
        trows.append([law, f"{1e3 * s['tip_z']:.3f}", f"{100 * s['relative_uncertainty']:.2f} %", f"{s['order_p']:.2f}",
                      f"{100 * s['finest_level_error']:.2f} % (n={s['ladder'][-1]['n']})",
                      f"{1e3 * d['amplitude_m']:.2f}" if d else "-",
                      f"{100 * d['uncertainty_rel']:.2f} %" if d else "-",
                      f"{100 * d['level_error_rel'][str(d['levels'][-1])]:.2f} % (n={d['levels'][-1]})" if d else "-"])
    lines.append(markdown_table(hdr, trows))
    for kind in ("static", "dynamic"):
        lines.append(f"\n## {kind.capitalize()}\n")
        cost = "wall to equilibrium (s)" if kind == "static" else "wall per simulated s (s)"
        hdr = ["law", "field", "mesh", "tets", "integrator", cost, "error", "notes"]
        trows = []
        laws = data["config"][f"{kind}_laws"]
        for law in laws:
            front = {id(r) for r in fronts.get((kind, law), [])}
            rs = [r for r in rows if r["kind"] == kind and r["law"] == law]
            rs.sort(key=lambda r: (r.get("cost_s", r.get("projected_wall_s", 1e99)), r["field"]))
            for r in rs:
                mesh = "x".join(str(c) for c in r["cells"])
                if "error" in r:
                    star = " ★" if id(r) in front else ""
                    note = ""
                    if kind == "static":
                        note = f"load steps {r['load_steps']}, {r['newton_iterations']} Newton it."
                        failed = [a["load_steps"] for a in r["attempts"] if not a["converged"]]
                        if failed:
                            note += f" (after {', '.join(map(str, failed))} failed; counted)"
                    elif r["integrator"] == "explicit":
                        note = f"{r['substeps']} substeps, dt_c {1e6 * r['critical_dt']:.0f} us"
                    else:
                        note = f"{r['newton_iterations']} Newton it."
                    if kind == "dynamic":
                        note += f"; amplitude kept {r['amplitude_ratio']:.2f}"
                    if r.get("inverted_at_s") is not None:
                        note += f"; tets inverted from t = {r['inverted_at_s']:.3f} s (min J {r['min_J']:.2f})"
                    elif r.get("min_J", 1.0) <= 0:
                        note += f"; inverted tets (min J {r['min_J']:.2f})"
                    trows.append([law, r["field"], mesh, r["n_tets"], config_label(r),
                                  f"{r['cost_s']:.3g}", f"{100 * r['error']:.3g} %{star}", note])
                elif r.get("status") == "over_cap":
                    trows.append([law, r["field"], mesh, r["n_tets"], config_label(r),
                                  f"(~{r['projected_wall_s']:.0f}, projected)", "-",
                                  f"not completed: projected over the {data['cap_s']:g} s cap"])
                elif r.get("status") == "diverged":
                    trows.append([law, r["field"], mesh, r["n_tets"], config_label(r), "-", "-",
                                  f"diverged at t = {r['diverged_at_s']:.3f} s"])
                else:
                    trows.append([law, r["field"], mesh, r["n_tets"], config_label(r), "-", "-",
                                  "did not converge: " + "; ".join(
                                      f"{a['load_steps']} steps" for a in r.get("attempts", []))])
        lines.append(markdown_table(hdr, trows))
    (out_dir / f"{stem}.md").write_text("\n".join(lines))


def plot_reference(ref, path):
    import matplotlib.pyplot as plt

    laws_s = list(ref["static"])
    laws_d = list(ref["dynamic"])
    fig, axes = plt.subplots(1, 1 + len(laws_d), figsize=(5 * (1 + len(laws_d)), 4.2), squeeze=False)
    ax = axes[0][0]
    for i, law in enumerate(laws_s):
        s = ref["static"][law]
        ns = np.array([r["n"] for r in s["ladder"]], dtype=float)
        err = np.array([abs(r["tip_z"] - s["tip_z"]) for r in s["ladder"]]) / abs(s["tip_z"])
        ax.loglog(1.0 / ns, err, "o-", color=f"C{i}", label=f"{law} (fit p = {s['order_p']:.2f})")
        ax.axhline(s["relative_uncertainty"], color=f"C{i}", ls=":", lw=0.8)
    ax.set_xlabel("1 / n  (n cells along x, cell size h = L / n)")
    ax.set_ylabel("|tip z - extrapolated| / |extrapolated|")
    ax.set_title("static: convergence under refinement\n(dotted: estimated reference uncertainty)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    for ax, law in zip(axes[0][1:], laws_d):
        d = ref["dynamic"][law]
        t = np.arange(len(d["tip_z"])) / d["rate_hz"]
        for j, n in enumerate(d["levels"]):
            ax.plot(t, 1e3 * np.asarray(d["level_tip_z"][str(n)]), lw=0.8, color=f"C{j}",
                    label=f"n = {n} ({100 * d['level_error_rel'][str(n)]:.1f} %)")
        ax.plot(t, 1e3 * np.asarray(d["tip_z"]), "k--", lw=1.0,
                label=f"extrapolated (± {100 * d['uncertainty_rel']:.1f} %)")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("tip z displacement (mm)")
        title = f"dynamic reference, {law}: explicit HEML, safety {ref['settings']['ref_safety']}"
        if d["uncertainty_rel"] > 0.1:
            title += "\nNOT converged under refinement"
        ax.set_title(title, fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


# ----------------------------------------------------------------------------- main
def main(argv=None):
    import json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small meshes, 0.25 s: a smoke run (output in /tmp)")
    ap.add_argument("--stage", choices=["all", "reference", "sweep", "report"], default="all",
                    help="reference: only the cached reference; report: redraw from the saved JSON")
    ap.add_argument("--cap-s", type=float, default=45.0,
                    help="dynamic runs projected to take longer than this (wall s per simulated s) are "
                         "stopped after 2 s and reported as over the cap")
    ap.add_argument("--recompute-reference", action="store_true")
    ap.add_argument("--only", choices=["static", "dynamic"], default=None,
                    help="rerun only this part of the sweep and merge it into the saved JSON")
    ap.add_argument("--out", type=Path, default=None, help="output folder (default docs/, /tmp for --quick)")
    args = ap.parse_args(argv)
    cfg = quick_config() if args.quick else full_config()
    if args.out is not None:
        out_dir, img_dir = args.out, args.out
    elif args.quick:
        out_dir = img_dir = Path("/tmp/speed_accuracy_quick")
    else:
        out_dir, img_dir = RESULTS, IMAGES
    out_dir.mkdir(parents=True, exist_ok=True)
    ref_path = out_dir / "speed_accuracy_reference.json"
    res_path = out_dir / "speed_accuracy.json"
    if args.stage == "report":
        data = json.loads(res_path.read_text())
        add_errors(data["results"], data["reference"])  # deterministic: refreshes derived numbers
        write_json(res_path.name, data, envs=(), folder=out_dir)
        write_report(data, out_dir, img_dir)
        return
    t_start = time.perf_counter()
    ref = load_reference(ref_path, cfg, cfg["static_laws"], cfg["dynamic_laws"], args.recompute_reference)
    if args.stage == "reference":
        return
    t0 = time.perf_counter()
    warm_up(sorted(set(cfg["static_laws"]) | set(cfg["dynamic_laws"])))
    kinds = (args.only,) if args.only else ("static", "dynamic")
    rows = add_errors(sweep(cfg, args.cap_s, kinds), ref)
    sweep_wall = {kind: time.perf_counter() - t0 for kind in kinds} if args.only else {"all": time.perf_counter() - t0}
    if args.only:  # keep the other part of the saved sweep
        old = json.loads(res_path.read_text())
        rows = add_errors([r for r in old["results"] if r["kind"] != args.only], ref) + rows
        sweep_wall = {**old.get("sweep_wall_parts_s", {"all (before)": old["sweep_wall_s"]}), **sweep_wall}
    data = {
        "machine": machine_info(), "config": cfg, "cap_s": args.cap_s,
        "scene": reference_settings(cfg),
        "sweep_wall_s": time.perf_counter() - t0, "sweep_wall_parts_s": sweep_wall,
        "total_wall_s": time.perf_counter() - t_start,
        "reference": ref,
        "results": rows,
    }
    write_json(res_path.name, data, envs=(), folder=out_dir)
    write_report(data, out_dir, img_dir)
    print(f"sweep {data['sweep_wall_s']:.0f} s, total {data['total_wall_s']:.0f} s; wrote {res_path}")


if __name__ == "__main__":
    main()
