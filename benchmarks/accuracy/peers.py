"""Peers on the speed-vs-accuracy cantilever: NVIDIA Newton (CPU) and MuJoCo 3D flex.

Same scene, meshes, error measure and references as ``benchmarks/accuracy/speed_accuracy.py``
(dynamic case: released straight, no damping, 1 s, RMS tip-z error relative to the peak
deflection of the extrapolated reference of the same law). Needs ``pip install newton
mujoco`` (newton pulls warp-lang; both run on CPU here), e.g. in a virtual environment
made with ``--system-site-packages`` so that heml_gym is importable.

Laws, checked on a deformed mesh against heml_gym's forces before any run (the force
differences are stored in the JSON):

* Newton ``SolverSemiImplicit`` (symplectic Euler, tet FEM kernel ``eval_tetrahedra``):
  Stable Neo-Hookean ``mu/2 (I1-3) - mu/2 ln(I1+1) + lam/2 (J-alpha)^2``,
  ``alpha = 1 + 3 mu / (4 lam)``, with ``k_mu, k_lambda`` used as that energy's own
  constants: exactly heml_gym's ``StableNeoHookean``, so we pass its native ``mu, lam``
  (from E, nu by Smith et al.'s ``mu = 4/3 mu_L``, ``lam = lam_L + 5/6 mu_L``).
* Newton ``SolverVBD``: ``mu/2 (I1-3) + lam'/2 (J-alpha)^2`` with ``lam' = k_lambda +
  k_mu``, ``alpha = 1 + mu/lam'`` (no log term): a different law that heml_gym does not
  have. We pass the Lamé constants ``k_mu = mu_L, k_lambda = lam_L`` (VBD's own mapping
  then matches E, nu at small strain) and compare with the Stable Neo-Hookean reference,
  labelled as a different law.
* MuJoCo ``<flex dim="3">`` with ``<elasticity young= poisson=>``: Saint Venant-Kirchhoff
  P1 (quadratic in the squared edge-length changes), the same as heml_gym's
  ``StVenantKirchhoff(E, nu)``. Vertices are bodies with three slide joints and
  mass ``rho V / 4`` (our lumping); clamped vertices are bodies without joints.
  Integrators: ``Euler`` (flex elasticity explicit: sub-stepped at safety x our critical
  step) and ``discrete`` (velocity update in the metric ``M + h D + h^2 K``).

    python benchmarks/accuracy/peers.py [--quick] [--cap-s 45]

Writes docs/benchmarks/speed_accuracy_peers.json and .md, docs/img/speed_accuracy_peers.png.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm
import heml_gym as hg
from heml_gym.benchmarks.accuracy import speed_accuracy as sa
from heml_gym.benchmarks.common import IMAGES, RESULTS, machine_info, markdown_table, with_tasks, write_json
from heml_gym import materials as M

SNH, STVK = "Stable Neo-Hookean", "StVK"


def peer_config(quick: bool) -> dict:
    base = sa.quick_config() if quick else sa.full_config()
    return {
        **base,
        "meshes": [5, 10] if quick else [10, 20, 30, 40],
        "safety": 0.5,
        "vbd_dt": [1 / 60, 1 / 240],
        "vbd_iterations": [10, 50],
        "mujoco_discrete_dt": [1 / 60, 1 / 240],
        "heml_implicit_dt": [1 / 60, 1 / 240],
    }


# ----------------------------------------------------------------------------- Newton
def newton_model(cant: sa.Cantilever, k_mu: float, k_lambda: float, vbd: bool):
    import newton
    import warp as wp

    b = newton.ModelBuilder(up_axis=newton.Axis.Z, gravity=tuple(sa.GRAVITY))
    b.add_soft_mesh(pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
                    vertices=[wp.vec3(*map(float, v)) for v in cant.mesh.vertices],
                    indices=cant.mesh.tets.ravel().tolist(), density=sa.RHO, k_mu=k_mu, k_lambda=k_lambda,
                    k_damp=0.0, add_surface_mesh_edges=False)
    for i in cant.fixed:  # zero mass = not integrated
        b.particle_mass[i] = 0.0
    if vbd:
        b.color()
    model = b.finalize(device="cpu")
    model.particle_grid = None  # no particle-particle contact
    return model


def newton_solver(model, kind: str, iterations: int = 10):
    import newton

    if kind == "semi-implicit":
        return newton.solvers.SolverSemiImplicit(model, enable_tri_contact=False)
    return newton.solvers.SolverVBD(model, iterations=iterations, particle_enable_self_contact=False)


def newton_force_check(cant: sa.Cantilever) -> float:
    """Max |f_newton - f_heml| / max |f_heml| for the semi-implicit tet kernel (SNH)."""
    import warp as wp
    from newton._src.solvers.semi_implicit.kernels_particle import eval_tetrahedra_forces

    mat = sa.LAWS[SNH]()
    model = newton_model(cant, mat.mu, mat.lam, vbd=False)
    state = model.state()
    x = deformed(cant)
    state.particle_q.assign(x.astype(np.float32))
    f = wp.zeros(model.particle_count, dtype=wp.vec3, device="cpu")
    eval_tetrahedra_forces(model, state, model.control(), f)
    fh = hg.HemlForce(cant.mesh, mat).forces(x)
    return float(np.abs(f.numpy() - fh).max() / np.abs(fh).max())


def deformed(cant: sa.Cantilever) -> np.ndarray:
    rng = np.random.default_rng(0)
    x = cant.mesh.vertices * np.array([1.05, 0.97, 0.98]) + 0.02 * cant.mesh.min_edge_length * rng.standard_normal(
        cant.mesh.vertices.shape)
    x[cant.fixed] = cant.mesh.vertices[cant.fixed]
    return x


# ----------------------------------------------------------------------------- MuJoCo
def mujoco_model(cant: sa.Cantilever, integrator: str, h: float):
    import mujoco

    v, mass = cant.mesh.vertices, sa.RHO * cant.mesh.vertex_volumes
    fixed = np.zeros(len(v), dtype=bool)
    fixed[cant.fixed] = True
    bodies = []
    for i, p in enumerate(v):
        pos = " ".join(repr(float(c)) for c in p)
        if fixed[i]:
            bodies.append(f'<body name="v{i}" pos="{pos}"/>')
        else:
            bodies.append(
                f'<body name="v{i}" pos="{pos}"><joint type="slide" axis="1 0 0"/><joint type="slide" axis="0 1 0"/>'
                f'<joint type="slide" axis="0 0 1"/><inertial pos="0 0 0" mass="{float(mass[i])!r}" '
                f'diaginertia="1e-12 1e-12 1e-12"/></body>')
    g = " ".join(repr(float(c)) for c in sa.GRAVITY)
    xml = (f'<mujoco><option gravity="{g}" timestep="{h!r}" integrator="{integrator}"/>'
           f'<worldbody>{"".join(bodies)}</worldbody><deformable>'
           f'<flex name="beam" dim="3" body="{" ".join(f"v{i}" for i in range(len(v)))}" '
           f'element="{" ".join(map(str, cant.mesh.tets.ravel()))}">'
           f'<elasticity young="{sa.E!r}" poisson="{sa.NU!r}" damping="0"/>'
           f'<contact contype="0" conaffinity="0"/></flex></deformable></mujoco>')
    model = mujoco.MjModel.from_xml_string(xml)
    free = np.flatnonzero(~fixed)
    return model, free


def mujoco_force_check(cant: sa.Cantilever) -> float:
    import mujoco

    model, free = mujoco_model(cant, "Euler", 1e-4)
    data = mujoco.MjData(model)
    x = deformed(cant)
    data.qpos[:] = (x[free] - cant.mesh.vertices[free]).ravel()
    mujoco.mj_forward(model, data)
    fh = hg.HemlForce(cant.mesh, sa.LAWS[STVK]()).forces(x)[free]
    return float(np.abs(data.qfrc_passive.reshape(-1, 3) - fh).max() / np.abs(fh).max())


# ------------------------------------------------------------------------------ runs
def timed_run(step_frame, tip_z, frames: int, cap_s: float):
    """Step ``frames`` frames; abort (projecting the cost) past ``cap_s``; stop on blow-up."""
    z = np.zeros(frames + 1)
    t = time.perf_counter()
    for k in range(frames):
        step_frame()
        z[k + 1] = tip_z()
        if not np.isfinite(z[k + 1]) or abs(z[k + 1]) > 10 * sa.LENGTH:
            return {"status": "diverged", "diverged_at_s": (k + 1) / frames, "wall_s": time.perf_counter() - t}
        elapsed = time.perf_counter() - t
        if elapsed > 2.0 and elapsed / (k + 1) * frames > cap_s:
            return {"status": "over_cap", "projected_wall_s": elapsed / (k + 1) * frames, "wall_s": elapsed}
    return {"status": "ok", "wall_s": time.perf_counter() - t, "tip_z": z.tolist()}


def critical_dt(cant: sa.Cantilever, law: str) -> float:
    sim = cant.simulation(hg.HemlForce(cant.mesh, sa.LAWS[law]()), integrator="explicit")
    return sim.critical_dt()


def run_newton(cant, kind, cfg, cap_s, dt=None, iterations=10):
    import warp as wp

    mat = sa.LAWS[SNH]()
    if kind == "semi-implicit":
        k_mu, k_lambda = mat.mu, mat.lam
        frame = cfg["explicit_frame"]
        dt_c = critical_dt(cant, SNH)
        sub = max(1, math.ceil(frame / (cfg["safety"] * dt_c)))
    else:
        k_mu, k_lambda = M.lame_from_young(sa.E, sa.NU)
        frame, sub, dt_c = dt, 1, None
    t0 = time.perf_counter()
    model = newton_model(cant, k_mu, k_lambda, vbd=kind == "VBD")
    solver = newton_solver(model, kind, iterations)
    state = [model.state(), model.state()]
    control = model.control()
    setup = time.perf_counter() - t0
    h = frame / sub

    def step_frame():
        for _ in range(sub):
            state[0].clear_forces()
            solver.step(state[0], state[1], control, None, h)
            state.reverse()

    def tip_z():
        return cant.tip_z(state[0].particle_q.numpy().astype(np.float64))

    wp.synchronize()
    step_frame()  # warm-up (kernel loads), then restart from rest
    state[0] = model.state()
    state[1] = model.state()
    res = timed_run(step_frame, tip_z, round(cfg["duration"] / frame), cap_s)
    name = "Newton semi-implicit" if kind == "semi-implicit" else "Newton VBD"
    label = (f"explicit s={cfg['safety']:g}" if kind == "semi-implicit"
             else f"VBD {iterations} it. dt=1/{round(1 / dt)}")
    law = SNH
    return {"field": name, "law": law, "config": label, "law_note": (
        "same law and constants as heml_gym StableNeoHookean" if kind == "semi-implicit"
        else "VBD's own Neo-Hookean (no log term, lam' = lam + mu): a different law, same E, nu at small strain"),
        "frame_dt": frame, "substeps_per_frame": sub, "critical_dt": dt_c, "setup_s": setup,
        "k_mu": k_mu, "k_lambda": k_lambda, "precision": "float32", **res}


def run_mujoco(cant, integrator, cfg, cap_s, dt=None):
    import mujoco

    if integrator == "Euler":
        frame = cfg["explicit_frame"]
        dt_c = critical_dt(cant, STVK)
        sub = max(1, math.ceil(frame / (cfg["safety"] * dt_c)))
    else:
        frame, sub, dt_c = dt, 1, None
    t0 = time.perf_counter()
    model, free = mujoco_model(cant, integrator, frame / sub)
    data = mujoco.MjData(model)
    setup = time.perf_counter() - t0
    tip = np.flatnonzero(np.isin(free, cant.tip))

    def step_frame():
        for _ in range(sub):
            mujoco.mj_step(model, data)

    def tip_z():
        return float(data.qpos.reshape(-1, 3)[tip, 2].mean())

    step_frame()
    mujoco.mj_resetData(model, data)
    res = timed_run(step_frame, tip_z, round(cfg["duration"] / frame), cap_s)
    label = f"explicit s={cfg['safety']:g}" if integrator == "Euler" else f"discrete dt=1/{round(1 / dt)}"
    return {"field": "MuJoCo flex", "law": STVK, "config": label, "integrator": integrator,
            "law_note": "flex dim=3 elasticity: StVK, same as heml_gym StVenantKirchhoff(E, nu)",
            "frame_dt": frame, "substeps_per_frame": sub, "critical_dt": dt_c, "setup_s": setup,
            "precision": "float64", **res}


def run_heml(cant, law, cfg, cap_s, integrator, dt=None):
    row = sa.run_dynamic("HEML", law, cant.n, integrator, cfg, cap_s,
                         safety=cfg["safety"] if integrator == "explicit" else None, dt=dt)
    row["config"] = sa.config_label(row)
    row["frame_dt"] = row["frame_dt"]
    return row


def add_errors(rows, ref):
    for r in rows:
        if r.get("status") != "ok":
            continue
        d = ref["dynamic"][r["law"]]
        stride = round(r["frame_dt"] * d["rate_hz"])
        zr = np.asarray(d["tip_z"])[::stride]
        z = np.asarray(r["tip_z"])
        r["error"] = sa.rms_rel(z[1:], zr[1: len(z)], d["amplitude_m"])
        r["cost_s"] = r["wall_s"] / d["duration_s"]
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--cap-s", type=float, default=45.0)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--report", action="store_true", help="only redraw the chart and table from the saved JSON")
    args = ap.parse_args(argv)
    cfg = peer_config(args.quick)
    if args.out is not None:
        out_dir = img_dir = args.out
    elif args.quick:
        out_dir = img_dir = Path("/tmp/speed_accuracy_quick")
    else:
        out_dir, img_dir = RESULTS, IMAGES
    out_dir.mkdir(parents=True, exist_ok=True)
    if args.report:
        data = json.loads((out_dir / "speed_accuracy_peers.json").read_text())
        ref = json.loads((out_dir / "speed_accuracy_reference.json").read_text())
        write_report(data, ref, out_dir, img_dir)
        return
    t_start = time.perf_counter()
    ref = sa.load_reference(out_dir / "speed_accuracy_reference.json", cfg, [SNH, STVK], [SNH, STVK])

    import mujoco
    import newton
    import warp as wp

    wp.config.quiet = True
    versions = {"newton": newton.__version__, "warp": wp.__version__, "mujoco": mujoco.__version__}
    check_cant = sa.Cantilever(cfg["meshes"][0])
    checks = {"newton_semi_implicit_vs_heml_snh": newton_force_check(check_cant),
              "mujoco_flex_vs_heml_stvk": mujoco_force_check(check_cant)}
    print("force checks (max rel. difference):", checks)
    sa.warm_up([SNH, STVK])
    jobs = []
    for n in cfg["meshes"]:
        jobs.append(("newton", n, "semi-implicit", None, None))
        jobs += [("newton", n, "VBD", dt, it) for dt in cfg["vbd_dt"] for it in cfg["vbd_iterations"]]
        jobs.append(("mujoco", n, "Euler", None, None))
        jobs += [("mujoco", n, "discrete", dt, None) for dt in cfg["mujoco_discrete_dt"]]
        for law in (SNH, STVK):
            jobs.append(("heml", n, law, "explicit", None))
            jobs += [("heml", n, law, "implicit", dt) for dt in cfg["heml_implicit_dt"]]
    rows = []
    for engine, n, a, b, c in tqdm(jobs, desc="peers", unit="run"):
        cant = sa.Cantilever(n)
        if engine == "newton":
            row = run_newton(cant, a, cfg, args.cap_s, dt=b, iterations=c or 10)
        elif engine == "mujoco":
            row = run_mujoco(cant, a, cfg, args.cap_s, dt=b)
        else:
            row = run_heml(cant, a, cfg, args.cap_s, b, dt=c)
        row.update({"n": n, "cells": cant.cells, "n_tets": cant.mesh.n_tets})
        rows.append(row)
    add_errors(rows, ref)
    data = {"machine": machine_info(), "versions": versions, "force_checks": checks, "config": cfg,
            "cap_s": args.cap_s, "wall_s": time.perf_counter() - t_start, "results": rows}
    data = with_tasks(data, envs=())  # physics only: no task
    write_json("speed_accuracy_peers.json", data, folder=out_dir)
    write_report(data, ref, out_dir, img_dir)


def write_report(data, ref, out_dir, img_dir):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    rows = data["results"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.8))
    markers = {"explicit": "o", "implicit": "v", "VBD": "s", "discrete": "^"}
    for ax, law in zip(axes, (SNH, STVK)):
        pts = [r for r in rows if r["law"] == law and "error" in r]
        for r in pts:
            kind = r["config"].split()[0]
            face = "none" if "VBD 50" in r["config"] or "1/240" in r["config"] else sa.FIELD_COLORS.get(r["field"], "k")
            ax.scatter(r["cost_s"], r["error"], marker=markers.get(kind, "*"), s=30,
                       edgecolors=sa.FIELD_COLORS.get(r["field"], "k"), facecolors=face, zorder=3)
            ax.annotate(f"{r['n']}", (r["cost_s"], r["error"]), fontsize=5, xytext=(2, 2),
                        textcoords="offset points")
        front = sa.pareto([(r["cost_s"], r["error"]) for r in pts])
        if front:
            ax.step([pts[i]["cost_s"] for i in front], [pts[i]["error"] for i in front], where="post",
                    color="k", ls="--", lw=1)
            ax.scatter([pts[i]["cost_s"] for i in front], [pts[i]["error"] for i in front], s=80,
                       facecolors="none", edgecolors="k")
        ax.axhspan(1e-12, ref["dynamic"][law]["uncertainty_rel"], color="0.85", zorder=0)
        ax.set_xscale("log")
        ax.set_yscale("log")
        lo = min([ref["dynamic"][law]["uncertainty_rel"]] + [r["error"] for r in pts])
        ax.set_ylim(0.5 * lo, 5)
        ax.set_xlabel("wall time per simulated second (s)")
        ax.set_ylabel("RMS tip-z error / peak deflection")
        title = {SNH: "Stable Neo-Hookean (Newton VBD: its own law, see text)",
                 STVK: "StVK (MuJoCo flex = StVK)\nreference NOT converged (grey band): compare costs"}[law]
        ax.set_title(f"dynamic, {title}", fontsize=9)
        ax.grid(True, which="both", alpha=0.25)
    handles = [Line2D([], [], color=sa.FIELD_COLORS[f], marker="s", ls="", label=f)
               for f in ("HEML", "Newton semi-implicit", "Newton VBD", "MuJoCo flex")]
    handles += [Line2D([], [], color="0.3", marker=m, ls="", label=k) for k, m in markers.items()]
    handles += [Line2D([], [], color="0.3", marker="o", mfc="none", ls="",
                       label="hollow: dt=1/240 or VBD 50 it."),
                Line2D([], [], color="k", marker="o", mfc="none", ls="--", label="Pareto front")]
    fig.legend(handles=handles, loc="lower center", ncol=6, fontsize=7, frameon=False)
    fig.suptitle("Peers on the cantilever, dynamic (labels: cells along x; CPU)", fontsize=10)
    fig.tight_layout(rect=(0, 0.09, 1, 0.95))
    fig.savefig(img_dir / "speed_accuracy_peers.png", dpi=130)
    plt.close(fig)

    hdr = ["law", "engine", "mesh", "tets", "integrator", "wall per simulated s (s)", "error", "notes"]
    table = []
    for law in (SNH, STVK):
        rs = sorted([r for r in rows if r["law"] == law],
                    key=lambda r: (r.get("cost_s", r.get("projected_wall_s", 1e99)), r["field"]))
        for r in rs:
            mesh = "x".join(map(str, r["cells"]))
            note = r.get("law_note", "")
            if r.get("status") == "ok":
                table.append([law, r["field"], mesh, r["n_tets"], r["config"], f"{r['cost_s']:.3g}",
                              f"{100 * r['error']:.3g} %", note])
            elif r.get("status") == "over_cap":
                table.append([law, r["field"], mesh, r["n_tets"], r["config"],
                              f"(~{r['projected_wall_s']:.0f}, projected)", "-",
                              f"not completed: over the {data['cap_s']:g} s cap"])
            else:
                table.append([law, r["field"], mesh, r["n_tets"], r["config"], "-", "-",
                              f"diverged at t = {r.get('diverged_at_s', float('nan')):.3f} s"])
    text = (f"# Peers on the cantilever ({data['machine']['cpu']}, {data['machine']['cores']} cores; "
            f"newton {data['versions']['newton']}, warp {data['versions']['warp']}, "
            f"mujoco {data['versions']['mujoco']})\n\n"
            "Generated by `benchmarks/accuracy/peers.py`; see `docs/studies/speed_accuracy.md`. Force checks against heml_gym "
            "on a deformed mesh (max relative difference): "
            + ", ".join(f"{k} {v:.1e}" for k, v in data["force_checks"].items()) + "\n\n"
            + markdown_table(hdr, table))
    (out_dir / "speed_accuracy_peers.md").write_text(text)


if __name__ == "__main__":
    main()
