"""How the flap's holding force follows the jaws' length, mesh by mesh.

``scene.gripper.jaw_length`` (m) makes closed jaws hold only the part of the grasp edge
within ``jaw_length / 2`` of them (:meth:`heml_gym.envs.scene.GripperSpec`). A mesh holds
whole vertices, so on every mesh the held part, and the force it takes to hold the flap
folded back, is a staircase in the jaws' length whose treads are two vertex spacings
wide: on the default 12 x 12 x 2 mesh every length from 32 to 42 mm holds the same
three vertices. This measures the staircase: per seed, the scripted fold recorded on
the default mesh with 40 mm jaws (its grasp at the same place for every length) is
replayed for every jaw length on each mesh (all by the default quasi-Newton integrator,
so only the mesh differs); the hold force is the mean grasp force (N) over env steps
21..30, while the flap is held folded back (before the first episode ends: the scripted
episodes last 39-46 steps).

With ``--jaw-ends weighted`` (``scene.gripper.jaw_ends``): the jaws hold each edge
vertex by its share of the edge inside them (the end vertices in part, by springs), so
the held length, and the force, should follow the jaws' length on every mesh.

Writes docs/benchmarks/jaw_length.{json,md} and docs/img/jaw_length.png
(``jaw_length_weighted.*`` with weighted ends).

    python benchmarks/accuracy/jaw_length.py [--jaw-ends weighted] [--from-json]   # ~7 min on one thread
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
from heml_gym.benchmarks.accuracy.scene_convergence import QN, record, replay, tissue

SCENE = "TissueRetraction"
#: the meshes, coarsest (the default) first; the last is the finest, the others' yardstick
MESHES = [(12, 12, 2), (16, 16, 2), (24, 24, 3), (32, 32, 4)]
#: jaw lengths (m) replayed; 40 mm is ``configs/experiments/quick_jaws_adhesion.yaml``'s
LENGTHS = [round(0.024 + 0.002 * k, 3) for k in range(17)]
RECORDED_LENGTH = 0.04
HOLD_STEPS = slice(20, 30)  # env steps 21..30


def measure(seeds, ends: str = "vertex") -> dict:
    """Per mesh, per jaw length, per seed: held vertices and hold force (N), the jaws'
    ends ``ends`` (``gripper.jaw_ends``)."""
    models = [tissue(cells, **QN) for cells in MESHES]
    out = {m.label: {f"{L:.3f}": {"held": [], "hold_force_N": [], "unconverged_steps": [], "diverged": []}
                     for L in LENGTHS} for m in models}
    for seed in tqdm(seeds, desc="seeds"):
        actions, _ = record(SCENE, models[0], seed, HOLD_STEPS.stop,
                            {"gripper": {"jaw_length": RECORDED_LENGTH, "jaw_ends": ends}})
        for L in tqdm(LENGTHS, desc=f"seed {seed}", leave=False):
            for m in models:
                run = replay(SCENE, m, seed, actions, changes={"gripper": {"jaw_length": L, "jaw_ends": ends}})
                cell = out[m.label][f"{L:.3f}"]
                cell["held"].append(run["held"])
                cell["hold_force_N"].append(float(np.mean(run["grasp_force"][HOLD_STEPS])))
                cell["unconverged_steps"].append(int(sum(run["unconverged"])))
                cell["diverged"].append(bool(any(run["diverged"])))
    return out


def solver_report(results: dict) -> str:
    """Which runs had a step that did not converge or diverged (their forces are suspect)."""
    bad = [f"{lab} with {1e3 * float(key):g} mm jaws: {sum(c['unconverged_steps'])} unconverged steps"
           f"{', diverged' if any(c['diverged']) else ''}"
           for lab, by_length in results.items() for key, c in by_length.items()
           if sum(c["unconverged_steps"]) or any(c["diverged"])]
    return ("Every step of every run converged; none diverged." if not bad
            else "Runs with unconverged or diverged steps (their forces are suspect): " + "; ".join(bad) + ".")


def tabulate(results: dict, seeds) -> str:
    labels = list(results)
    finest = labels[-1]
    header = ["jaws (mm)"] + [f"{lab}: held / force (N) / vs finest" for lab in labels[:-1]] + [
        f"{finest}: held / force (N)"]
    rows = []
    for key in results[finest]:
        ref = np.asarray(results[finest][key]["hold_force_N"])
        row = [f"{1e3 * float(key):g}"]
        for lab in labels:
            cell = results[lab][key]
            f = np.asarray(cell["hold_force_N"])
            held = "/".join(map(str, sorted(set(cell["held"]))))
            text = f"{held} / {np.median(f):.3f}"
            if lab != finest:
                err = (f - ref) / ref  # signed, per seed; the worst (largest magnitude) shown
                text += f" / {100 * err[np.argmax(np.abs(err))]:+.1f} %"
            row.append(text)
        rows.append(row)
    return (f"Seeds {list(seeds)}; force: the median over the seeds of the mean grasp force over env steps "
            f"21..30 (the flap held folded back); held: vertices between the jaws (on the grasp edge); vs finest: "
            f"the worst seed's signed difference from {finest}.\n\n" + markdown_table(header, rows))


def chart(results: dict, path: Path, ends: str = "vertex") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12.5, 4.4))
    for lab, by_length in results.items():
        mm = [1e3 * float(k) for k in by_length]
        force = [np.median(c["hold_force_N"]) for c in by_length.values()]
        held = [np.median(c["held"]) for c in by_length.values()]
        if ends == "vertex":  # whole vertices: a staircase
            axes[0].step(mm, force, where="mid", marker="o", ms=3, label=lab)
        else:
            axes[0].plot(mm, force, marker="o", ms=3, label=lab)
        axes[1].step(mm, held, where="mid", marker="o", ms=3, label=lab)
    for a in axes:
        a.axvline(1e3 * RECORDED_LENGTH, color="k", ls=":", lw=1, label="configs/experiments/quick_jaws_adhesion.yaml")
        a.set_xlabel("jaw length (mm)")
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    axes[0].set_ylabel("hold force (N), median over seeds")
    axes[0].set_title("Force to hold the flap folded back vs the jaws' length", fontsize=9)
    axes[1].set_ylabel("vertices held on the grasp edge" + ("" if ends == "vertex" else " (wholly or in part)"))
    axes[1].set_title("Vertices between the jaws", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2,3,4", help="comma-separated episode seeds (default 0,1,2,3,4)")
    ap.add_argument("--jaw-ends", choices=("vertex", "weighted"), default="vertex",
                    help="scene.gripper.jaw_ends: whole vertices (the default), or weighted by their share")
    ap.add_argument("--from-json", action="store_true", help="rebuild the table and chart from the stored runs")
    args = ap.parse_args(argv)
    name = "jaw_length" if args.jaw_ends == "vertex" else "jaw_length_weighted"
    if args.from_json:
        stored = json.loads((RESULTS / f"{name}.json").read_text())
        write_docs(stored["results"], stored["seeds"], stored["wall_s"], stored["machine"], name, args.jaw_ends)
        return
    try:
        seeds = [int(s) for s in args.seeds.split(",")]
    except ValueError:
        ap.error(f"--seeds: comma-separated integers, got {args.seeds!r}")
    numba.set_num_threads(1)
    start = time.perf_counter()
    results = measure(seeds, args.jaw_ends)
    wall = time.perf_counter() - start
    machine = machine_info()
    write_json(f"{name}.json", {"machine": machine, "wall_s": wall, "seeds": seeds, "jaw_ends": args.jaw_ends,
                                "recorded_jaw_length_m": RECORDED_LENGTH, "hold_steps": [21, 30],
                                "results": results}, envs=[SCENE])
    write_docs(results, seeds, wall, machine, name, args.jaw_ends)


def write_docs(results: dict, seeds, wall: float, machine: dict, name: str = "jaw_length",
               ends: str = "vertex") -> None:
    """docs/benchmarks/NAME.md and docs/img/NAME.png from the runs."""
    how = ("whole vertices between the jaws" if ends == "vertex" else
           "each edge vertex by its share inside the jaws, `scene.gripper.jaw_ends: weighted`")
    flag = "" if ends == "vertex" else " --jaw-ends weighted"
    md = (f"Generated by `benchmarks/accuracy/jaw_length.py{flag}` in {wall / 60:.0f} min on one thread of "
          f"{machine['cpu']} ({machine['vector_isa']}, {machine['date']}). The flap (TissueRetraction, "
          f"`scene.gripper.jaw_length`; the jaws hold {how}), every mesh by the "
          "default quasi-Newton integrator (dt 0.05 s, tol 3e-3); method: the script's docstring.\n\n"
          + tabulate(results, seeds) + "\n\n" + solver_report(results)
          + f"\n\n![hold force vs jaw length](../img/{name}.png)\n")
    (RESULTS / f"{name}.md").write_text(md)
    chart(results, IMAGES / f"{name}.png", ends)
    print(md)


if __name__ == "__main__":
    main()
