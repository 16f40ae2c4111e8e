"""Where along the grasp region the jaws close: hold force and exposure, mesh by mesh.

With jaws shorter than the grasp region (``scene.gripper.jaw_length``) whose ends hold
each vertex by its share inside them (``scene.gripper.jaw_ends: weighted``), where the
jaws close along the region decides what they hold: at the region's middle the tissue
on both sides of them is folded back with it; at its end, only one side is. This
measures how much that changes the force it takes to hold the tissue folded back, and
whether the default mesh follows a fine one there (the 5 % rule of
docs/studies/scene_convergence.md, which the default jaws must meet at every place they close).

Protocol, per scene and seed: the scripted baseline (``heml_gym.envs.scripted``), told to
close the jaws ``offset`` from the region's middle along its long axis (from the middle
to where the jaws' end meets the region's end), is recorded on the default mesh; the same
actions (the same gripper path) are replayed on every mesh, by the default
quasi-Newton integrator (the flap's quadratic-tet models, ``physics.field
"quadratic"``, by Newton's backward Euler in 0.025 s steps), ignoring termination. A
seed fixes E, the target and the gripper's start on every mesh. Per run: the hold force, the mean grasp force (N) over
the last ``HOLD_STEPS`` env steps (the tissue held still), and the mean exposure there.

Reported per scene and offset: each mesh's median hold force over the seeds, the worst
seed's signed force difference from the finest mesh (%), the worst seed's exposure
difference (points of exposure, a fraction) and, per mesh, how much closing at the end
changes the force and the peak gauge strain (the largest over the run) against the
middle (median and range over the seeds).

Writes docs/benchmarks/grasp_position.{json,md} and docs/img/grasp_position.png.

    python benchmarks/accuracy/grasp_position.py [tissue] [organ] [--seeds 0,1,2,3,4] [--from-json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numba
import numpy as np
from tqdm import tqdm
from heml_gym.benchmarks.common import IMAGES, RESULTS, machine_info, markdown_table, write_json
from heml_gym.benchmarks.accuracy.scene_convergence import (P2, QN, SCENE_ARGS, TOLERANCE, J, organ, record,
                                                             replay, tissue)
from heml_gym.envs import scripted

#: the last env steps of each run over which the hold force and exposure are averaged
HOLD_STEPS = 10
#: per scene: the jaws' length (m; the jaw variation of each scene, docs/studies/scene_convergence.md),
#: the offsets (m) of the jaws' centre from the grasp region's middle along its axis (the
#: last puts the jaws' end at the region's end), the meshes (the default first, the finest
#: last: the others' yardstick) and the env steps recorded
SCENES = {
    "TissueRetraction": dict(
        jaw_length=0.04, offsets=[0.0, 0.01, 0.02, 0.03, 0.04],
        models=[tissue((12, 12, 2), **QN), tissue((16, 16, 2), **QN), tissue((24, 24, 3), **QN),
                # quadratic tets: 6 x 6 x 1 has the default's nodes, 8 x 8 x 1 those of 16 x 16 x 2
                tissue((6, 6, 1), **P2, max_dt=0.025), tissue((8, 8, 1), **P2, max_dt=0.025),
                tissue((32, 32, 4), **QN)],
        steps=55),
    "OrganRetraction": dict(
        jaw_length=0.02, offsets=[0.0, 0.0025, 0.005, 0.0075, 0.01],
        models=[organ(0.010, jaw=J, **QN), organ(0.006, jaw=J, **QN), organ(0.005, jaw=J, **QN),
                organ(0.004, edge=0.0025, **QN)],
        steps=50),
}


def jaws(spec: dict) -> dict:
    """The scene changes of a scene's weighted jaws."""
    return {"gripper": {"jaw_length": spec["jaw_length"], "jaw_ends": "weighted"}}


def grasp_offset_policy(offset: float):
    """A maker of the scripted baseline of a scene (its ``policy_for``) that closes the jaws
    ``offset`` (m) from the grasp region's middle towards its low end (along y, the long
    axis of both scenes' grasp regions)."""
    def policy_for(scene):
        policy = scripted.scripted_policy(scene)
        x, y = scripted.grasp_point(scene)
        if y is None:
            raise ValueError(f"{scene.name}: its grasp region has no middle along y to offset the jaws from")
        policy.grasp_point = np.array([np.nan if x is None else x, y - offset])
        return policy
    return policy_for


def measure(scene: str, seeds) -> dict:
    """Per mesh, per offset, per seed: hold force (N), exposure, peak gauge strain, the
    solver's unconverged steps, divergence."""
    spec = SCENES[scene]
    changes = jaws(spec)
    models = spec["models"]
    out = {m.label: {f"{o:.4f}": {"hold_force_N": [], "exposure": [], "max_strain": [], "unconverged_steps": [],
                                  "diverged": []} for o in spec["offsets"]} for m in models}
    for seed in tqdm(seeds, desc=f"{scene} seeds"):
        for offset in tqdm(spec["offsets"], desc=f"seed {seed}", leave=False):
            actions, _ = record(scene, models[0], seed, spec["steps"], changes, grasp_offset_policy(offset))
            for m in models:
                run = replay(scene, m, seed, actions, changes=changes)
                cell = out[m.label][f"{offset:.4f}"]
                cell["hold_force_N"].append(float(np.mean(run["grasp_force"][-HOLD_STEPS:])))
                cell["exposure"].append(float(np.mean(run["exposure"][-HOLD_STEPS:])))
                cell["max_strain"].append(float(np.max(run["max_strain"])))
                cell["unconverged_steps"].append(int(sum(run["unconverged"])))
                cell["diverged"].append(bool(any(run["diverged"])))
    return out


def summarise(results: dict) -> dict:
    """Per mesh: the worst seed's force difference (signed, fraction) and exposure
    difference from the finest at each offset, and the end-vs-middle force change (median,
    min, max over the seeds, fractions)."""
    labels = list(results)
    finest = labels[-1]
    keys = list(results[finest])
    summary = {}
    for lab in labels:
        by = results[lab]
        f_mid, f_end = np.asarray(by[keys[0]]["hold_force_N"]), np.asarray(by[keys[-1]]["hold_force_N"])
        change = f_end / f_mid - 1.0
        s_mid, s_end = np.asarray(by[keys[0]]["max_strain"]), np.asarray(by[keys[-1]]["max_strain"])
        strain = s_end / s_mid - 1.0
        row = {"end_vs_middle": {"median": float(np.median(change)), "min": float(change.min()),
                                 "max": float(change.max())},
               "strain_end_vs_middle": {"median": float(np.median(strain)), "min": float(strain.min()),
                                        "max": float(strain.max())}}
        if lab != finest:
            force_err, exposure_err = [], []
            for key in keys:
                f, ref = np.asarray(by[key]["hold_force_N"]), np.asarray(results[finest][key]["hold_force_N"])
                err = (f - ref) / ref
                force_err.append(float(err[np.argmax(np.abs(err))]))
                exposure_err.append(float(np.max(np.abs(np.asarray(by[key]["exposure"])
                                                        - np.asarray(results[finest][key]["exposure"])))))
            row.update(force_error=force_err, exposure_error=exposure_err,
                       within=bool(max(map(abs, force_err)) <= TOLERANCE and max(exposure_err) <= TOLERANCE))
        summary[lab] = row
    return summary


def solver_report(results: dict) -> str:
    bad = [f"{lab} closing {1e3 * float(key):g} mm off the middle: {sum(c['unconverged_steps'])} unconverged steps"
           f"{', diverged' if any(c['diverged']) else ''}"
           for lab, by in results.items() for key, c in by.items() if sum(c["unconverged_steps"]) or any(c["diverged"])]
    return ("Every step of every run converged; none diverged." if not bad
            else "Runs with unconverged or diverged steps (their numbers are suspect): " + "; ".join(bad) + ".")


def tabulate(scene: str, results: dict, summary: dict, seeds) -> str:
    spec = SCENES[scene]
    labels = list(results)
    finest = labels[-1]
    header = ["jaws' centre off the middle (mm)"] + [
        f"{lab}: force (N) / vs finest / exposure diff." for lab in labels[:-1]] + [f"{finest}: force (N) / exposure"]
    rows = []
    for k, key in enumerate(results[finest]):
        row = [f"{1e3 * float(key):g}"]
        for lab in labels:
            cell = results[lab][key]
            text = f"{np.median(cell['hold_force_N']):.3f}"
            if lab != finest:
                text += f" / {100 * summary[lab]['force_error'][k]:+.1f} % / {summary[lab]['exposure_error'][k]:.3f}"
            else:
                text += f" / {np.median(cell['exposure']):.2f}"
            row.append(text)
        rows.append(row)
    change = ["force at the end vs the middle (median; range over seeds)"] + [
        f"{100 * s['end_vs_middle']['median']:+.1f} % ({100 * s['end_vs_middle']['min']:+.1f}.."
        f"{100 * s['end_vs_middle']['max']:+.1f})" for s in summary.values()]
    strain = ["peak gauge strain at the end vs the middle (median; range)"] + [
        f"{100 * s['strain_end_vs_middle']['median']:+.0f} % ({100 * s['strain_end_vs_middle']['min']:+.0f}.."
        f"{100 * s['strain_end_vs_middle']['max']:+.0f})" for s in summary.values()]
    within = ["within 5 % at every offset"] + ["yes" if s["within"] else "no" for lab, s in summary.items()
                                               if lab != finest] + ["(yardstick)"]
    rows += [change, strain, within]
    return (f"### {scene}: {1e3 * spec['jaw_length']:g} mm jaws, weighted ends\n\n"
            f"Seeds {list(seeds)}; force: the median over the seeds of the mean grasp force over the last "
            f"{HOLD_STEPS} of {spec['steps']} env steps (held still); vs finest: the worst seed's signed "
            f"force difference from {finest}; exposure diff.: the worst seed's |difference| of the mean exposure "
            f"there (a fraction).\n\n" + markdown_table(header, rows) + "\n\n" + solver_report(results))


def verdict(scene: str, summary: dict) -> str:
    """One line: does the default mesh meet the 5 % rule at every offset, and how much does
    closing at the end change the force (on the finest mesh)? ``summary``: :func:`summarise`'s."""
    labels = list(summary)
    default, finest = summary[labels[0]], summary[labels[-1]]
    return (f"{scene}: the default mesh ({labels[0]}) is {'within' if default['within'] else 'NOT within'} 5 % "
            f"of the finest at every offset (force {100 * max(map(abs, default['force_error'])):.1f} %, exposure "
            f"{max(default['exposure_error']):.3f} at worst). Closing at the region's end changes the hold force "
            f"by {100 * finest['end_vs_middle']['median']:+.1f} % (median over seeds, finest mesh; default "
            f"{100 * default['end_vs_middle']['median']:+.1f} %) and the peak gauge strain by "
            f"{100 * finest['strain_end_vs_middle']['median']:+.0f} %.")


def chart(stored: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(stored)
    fig, axes = plt.subplots(2, len(scenes), figsize=(6.2 * len(scenes), 7.6), squeeze=False)
    for col, scene in enumerate(scenes):
        for lab, by in stored[scene]["results"].items():
            mm = [1e3 * float(k) for k in by]
            axes[0, col].plot(mm, [np.median(c["hold_force_N"]) for c in by.values()], marker="o", ms=3, label=lab)
            axes[1, col].plot(mm, [np.median(c["exposure"]) for c in by.values()], marker="o", ms=3, label=lab)
        axes[0, col].set_title(f"{scene}: {1e3 * SCENES[scene]['jaw_length']:g} mm weighted jaws", fontsize=9)
        axes[0, col].set_ylabel("hold force (N), median over seeds")
        axes[1, col].set_ylabel("exposure while held, median over seeds")
        axes[1, col].set_ylim(-0.05, 1.05)
        for ax in axes[:, col]:
            ax.set_xlabel("jaws' centre from the region's middle (mm; last: at its end)")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_docs(stored: dict) -> None:
    parts, lines = [], []
    for scene, res in stored.items():
        m, summary = res["machine"], summarise(res["results"])
        parts.append(f"Generated by `benchmarks/accuracy/grasp_position.py {'tissue' if scene == 'TissueRetraction' else 'organ'}` "
                     f"in {res['wall_s'] / 60:.0f} min on one thread of {m['cpu']} ({m['vector_isa']}, {m['date']}).\n\n"
                     + tabulate(scene, res["results"], summary, res["seeds"]))
        lines.append(verdict(scene, summary))
    md = ("Where the jaws close along the grasp region (method: the script's docstring). "
          "Not the default task: both envs' default jaws hold the whole region.\n\n"
          + "\n\n".join(f"- {line}" for line in lines) + "\n\n" + "\n\n".join(parts)
          + "\n\n![hold force vs where the jaws close](../img/grasp_position.png)\n")
    (RESULTS / "grasp_position.md").write_text(md)
    chart(stored, IMAGES / "grasp_position.png")
    print(md)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*", help="tissue and/or organ (default: both)")
    ap.add_argument("--seeds", default="0,1,2,3,4", help="comma-separated episode seeds (default 0,1,2,3,4)")
    ap.add_argument("--from-json", action="store_true", help="rebuild the tables and chart from the stored runs")
    args = ap.parse_args(argv)
    unknown = [name for name in args.scenes if name not in SCENE_ARGS]
    if unknown:
        ap.error(f"scenes: {', '.join(SCENE_ARGS)}, got {', '.join(map(repr, unknown))}")
    path = RESULTS / "grasp_position.json"
    stored = json.loads(path.read_text())["scenes"] if path.exists() else {}
    if not args.from_json:
        try:
            seeds = [int(s) for s in args.seeds.split(",")]
        except ValueError:
            ap.error(f"--seeds: comma-separated integers, got {args.seeds!r}")
        numba.set_num_threads(1)
        for name in args.scenes or list(SCENE_ARGS):
            scene = SCENE_ARGS[name]
            start = time.perf_counter()
            results = measure(scene, seeds)
            stored[scene] = {"machine": machine_info(), "wall_s": time.perf_counter() - start, "seeds": seeds,
                             "jaw_length_m": SCENES[scene]["jaw_length"], "jaw_ends": "weighted",
                             "hold_steps": HOLD_STEPS, "steps": SCENES[scene]["steps"], "results": results,
                             "summary": summarise(results)}
            write_json("grasp_position.json", {"scenes": stored}, envs=list(stored))
    elif not stored:
        ap.error(f"--from-json: nothing stored at {path}")
    write_docs(stored)


if __name__ == "__main__":
    main()
