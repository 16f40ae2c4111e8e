"""Quadratic tets by Newton or by L-BFGS: the same backward Euler steps, their cost.

Quadratic (10-node) tets drape the flap where its default linear ones are too stiff
(docs/studies/status.md), but until 2026-11-28 only Newton's backward Euler stepped them. Since
then ``physics={"field": "quadratic", "integrator": "quasi_newton"}`` minimises the same
incremental potential by L-BFGS (``heml_gym.ImplicitSolver(method="lbfgs")``: one
factorised scalar initial Hessian per world instead of the field's Hessian assembled and
solved at every iteration).

Protocol, per case and seed: the scripted baseline's actions are recorded on the scene's
default (linear) mesh and replayed on each quadratic model by Newton
(``integrator="implicit"``) and by L-BFGS (``"quasi_newton"``), both to the same tolerance
(``newton_tol`` 3e-3 of the weight), one after the other in one process on one thread,
ignoring termination. Cases: the flap's default task (jaws holding the whole grasp line),
the flap with 40 mm weighted jaws closed at the grasp region's end (``grasp_position.py``'s
hardest place: the unheld side drapes), and the lobe's default task on uniform quadratic
meshes (16 and 12 mm).

Reported per case and model: CPU ms per env step for each solver (median over the steps
of every seed) and their ratio, iterations per env step (mean), how far apart the two
runs are (the worst seed's largest grasp-force difference over the run, relative to the
Newton run's largest force, and its largest exposure difference), the steps either left
unconverged and where either diverged (a run stops there). The two minimise the same
potential, so they differ by their tolerance only.

Writes docs/benchmarks/quadratic_solvers.{json,md} and docs/img/quadratic_solvers.png.

    python benchmarks/speed/quadratic_solvers.py [--seeds 0,1,2] [--from-json]
"""

from __future__ import annotations

import argparse
import time

import numba
import numpy as np
from heml_gym.benchmarks.common import (IMAGES, command_line, generated_by, machine_info, markdown_table,
                                       store_and_report)

NAME = "quadratic_solvers"
ENVS = ["heml_gym/TissueRetraction-v1", "heml_gym/OrganRetraction-v2"]
#: the solvers compared: integrator, iterations at most per (sub-)step
SOLVERS = {"Newton": ("implicit", 20), "L-BFGS": ("quasi_newton", 200)}
#: the flap's quadratic models: cells, step (s); the lobe's: mesh size (m, uniform), step (s)
FLAP_MODELS = [((6, 6, 1), 0.05), ((6, 6, 1), 0.025), ((8, 8, 1), 0.05), ((8, 8, 1), 0.025)]
LOBE_MODELS = [(0.016, 0.05), (0.012, 0.05)]
#: env steps replayed per scene
STEPS = {"TissueRetraction": 55, "OrganRetraction": 40}
TOL = 3e-3


def cases():
    """name -> (scene, scene changes, the scripted baseline's maker, the default (linear)
    model it is recorded on, the quadratic models: (label, maker of a model of an integrator))."""
    from heml_gym.benchmarks.accuracy.grasp_position import SCENES, grasp_offset_policy, jaws
    from heml_gym.benchmarks.accuracy.scene_convergence import QN, organ, tissue
    from heml_gym.envs import scripted
    from heml_gym.envs.organ_retraction import DEFAULT_JAW_SIZE

    def flap(cells, dt):
        return lambda integrator, max_newton: tissue(cells, field="quadratic", integrator=integrator, max_dt=dt,
                                                     newton_tol=TOL, max_newton=max_newton)

    def lobe(size, dt):
        return lambda integrator, max_newton: organ(size, field="quadratic", integrator=integrator, max_dt=dt,
                                                    newton_tol=TOL, max_newton=max_newton)

    flaps = [(f"{'x'.join(map(str, c))} quadratic, {dt:g} s steps", flap(c, dt)) for c, dt in FLAP_MODELS]
    lobes = [(f"{1e3 * s:g} mm quadratic (uniform), {dt:g} s steps", lobe(s, dt)) for s, dt in LOBE_MODELS]
    spec = SCENES["TissueRetraction"]
    flap_default = tissue((12, 12, 2), **QN)
    return {"flap, default task": ("TissueRetraction", {}, scripted.scripted_policy, flap_default, flaps),
            "flap, 40 mm weighted jaws at the region's end": ("TissueRetraction", jaws(spec),
                                                              grasp_offset_policy(spec["offsets"][-1]), flap_default,
                                                              flaps),
            "lobe, default task": ("OrganRetraction", {}, scripted.scripted_policy,
                                   organ(0.010, jaw=DEFAULT_JAW_SIZE, **QN), lobes)}


def measure(seeds) -> dict:
    from tqdm import tqdm

    from heml_gym.benchmarks.accuracy.scene_convergence import record

    numba.set_num_threads(1)
    out = {}
    for case, (scene, changes, policy_for, default, models) in cases().items():
        out[case] = {}
        for seed in tqdm(seeds, desc=case):
            actions, _ = record(scene, default, seed, STEPS[scene], changes or None, policy_for)
            for label, make in models:
                cell = out[case].setdefault(label, {s: {"cpu_s": [], "iterations": [], "force": [], "exposure": [],
                                                        "unconverged": [], "diverged_at": []} for s in SOLVERS})
                for solver, (integrator, max_newton) in SOLVERS.items():
                    run = replay(make(integrator, max_newton).env(scene, changes or None), seed, actions)
                    rec = cell[solver]
                    for key in ("cpu_s", "iterations", "force", "exposure"):
                        rec[key].append(run[key])
                    rec["unconverged"].append(run["unconverged"])
                    rec["diverged_at"].append(run["diverged_at"])
    return out


def replay(env, seed: int, actions) -> dict:
    """Per env step of ``actions`` from ``env.reset(seed)``: CPU s, solver iterations, grasp
    force (N), exposure; the steps left unconverged, and the step at which the simulation
    diverged (the run stops there; None: it did not)."""
    env.reset(seed=seed)
    run = {"cpu_s": [], "iterations": [], "force": [], "exposure": [], "unconverged": 0, "diverged_at": None}
    for k, a in enumerate(actions):
        started = time.thread_time()
        _, _, _, _, info = env.step(a)
        if info["simulation_diverged"]:
            run["diverged_at"] = k
            break
        run["cpu_s"].append(time.thread_time() - started)
        run["iterations"].append(int(info["newton_iterations"]))
        run["force"].append(float(info["grasp_force"]))
        run["exposure"].append(float(info["exposure"]))
        run["unconverged"] += not bool(info["solver_converged"])
    return run


def summarise(results: dict, seeds) -> dict:
    summary = {}
    for case, models in results.items():
        summary[case] = {}
        for label, runs in models.items():
            n, q = runs["Newton"], runs["L-BFGS"]
            ms = {s: 1e3 * float(np.median(np.concatenate(r["cpu_s"]))) for s, r in runs.items()}
            # (over the steps both ran: a run stops where it diverged)
            force_gap = max(float(np.max(np.abs(np.subtract(fq[:len(fn)], fn[:len(fq)]))) / np.max(fn))
                            for fn, fq in zip(n["force"], q["force"]))
            exposure_gap = max(float(np.max(np.abs(np.subtract(eq[:len(en)], en[:len(eq)]))))
                               for en, eq in zip(n["exposure"], q["exposure"]))
            summary[case][label] = {
                "ms_per_step": ms, "speedup": ms["Newton"] / ms["L-BFGS"],
                "iterations_per_step": {s: float(np.mean(np.concatenate(r["iterations"]))) for s, r in runs.items()},
                "force_gap": force_gap, "exposure_gap": exposure_gap,
                "unconverged_steps": {s: int(sum(r["unconverged"])) for s, r in runs.items()},
                "diverged": {s: [f"seed {seed} step {k}" for seed, k in zip(seeds, r["diverged_at"]) if k is not None]
                             for s, r in runs.items()}}
    return summary


def report(data: dict) -> str:
    text = (f"{generated_by(data)}: the flap (TissueRetraction-v1's scene) and the lobe (OrganRetraction-v2's) on "
            f"quadratic tets, the scripted baseline's path (recorded on the default linear mesh; env steps: "
            f"{', '.join(f'{k} {v}' for k, v in data['steps'].items())}) replayed by each "
            f"solver to {data['newton_tol']:g} of the weight, seeds {data['seeds']}, one thread. "
            "CPU ms: median over the env steps of every seed; gaps: the worst seed's largest difference "
            "between the two runs (force relative to the Newton run's largest).\n\n")
    for case, models in data["summary"].items():
        rows = []
        for label, s in models.items():
            rows.append([label, f"{s['ms_per_step']['Newton']:.1f}", f"{s['ms_per_step']['L-BFGS']:.1f}",
                         f"{s['speedup']:.1f}x", f"{s['iterations_per_step']['Newton']:.1f}",
                         f"{s['iterations_per_step']['L-BFGS']:.1f}", f"{100 * s['force_gap']:.2f} %",
                         f"{s['exposure_gap']:.3f}",
                         f"{s['unconverged_steps']['Newton']} / {s['unconverged_steps']['L-BFGS']}",
                         " / ".join(", ".join(s["diverged"][k]) or "none" for k in SOLVERS)])
        text += f"**{case[0].upper() + case[1:]}**\n\n" + markdown_table(
            ["model", "Newton CPU ms/step", "L-BFGS CPU ms/step", "L-BFGS faster", "Newton iterations/step",
             "L-BFGS iterations/step", "force gap", "exposure gap", "unconverged steps (Newton / L-BFGS)",
             "diverged (Newton / L-BFGS)"], rows) + "\n"
    if data.get("note"):
        text += f"{data['note']}\n\n"
    return text + f"![CPU ms per env step, Newton and L-BFGS](../img/{NAME}.png)\n"


def plot(data: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases_ = list(data["summary"])
    fig, axes = plt.subplots(1, len(cases_), figsize=(4.6 * len(cases_), 3.6), sharey=True)
    for ax, case in zip(np.atleast_1d(axes), cases_):
        models = data["summary"][case]
        x = np.arange(len(models))
        for k, solver in enumerate(SOLVERS):
            ax.bar(x + (k - 0.5) * 0.38, [m["ms_per_step"][solver] for m in models.values()], 0.38,
                   label=solver, color=f"C{k}")
        ax.set_xticks(x, [lab.replace(" quadratic, ", "\n").replace(" quadratic (uniform), ", "\n")
                          for lab in models], fontsize=8)
        ax.set_yscale("log")
        ax.set_title(case, fontsize=9)
        ax.grid(axis="y", alpha=0.3)
    np.atleast_1d(axes)[0].set_ylabel("CPU ms per env step (one thread)")
    np.atleast_1d(axes)[0].legend(fontsize=8)
    m = data["machine"]
    fig.suptitle(f"Quadratic tets: Newton vs L-BFGS backward Euler ({m['cpu']}, {m.get('vector_isa', '?')})",
                 fontsize=9)
    fig.tight_layout()
    IMAGES.mkdir(parents=True, exist_ok=True)
    fig.savefig(IMAGES / f"{NAME}.png", dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2", help="seeds, comma-separated")
    ap.add_argument("--note", default="", help="a line stored with the result (e.g. what else ran on the machine)")
    ap.add_argument("--from-json", action="store_true", help="only rebuild the table and chart from the stored result")
    args = ap.parse_args(argv)
    if args.from_json:
        data = store_and_report(NAME, None, report)
    else:
        try:
            seeds = [int(v) for v in args.seeds.split(",")]
        except ValueError:
            ap.error(f"--seeds must be integers separated by commas, got {args.seeds!r}")
        started = time.perf_counter()
        results = measure(seeds)
        data = {"machine": machine_info(), "command": command_line(f"heml_gym.benchmarks.speed.{NAME}", ap, args,
                                                              leave_out=("from_json", "note")),
                "seeds": seeds, "steps": STEPS, "newton_tol": TOL, "wall_s": time.perf_counter() - started,
                "note": args.note, "summary": summarise(results, seeds)}
        data = store_and_report(NAME, data, report, envs=ENVS)
    plot(data)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
