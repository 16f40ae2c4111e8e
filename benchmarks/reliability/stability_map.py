"""Stability map: force field x integrator x time step x scenario -> how each run ends.

Every run uses one fixed step ``dt = multiple * dt_c`` with ``substeps=1`` (the explicit
integrator's automatic sub-stepping is bypassed), where ``dt_c = sim.critical_dt()`` is the
rest-state explicit limit of that field on that mesh. Scenarios (soft tissue, E = 5 kPa,
nu = 0.45, rho = 1000 kg/m^3, gravity, no damping):

* ``cantilever``: 0.10 x 0.02 x 0.02 m box clamped at x = 0, released straight, 0.5 s;
* ``compression``: 0.03 m cube, top and bottom vertex layers attached and driven towards
  each other to 20 % of the rest height in 0.1 s, then held 0.05 s;
* ``pull-through``: 0.02 m cube fixed at its bottom face; one top corner vertex is dragged
  in 0.1 s along a straight line across the body and out through the fixed bottom face,
  then held 0.05 s;
* ``grasp-yank``: 0.06 x 0.06 x 0.02 m slab fixed at its bottom; a 3 x 3 patch of top
  vertices is pulled up at 1 m/s for 0.05 s, then released; 0.15 s in all.

Each run is classified (criteria in docs/studies/stability.md): stable, Newton stalled, inverted
elements left inverted, energy blow-up, diverged (speed limit), diverged (non-finite),
timeout. Every implicit run that fails or stalls is re-run once without Newton's early
"stalled" exit (a diagnostic: ``ImplicitSolver.stall_limit = None``). Writes
docs/benchmarks/stability_map.json, .md and docs/img/stability_map.png,
stability_map_newton.png, stability_map_time.png. The full run takes about 7 minutes on
2 cores.

    python benchmarks/reliability/stability_map.py [--quick] [--scenarios a,b] [--fields a,b] [--replot]
"""

from __future__ import annotations

import argparse
import inspect
import math
import time
from dataclasses import dataclass, field as dc_field
from pathlib import Path

import numpy as np
from tqdm import tqdm
import heml_gym as hg
import warnings

# the map counts unconverged steps itself; the facade's warnings would flood the log
warnings.simplefilter("ignore", hg.NotConvergedWarning)
from heml_gym.benchmarks.common import IMAGES, RESULTS, ROOT, machine_info, markdown_table, write_json
from heml_gym import materials as M
from heml_gym.kinematics import volume_ratios

E, NU, RHO = 5e3, 0.45, 1000.0
GRAVITY = np.array([0.0, 0.0, -9.81])
MULTIPLES = [0.5, 1, 2, 5, 10, 30, 100]
INTEGRATORS = ["explicit", "implicit"]

FIELDS = {
    "HEML Neo-Hookean": lambda mesh: hg.HemlForce(mesh, M.NeoHookean(E=E, nu=NU)),
    "HEML StVK": lambda mesh: hg.HemlForce(mesh, M.StVenantKirchhoff(E=E, nu=NU)),
    "HEML StableNeoHookean": lambda mesh: hg.HemlForce(mesh, M.StableNeoHookean(E=E, nu=NU)),
    "F-FEM Neo-Hookean": lambda mesh: hg.FemForce(mesh, M.NeoHookean(E=E, nu=NU)),
    "Mass-tensor StVK": lambda mesh: hg.MassTensorForce(mesh, M.StVenantKirchhoff(E=E, nu=NU)),
    "Mass-spring": lambda mesh: hg.MassSpringForce(mesh, M.NeoHookean(E=E, nu=NU)),
}
#: Fields whose energy is defined for inverted tets (J <= 0): only for them does
#: "inverted elements left inverted" apply; a Neo-Hookean tet at J <= 0 is non-finite.
ALLOWS_INVERSION = {"HEML StVK", "HEML StableNeoHookean", "Mass-tensor StVK", "Mass-spring"}

# ----------------------------------------------------------------- outcome criteria
BLOWUP_FACTOR = 100.0  # energy blow-up: E_mech - E_mech(0) > BLOWUP_FACTOR * E_in
STALL_FACTOR = 1e-3  # Newton stalled: a step ends with residual > STALL_FACTOR * weight (M |g|)
RUN_CAP_S = 60.0  # wall-clock cap per run (timeout)
MIN_STEPS = 10  # a run lasts at least this many steps (the last phase is extended)

OUTCOMES = [  # (key, label, colour), from best to worst
    ("stable", "stable", "#4caf50"),
    ("newton_stalled", "Newton stalled (residual > 1e-3 x weight)", "#cddc39"),
    ("inverted", "inverted elements left inverted (J <= 0 at end)", "#ff9800"),
    ("energy_blowup", "energy blow-up (> 100x input bound, finite)", "#9c27b0"),
    ("diverged_speed", "diverged: speed > max_speed (SimulationDiverged)", "#e53935"),
    ("diverged_nonfinite", "diverged: NaN / non-finite (SimulationDiverged)", "#7f0000"),
    ("timeout", "too slow (timeout)", "#9e9e9e"),
]
OUTCOME_KEYS = [o[0] for o in OUTCOMES]


# ----------------------------------------------------------------------- scenarios
@dataclass
class Scenario:
    """A mesh, its fixed and driven vertices, a schedule and an energy-input bound."""

    name: str
    description: str
    mesh: hg.TetMesh
    fixed: np.ndarray
    t_end: float
    driven: np.ndarray = dc_field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    drive_speed: float = 0.0  # m/s, for the kinetic part of the input bound
    drop: float = 0.0  # m, largest fall any vertex can make under gravity

    def targets(self, t: float):  # positions of the driven vertices at time t (m)
        return None

    def release_time(self) -> float:  # driven vertices are detached from this time on
        return math.inf

    def energy_input_bound(self, field) -> float:
        """A-priori bound E_in (J) on the mechanical energy the scenario can put in.

        ``V (lam + 2 mu)``: every tet carrying a unit strain in the stiffest (P-wave) mode;
        plus ``M g drop``: everything falling by ``drop``; plus ``M v^2 / 2``: everything
        moving at the drive speed. Small-strain moduli of the field's material.
        """
        mat = field.material
        mass = RHO * self.mesh.total_volume
        elastic = self.mesh.total_volume * (mat.lame_lambda + 2.0 * mat.shear_modulus)
        return elastic + mass * float(np.linalg.norm(GRAVITY)) * self.drop + 0.5 * mass * self.drive_speed**2


class Cantilever(Scenario):
    def __init__(self, t_end=0.5):
        mesh = hg.box_mesh((0.10, 0.02, 0.02), (15, 3, 3))
        fixed = np.flatnonzero(mesh.vertices[:, 0] < 1e-9)
        super().__init__("cantilever", "0.10 x 0.02 x 0.02 m beam clamped at x = 0, released straight "
                         "under gravity", mesh, fixed, t_end, drop=0.10)


class Compression(Scenario):
    def __init__(self, t_drive=0.1, t_hold=0.05, side=0.03, final=0.2):
        mesh = hg.box_mesh((side, side, side), 5)
        z = mesh.vertices[:, 2]
        self.bottom = np.flatnonzero(z < 1e-9)
        self.top = np.flatnonzero(z > side - 1e-9)
        self.t_drive, self.side, self.final = t_drive, side, final
        self.rest = mesh.vertices.copy()
        travel = 0.5 * (1.0 - final) * side
        super().__init__("compression", f"{side * 100:g} cm cube, top and bottom layers driven together "
                         f"to {final:.0%} of the height in {t_drive:g} s, held {t_hold:g} s",
                         mesh, np.zeros(0, dtype=np.int64), t_drive + t_hold,
                         driven=np.concatenate([self.bottom, self.top]),
                         drive_speed=travel / t_drive, drop=side)

    def targets(self, t):
        travel = 0.5 * (1.0 - self.final) * self.side * min(t / self.t_drive, 1.0)
        x = self.rest[self.driven].copy()
        nb = len(self.bottom)
        x[:nb, 2] += travel
        x[nb:, 2] -= travel
        return x


class PullThrough(Scenario):
    def __init__(self, t_drive=0.1, t_hold=0.05, side=0.02):
        mesh = hg.box_mesh((side, side, side), 4)
        v = mesh.vertices
        fixed = np.flatnonzero(v[:, 2] < 1e-9)
        corner = int(np.argmin(np.linalg.norm(v - np.array([0.0, 0.0, side]), axis=1)))
        self.start = v[corner].copy()
        # across the body, out through the fixed bottom face between its vertices
        self.end = np.array([1.05, 0.85, -0.25]) * side
        self.t_drive = t_drive
        dist = float(np.linalg.norm(self.end - self.start))
        super().__init__("pull-through", f"{side * 100:g} cm cube fixed at its bottom; the top corner "
                         f"vertex is dragged {dist * 100:.1f} cm across the body and out through the "
                         f"fixed bottom face in {t_drive:g} s, then held {t_hold:g} s",
                         mesh, fixed, t_drive + t_hold, driven=np.array([corner]),
                         drive_speed=dist / t_drive, drop=side)

    def targets(self, t):
        s = min(t / self.t_drive, 1.0)
        return (self.start + s * (self.end - self.start))[None, :]


class GraspYank(Scenario):
    def __init__(self, t_pull=0.05, t_after=0.10, speed=1.0):
        size = (0.06, 0.06, 0.02)
        mesh = hg.box_mesh(size, (8, 8, 3))
        v = mesh.vertices
        fixed = np.flatnonzero(v[:, 2] < 1e-9)
        top = v[:, 2] > size[2] - 1e-9
        near = np.all(np.abs(v[:, :2] - np.array([0.03, 0.03])) < 0.008, axis=1)  # 3 x 3 vertices
        self.patch = np.flatnonzero(top & near)
        self.rest = v[self.patch].copy()
        self.t_pull, self.speed = t_pull, speed
        super().__init__("grasp-yank", f"6 x 6 x 2 cm slab fixed at its bottom; a patch of "
                         f"{len(self.patch)} top vertices pulled up at {speed:g} m/s for {t_pull:g} s "
                         f"({speed * t_pull * 100:g} cm), then released; {t_pull + t_after:g} s in all",
                         mesh, fixed, t_pull + t_after, driven=self.patch, drive_speed=speed,
                         drop=size[2])

    def targets(self, t):
        x = self.rest.copy()
        x[:, 2] += self.speed * min(t, self.t_pull)
        return x

    def release_time(self):
        return self.t_pull


def make_scenarios(scale: float = 1.0) -> dict:
    """The four scenarios; ``scale`` < 1 shortens every phase (quick mode)."""
    return {s.name: s for s in (
        Cantilever(t_end=0.5 * scale),
        Compression(t_drive=0.1 * scale, t_hold=0.05 * scale),
        PullThrough(t_drive=0.1 * scale, t_hold=0.05 * scale),
        GraspYank(t_pull=0.05 * scale, t_after=0.10 * scale, speed=1.0),
    )}


# --------------------------------------------------------------------------- a run
def run_case(scn: Scenario, field, field_name: str, integrator: str, mult: float, dt_c: float,
             cap_s: float, stall_exit: bool = True) -> dict:
    """One simulation at ``dt = mult * dt_c``, ``substeps=1``; returns the classified record.

    ``stall_exit=False``: Newton without its early "stalled" exit (the diagnostic re-run,
    ``ImplicitSolver.stall_limit = None``).
    """
    mesh = scn.mesh
    # refinements=(): the explicit method itself, without the solver's finer second try
    kw = {"refinements": ()} if integrator == "explicit" else {}
    sim = hg.Simulation(field, RHO, gravity=GRAVITY, fixed=scn.fixed, integrator=integrator, **kw)
    if not stall_exit and integrator == "implicit":
        sim.solver.stall_limit = None
    dt = mult * dt_c
    n_steps = max(MIN_STEPS, math.ceil(scn.t_end / dt - 1e-9))
    weight = float(sim.mass.sum() * np.linalg.norm(GRAVITY))
    e_in = scn.energy_input_bound(field)
    if len(scn.driven):
        sim.attach(scn.driven)
    released = False
    e0 = sim.total_energy()
    rec = {
        "scenario": scn.name, "field": field_name, "integrator": integrator, "multiple": mult,
        "dt_c_s": dt_c, "dt_s": dt, "steps_planned": n_steps, "t_end_s": n_steps * dt,
        "energy_input_bound_J": e_in, "weight_N": weight,
    }
    max_e = 0.0
    min_j = 1.0
    max_inverted = 0
    max_res = 0.0
    max_iter = 0
    stalled_steps = 0
    newton_iters = 0
    outcome, detail, fail_step = None, "", None
    diag = {}
    steps_done = 0
    t0 = time.perf_counter()
    for k in range(n_steps):
        t_start, t_next = k * dt, (k + 1) * dt
        if not released and t_start >= scn.release_time() - 1e-12:
            sim.detach()
            released = True
        if sim.kinematic.any():
            sim.drive(scn.driven, scn.targets(t_next))
        try:
            stats = sim.step(dt, substeps=1)
        except hg.SimulationDiverged as err:
            outcome = "diverged_speed" if "speed" in err.reason else "diverged_nonfinite"
            detail = f"SimulationDiverged at step {err.step} (t = {t_start:.4g} s): {err.reason}"
            fail_step = err.step
            # diagnosis: the state before the failing step (the simulation restored it) and,
            # for the implicit integrator, Newton's starting guess x + dt v (drivers at targets)
            inv_before = int((volume_ratios(mesh, sim.x) <= 0).sum())
            diag["inverted_before_failure"] = inv_before
            if inv_before:
                detail += f"; {inv_before} tets already inverted before that step"
            if integrator == "implicit":
                guess = sim.x + dt * sim.v
                guess[sim.fixed] = sim.x[sim.fixed]
                if sim.kinematic.any():
                    guess[scn.driven] = scn.targets(t_next)
                inv_guess = int((volume_ratios(mesh, guess) <= 0).sum())
                diag["initial_guess_inverted"] = inv_guess
                diag["initial_guess_energy_finite"] = bool(np.isfinite(field.energy(guess)))
                if inv_guess:
                    detail += f"; Newton's initial guess x + dt v inverts {inv_guess} tets"
            break
        steps_done += 1
        if integrator == "implicit":
            res = float(stats.residual)
            max_res = max(max_res, res)
            max_iter = max(max_iter, stats.newton_iterations)
            newton_iters += stats.newton_iterations
            stalled_steps += res > STALL_FACTOR * weight
        j = volume_ratios(mesh, sim.x)
        min_j = min(min_j, float(j.min()))
        max_inverted = max(max_inverted, int((j <= 0).sum()))
        e = sim.total_energy() - e0
        if np.isfinite(e):
            max_e = max(max_e, e)
            if e > BLOWUP_FACTOR * e_in:
                outcome = "energy_blowup"
                detail = (f"mechanical energy {e:.3g} J > {BLOWUP_FACTOR:g} x E_in = "
                          f"{BLOWUP_FACTOR * e_in:.3g} J at step {k} (t = {t_next:.4g} s)")
                fail_step = k
                break
        else:
            max_e = math.inf  # an inverted tet of a ln J law: the next step's forces are NaN
        if time.perf_counter() - t0 > cap_s and k < n_steps - 1:
            outcome = "timeout"
            detail = (f"stopped after {time.perf_counter() - t0:.1f} s wall time at step {k + 1} of "
                      f"{n_steps} (t = {t_next:.4g} s)")
            break
    wall = time.perf_counter() - t0
    j_end = volume_ratios(mesh, sim.x)
    n_inv_end = int((j_end <= 0).sum())
    e_end = sim.total_energy() - e0
    if outcome is None:
        if not np.isfinite(e_end):
            outcome = "diverged_nonfinite"
            detail = (f"final state has {n_inv_end} tets at J <= 0 where the law is undefined "
                      "(energy +inf, the next step's forces are NaN)")
        elif n_inv_end > 0 and field_name in ALLOWS_INVERSION:
            outcome = "inverted"
            detail = f"{n_inv_end} of {mesh.n_tets} tets inverted at the end (min J {j_end.min():.3g})"
        elif stalled_steps:
            outcome = "newton_stalled"
            detail = (f"{stalled_steps} of {steps_done} steps ended with residual > {STALL_FACTOR:g} x weight; "
                      f"max {max_res / weight:.3g} x weight")
        else:
            outcome = "stable"
            detail = f"max energy {max_e / e_in:.3g} E_in, min J {min_j:.3g}"
    rec.update({
        "outcome": outcome, "detail": detail, "fail_step": fail_step, "steps_done": steps_done,
        "t_reached_s": steps_done * dt, "wall_s": wall, "max_energy_J": max_e,
        "max_energy_over_input": max_e / e_in, "final_energy_J": e_end if np.isfinite(e_end) else None,
        "min_J_run": min_j, "max_inverted_run": max_inverted, "inverted_end": n_inv_end,
        "min_J_end": float(j_end.min()) if np.all(np.isfinite(j_end)) else None,
        "mean_z_free_end_m": float(sim.x[sim.free, 2].mean()) if sim.free.any() else None,
        **diag,
    })
    if integrator == "implicit":
        rec.update({"newton_iterations": newton_iters, "max_newton_iterations": max_iter,
                    "max_residual_N": max_res, "max_residual_over_weight": max_res / weight,
                    "stalled_steps": stalled_steps})
    return rec


def git_state() -> dict:
    """Commit of the working tree and whether heml_gym/ had uncommitted changes."""
    import subprocess

    root = ROOT
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True,
                                text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "heml_gym"], cwd=root, capture_output=True,
                               text=True, check=True).stdout.strip()
        return {"commit": commit, "heml_gym_uncommitted_changes": bool(dirty)}
    except (OSError, subprocess.CalledProcessError):
        return {}


def warm_up(scenarios):
    """Compile every kernel (forces, energy, Hessians) on a tiny mesh before timing."""
    mesh = hg.box_mesh((0.01, 0.01, 0.01), 1)
    for make in FIELDS.values():
        field = make(mesh)
        for integrator in INTEGRATORS:
            sim = hg.Simulation(field, RHO, gravity=GRAVITY, fixed=[0, 1], integrator=integrator)
            sim.critical_dt()
            sim.step(1e-4, substeps=1)
            sim.total_energy()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="smoke run: phases 4x shorter, multiples 1, 5, 100, output under /tmp")
    ap.add_argument("--scenarios", default="", help="comma-separated subset of scenarios")
    ap.add_argument("--fields", default="", help="comma-separated subset of fields")
    ap.add_argument("--multiples", default="", help="comma-separated dt multiples")
    ap.add_argument("--cap", type=float, default=RUN_CAP_S, help="wall-clock cap per run (s)")
    ap.add_argument("--outdir", default="", help="where to write (default docs/, /tmp for --quick)")
    ap.add_argument("--no-newton-diagnostic", action="store_true",
                    help="skip re-running the failed implicit cases without Newton's stall exit")
    ap.add_argument("--replot", action="store_true",
                    help="only redraw the charts and the table from the JSON already written")
    args = ap.parse_args(argv)
    if args.replot:
        import json

        res_dir = Path(args.outdir) if args.outdir else RESULTS
        img_dir = Path(args.outdir) if args.outdir else IMAGES
        write_report(json.loads((res_dir / "stability_map.json").read_text()), res_dir, img_dir)
        return
    t_total = time.perf_counter()
    scenarios = make_scenarios(0.25 if args.quick else 1.0)
    if args.scenarios:
        scenarios = {k: scenarios[k] for k in args.scenarios.split(",")}
    fields = list(FIELDS) if not args.fields else args.fields.split(",")
    mults = [float(m) for m in args.multiples.split(",")] if args.multiples else (
        [1, 5, 100] if args.quick else MULTIPLES)
    mults = [int(m) if float(m).is_integer() else m for m in mults]
    if args.outdir:
        res_dir = img_dir = Path(args.outdir)
    elif args.quick:
        res_dir = img_dir = Path("/tmp/stability_map_quick")
    else:
        res_dir, img_dir = RESULTS, IMAGES
    res_dir.mkdir(parents=True, exist_ok=True)
    img_dir.mkdir(parents=True, exist_ok=True)

    warm_up(scenarios)
    newton_diag = not args.no_newton_diagnostic
    records, setups = [], []
    jobs = [(s, f) for s in scenarios for f in fields]
    bar = tqdm(total=len(jobs) * len(INTEGRATORS) * len(mults), desc="stability map", unit="run")
    for scn_name, field_name in jobs:
        scn = scenarios[scn_name]
        t0 = time.perf_counter()
        field = FIELDS[field_name](scn.mesh)
        dt_c = hg.Simulation(field, RHO, gravity=GRAVITY, fixed=scn.fixed).critical_dt()
        setups.append({"scenario": scn_name, "field": field_name, "dt_c_s": dt_c,
                       "setup_s": time.perf_counter() - t0})
        for integrator in INTEGRATORS:
            for mult in mults:
                bar.set_postfix_str(f"{scn_name} {field_name} {integrator} {mult}x")
                rec = run_case(scn, field, field_name, integrator, mult, dt_c, args.cap)
                if newton_diag and integrator == "implicit" and (
                        rec["outcome"] != "stable" or rec["stalled_steps"]):
                    d = run_case(scn, field, field_name, integrator, mult, dt_c, args.cap, stall_exit=False)
                    rec["without_stall_exit"] = {k: d.get(k) for k in (
                        "outcome", "detail", "steps_done", "stalled_steps", "max_residual_over_weight",
                        "max_newton_iterations", "newton_iterations", "max_energy_over_input",
                        "inverted_end", "min_J_run", "wall_s")}
                records.append(rec)
                bar.update()
    bar.close()
    total = time.perf_counter() - t_total
    data = {
        "machine": machine_info(),
        "git": git_state(),
        "total_wall_s": total,
        "simulation_defaults": {k: v.default for k, v in inspect.signature(hg.Simulation).parameters.items()
                                if k in ("safety", "newton_tol", "max_newton", "max_speed", "linear_solver")},
        "newton_diagnostic": newton_diag,
        "material": {"E_Pa": E, "nu": NU, "density_kg_m3": RHO, "gravity_m_s2": GRAVITY.tolist(),
                     "damping": "none"},
        "criteria": {"blowup_factor": BLOWUP_FACTOR, "stall_factor_of_weight": STALL_FACTOR,
                     "run_cap_s": args.cap, "max_speed_m_s": 1e3},
        "multiples": mults,
        "integrators": INTEGRATORS,
        "fields": fields,
        "scenarios": {k: {"description": s.description, "n_tets": s.mesh.n_tets,
                          "n_vertices": s.mesh.n_vertices, "t_end_s": s.t_end,
                          "fixed": int(len(s.fixed)), "driven": int(len(s.driven))}
                      for k, s in scenarios.items()},
        "setup": setups,
        "results": records,
    }
    write_json("stability_map.json", data, envs=(), folder=res_dir)
    write_report(data, res_dir, img_dir)
    print(f"total wall time {total:.0f} s")


# ------------------------------------------------------------------------ reports
def _cell_text(r) -> str:
    o = r["outcome"]
    txt = ""
    if o in ("diverged_speed", "diverged_nonfinite", "energy_blowup"):
        txt = f"{r['t_reached_s'] * 1e3:.0f}ms" if r["t_reached_s"] < 1 else f"{r['t_reached_s']:.2g}s"
    elif o == "inverted":
        txt = f"{r['inverted_end']}"
    elif o == "newton_stalled":
        txt = f"{r['stalled_steps']}/{r['steps_done']}"
    elif o == "timeout":
        txt = f"{r['wall_s']:.0f}s"
    if o != "newton_stalled" and r.get("stalled_steps"):
        txt += "*"  # some Newton steps also stalled
    return txt


SHORT_NAMES = {"HEML StableNeoHookean": "HEML Stable NH"}


def _label(field_name: str) -> str:
    return SHORT_NAMES.get(field_name, field_name)


def summary(data) -> str:
    """The map in numbers, for docs/studies/stability.md (generated: no hand-typed counts)."""
    from collections import Counter

    res = data["results"]
    parts = []
    for integ in data["integrators"]:
        runs = [r for r in res if r["integrator"] == integ]
        counts = Counter(r["outcome"] for r in runs)
        names = {"stable": "stable", "newton_stalled": "Newton stalled", "inverted": "inverted",
                 "energy_blowup": "energy blow-ups", "diverged_speed": "speed-limit divergences",
                 "diverged_nonfinite": "non-finite", "timeout": "timeouts"}
        text = ", ".join(f"{counts[k]} {v}" for k, v in names.items() if counts[k])
        line = f"{integ.capitalize()} ({len(runs)} runs): {text}."
        if integ == "implicit":
            unconverged = [r for r in runs if r.get("stalled_steps")]
            steps = sum(r["stalled_steps"] for r in unconverged)
            total = sum(r.get("steps_done", 0) for r in runs)
            worst = max((r.get("max_residual_over_weight", 0.0) for r in runs), default=0.0)
            line += (f" **{len(unconverged)} implicit runs had steps whose Newton solve did not converge** "
                     f"({steps} of {total} steps ended with a force residual above {STALL_FACTOR:g} x weight; the "
                     f"worst {worst:.2g} x weight); they are counted under their final outcome above, and since "
                     "issue 12 every such step is reported (`StepStats.converged`, a warning from `Simulation`).")
        parts.append(line)
    stable = sum(r["outcome"] == "stable" for r in res)
    return (f"Of {len(res)} runs, **{stable} are stable**. " + " ".join(parts)
            + " No run timed out." * (not any(r["outcome"] == "timeout" for r in res)))


def write_report(data, res_dir: Path, img_dir: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap, LogNorm
    from matplotlib.patches import Patch

    recs = data["results"]
    scen = list(data["scenarios"])
    fields, mults, integ = data["fields"], data["multiples"], data["integrators"]
    rows = [(f, i) for f in fields for i in integ]
    index = {(r["scenario"], r["field"], r["integrator"], r["multiple"]): r for r in recs}
    colours = [o[2] for o in OUTCOMES]
    cmap = ListedColormap(["#ffffff"] + colours)

    def grid(s, value):
        g = np.full((len(rows), len(mults)), np.nan)
        for a, (f, i) in enumerate(rows):
            for b, m in enumerate(mults):
                r = index.get((s, f, i, m))
                if r is not None:
                    g[a, b] = value(r)
        return g

    ncol = min(2, len(scen))
    nrow = math.ceil(len(scen) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(7.2 * ncol, 5.2 * nrow + 1.2), squeeze=False)
    for ax, s in zip(axes.ravel(), scen):
        g = grid(s, lambda r: OUTCOME_KEYS.index(r["outcome"]) + 1)
        ax.imshow(np.nan_to_num(g, nan=0), cmap=cmap, vmin=0, vmax=len(OUTCOMES), aspect="auto")
        for a, (f, i) in enumerate(rows):
            for b, m in enumerate(mults):
                r = index.get((s, f, i, m))
                if r is not None:
                    dark = r["outcome"] in ("diverged_nonfinite", "energy_blowup", "diverged_speed")
                    ax.text(b, a, _cell_text(r), ha="center", va="center", fontsize=6.5,
                            color="white" if dark else "black")
        ax.set_xticks(range(len(mults)), [f"{m:g}" for m in mults])
        ax.set_yticks(range(len(rows)), [f"{_label(f)} / {i[:4]}." for f, i in rows], fontsize=7.5)
        for a in range(2, len(rows), 2):
            ax.axhline(a - 0.5, color="black", lw=0.8)
        ax.set_xlabel("dt / dt_c (rest critical step), substeps = 1")
        sd = data["scenarios"][s]
        ax.set_title(f"{s} ({sd['n_tets']} tets, {sd['t_end_s']:g} s)", fontsize=10)
    for ax in axes.ravel()[len(scen):]:
        ax.axis("off")
    handles = [Patch(facecolor=c, edgecolor="black", label=lab) for _, lab, c in OUTCOMES]
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=8, frameon=False)
    fig.suptitle("Stability map: E = 5 kPa, nu = 0.45, no damping. Cell text: simulated time at failure, "
                 "tets left inverted, stalled/total Newton steps, wall time of a timeout; "
                 "* = some Newton steps stalled", fontsize=9)
    fig.tight_layout(rect=(0, 0.07, 1, 0.97))
    fig.savefig(img_dir / "stability_map.png", dpi=130)
    plt.close(fig)

    # diagnostic: implicit runs as shipped vs without Newton's early "stalled" exit
    if any("without_stall_exit" in r for r in recs):
        diag_rows = [(f, v) for f in fields for v in ("shipped", "no stall exit")]
        fig, axes = plt.subplots(nrow, ncol, figsize=(7.2 * ncol, 5.2 * nrow + 1.2), squeeze=False)
        for ax, s in zip(axes.ravel(), scen):
            g = np.zeros((len(diag_rows), len(mults)))
            for a, (f, v) in enumerate(diag_rows):
                for b, m in enumerate(mults):
                    r = index.get((s, f, "implicit", m))
                    if r is None:
                        continue
                    if v == "no stall exit":
                        r = {**r, **r.get("without_stall_exit", {})}
                    g[a, b] = OUTCOME_KEYS.index(r["outcome"]) + 1
                    dark = r["outcome"] in ("diverged_nonfinite", "energy_blowup", "diverged_speed")
                    ax.text(b, a, _cell_text(r), ha="center", va="center", fontsize=6.5,
                            color="white" if dark else "black")
            ax.imshow(g, cmap=cmap, vmin=0, vmax=len(OUTCOMES), aspect="auto")
            ax.set_xticks(range(len(mults)), [f"{m:g}" for m in mults])
            ax.set_yticks(range(len(diag_rows)), [f"{_label(f)} / {v}" for f, v in diag_rows], fontsize=7.5)
            for a in range(2, len(diag_rows), 2):
                ax.axhline(a - 0.5, color="black", lw=0.8)
            ax.set_xlabel("dt / dt_c, implicit, substeps = 1")
            ax.set_title(f"{s}: implicit, shipped Newton vs without its 'stalled' exit", fontsize=10)
        for ax in axes.ravel()[len(scen):]:
            ax.axis("off")
        fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=8, frameon=False)
        fig.suptitle("Diagnostic: the implicit runs that failed or stalled, re-run with Newton's early "
                     "'stalled' exit removed (max_newton = 20 still applies)", fontsize=9)
        fig.tight_layout(rect=(0, 0.07, 1, 0.97))
        fig.savefig(img_dir / "stability_map_newton.png", dpi=130)
        plt.close(fig)

    # wall time per run
    fig, axes = plt.subplots(nrow, ncol, figsize=(7.2 * ncol, 5.2 * nrow + 0.6), squeeze=False)
    walls = [r["wall_s"] for r in recs]
    norm = LogNorm(vmin=max(min(walls), 1e-3), vmax=max(max(walls), 1e-2))
    for ax, s in zip(axes.ravel(), scen):
        g = grid(s, lambda r: max(r["wall_s"], 1e-3))
        im = ax.imshow(g, cmap="viridis", norm=norm, aspect="auto")
        for a, (f, i) in enumerate(rows):
            for b, m in enumerate(mults):
                r = index.get((s, f, i, m))
                if r is not None:
                    ax.text(b, a, f"{r['wall_s']:.2g}", ha="center", va="center", fontsize=6.5,
                            color="white" if r["wall_s"] < norm.vmax ** 0.5 * norm.vmin ** 0.5 else "black")
        ax.set_xticks(range(len(mults)), [f"{m:g}" for m in mults])
        ax.set_yticks(range(len(rows)), [f"{_label(f)} / {i[:4]}." for f, i in rows], fontsize=7.5)
        for a in range(2, len(rows), 2):
            ax.axhline(a - 0.5, color="white", lw=0.8)
        ax.set_xlabel("dt / dt_c")
        ax.set_title(f"{s}: wall time per run (s), until the end or the failure", fontsize=10)
        fig.colorbar(im, ax=ax, fraction=0.04)
    for ax in axes.ravel()[len(scen):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(img_dir / "stability_map_time.png", dpi=120)
    plt.close(fig)

    # markdown: one compact table per scenario, then every run
    short = {"stable": "ok", "newton_stalled": "stall", "inverted": "INV", "energy_blowup": "BLOW",
             "diverged_speed": "DIV-v", "diverged_nonfinite": "NaN", "timeout": "slow"}
    out = ["# Stability map results\n",
           f"Generated by `benchmarks/reliability/stability_map.py`; total wall time {data['total_wall_s']:.0f} s on "
           f"{data['machine']['cpu']} ({data['machine']['cores']} cores). Criteria and discussion: "
           "[docs/studies/stability.md](../studies/stability.md).\n",
           "Legend: ok = stable, stall = Newton stalled, INV = inverted elements left inverted "
           "(count), BLOW = energy blow-up, DIV-v = SimulationDiverged (speed limit), NaN = "
           "SimulationDiverged (non-finite), slow = timeout. After a failure: the simulated time "
           "reached; * = some implicit steps also ended with a stalled Newton solve.\n"]
    (res_dir / "stability_summary.md").write_text(summary(data) + "\n")
    for s in scen:
        sd = data["scenarios"][s]
        out.append(f"\n## {s}\n\n{sd['description']}; {sd['n_tets']} tets, {sd['n_vertices']} vertices.\n\n")
        dtc = {x["field"]: x["dt_c_s"] for x in data["setup"] if x["scenario"] == s}
        table = []
        for f, i in rows:
            cells = []
            for m in mults:
                r = index.get((s, f, i, m))
                if r is None:
                    cells.append("")
                    continue
                c = short[r["outcome"]]
                if r["outcome"] in ("diverged_speed", "diverged_nonfinite", "energy_blowup"):
                    c += f" @{r['t_reached_s'] * 1e3:.0f}ms"
                elif r["outcome"] == "inverted":
                    c += f" ({r['inverted_end']})"
                elif r["outcome"] == "newton_stalled":
                    c += f" ({r['stalled_steps']}/{r['steps_done']})"
                if r["outcome"] != "newton_stalled" and r.get("stalled_steps"):
                    c += "*"
                cells.append(c)
            table.append([f, i, f"{dtc[f] * 1e3:.3f}"] + cells)
        out.append(markdown_table(["field", "integrator", "dt_c (ms)"] + [f"{m:g} dt_c" for m in mults],
                                  table))
    rerun = [r for r in recs if "without_stall_exit" in r]
    if rerun:
        out.append("\n## Diagnostic: implicit runs re-run without Newton's early 'stalled' exit\n\n"
                   "Every implicit run that did not end stable, or had a stalled step, was run again with "
                   "the Newton solver's exit after 5 non-improving iterations removed (`stall_limit = None`) (`max_newton` = 20 "
                   "still applies). See docs/studies/stability.md.\n\n")
        diag = []
        for r in rerun:
            d = r["without_stall_exit"]
            diag.append([r["scenario"], r["field"], f"{r['multiple']:g}", short[r["outcome"]],
                         f"{r['stalled_steps']}", f"{r['max_residual_over_weight']:.2g}", short[d["outcome"]],
                         f"{d['stalled_steps']}", f"{d['max_residual_over_weight']:.2g}",
                         f"{d['max_newton_iterations']}", d["detail"].replace("|", "/")])
        out.append(markdown_table(["scenario", "field", "dt/dt_c", "shipped", "stalled steps",
                                   "max res / weight", "no stall exit", "stalled steps", "max res / weight",
                                   "max Newton it.", "detail (no stall exit)"], diag))
    out.append("\n## Every run\n\n")
    full = []
    for r in recs:
        full.append([r["scenario"], r["field"], r["integrator"], f"{r['multiple']:g}",
                     f"{r['dt_s'] * 1e3:.3g}", f"{r['steps_done']}/{r['steps_planned']}", r["outcome"],
                     f"{r['max_energy_over_input']:.3g}", f"{r['min_J_run']:.3g}", r["inverted_end"],
                     f"{r.get('max_residual_over_weight', float('nan')):.2g}"
                     if r["integrator"] == "implicit" else "",
                     f"{r['wall_s']:.2f}", r["detail"].replace("|", "/")])
    out.append(markdown_table(["scenario", "field", "integrator", "dt/dt_c", "dt (ms)", "steps", "outcome",
                               "max E/E_in", "min J", "inverted at end", "max res / weight", "wall (s)",
                               "detail"], full))
    (res_dir / "stability_map.md").write_text("".join(out))


if __name__ == "__main__":
    main()
