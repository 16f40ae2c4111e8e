"""Line and patch grasps on the liver lobe: which has a fine-mesh limit?

OrganRetraction's jaws hold a 40 mm *line* of the lobe's top face (the default) or, with
``organ_scene(grasp="patch")``, the jaws' 6 mm x 40 mm *footprint*. In 3-D elasticity a
line held in place is not a well-posed boundary condition: the tissue next to it grows
ever more compliant as the mesh refines (the displacement of a line load is
logarithmically singular), so the held edge droops further and the grasp force falls on
every finer mesh, without limit. A held patch has a limit. This study measures both.

On the lobe's former task (``organ_retraction.FORMER_TASK``: the target behind the thin
edge, exposed by a 2 cm lift, the underside free; the default until 2026-11-25).

Protocol: for each grasp, the scripted baseline runs 30 steps on the default model (7 mm,
backward Euler by L-BFGS) from ``reset(seed)`` for seeds 0-4 (as scene_convergence.py;
on the line grasp, seeds 2-4 hold the target at the margin of its visibility) and its
actions are replayed on a
sequence of meshes stepped explicitly (0.5 of the critical step): uniform 7 / 6 / 5 / 4 mm
and 5 / 4 mm meshes graded to 3 / 2.5 / 2 mm within 30 mm of the thin edge (which covers
the grasp), and on the quasi-Newton candidates for a default. Recorded per step: grasp
force (N), exposure, the thin edge's height (mean z of the vertices within 6 mm of its
tip, mm). The finest mesh is each grasp's reference; errors as in scene_convergence.py
(force: max |F - F_ref| / max F_ref; exposure with half a step of timing tolerance).

Writes docs/benchmarks/grasp_convergence.{json,md} and docs/img/grasp_convergence.png.

    python benchmarks/accuracy/grasp_convergence.py            # about 15 minutes on one thread
    python benchmarks/accuracy/grasp_convergence.py --from-json
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
from heml_gym.benchmarks.accuracy.scene_convergence import QN, Model, errors, lobe_mesh_label, record, replay

from heml_gym.envs.organ_retraction import FORMER_TASK

SCENE = "OrganRetraction"
SEEDS = (0, 1, 2, 3, 4)
STEPS = 30
HOLD_FROM = 10  # steps 11-30 (1-3 s): the lift is over, the tissue is held
TIP_BAND = 0.006  # m: vertices this close (at rest, in x) to the lobe's tip measure its height
#: explicit sequence, coarsest first; the last is the reference: (mesh size, edge size) in m
MESHES = [(0.007, None), (0.006, None), (0.005, None), (0.004, None), (0.005, 0.003), (0.004, 0.0025),
          (0.004, 0.002)]
#: quasi-Newton candidates for a default (the default's own step and tolerance): (mesh size,
#: edge size, jaw size) in m, the last refining the mesh only around the jaws
CANDIDATES = [(0.007, None, None), (0.007, 0.004, None), (0.006, 0.004, None), (0.007, 0.003, None),
              (0.005, 0.003, None), (0.008, None, 0.0025), (0.007, None, 0.003)]


def model(grasp: str, size: float, edge: float | None, quasi_newton: bool, jaw: float | None = None) -> Model:
    label = lobe_mesh_label(size, edge, jaw)
    physics = QN if quasi_newton else {"integrator": "explicit"}
    label += " quasi_newton dt=0.05" if quasi_newton else " s=0.5"
    return Model(f"{grasp}: {label}", (size, edge, grasp, jaw), 0.5, tuple(sorted(physics.items())))


def tip_height_mm(env) -> float:
    rest = env.task.scene.mesh.vertices
    near = rest[:, 0] <= rest[:, 0].min() + TIP_BAND
    return 1e3 * float(env.task.state.x[0][near, 2].mean())


def run(grasp: str) -> dict:
    explicit = [model(grasp, s, e, False) for s, e in MESHES]
    candidates = [model(grasp, s, e, True, j) for s, e, j in CANDIDATES]
    default = candidates[0]
    runs, actions, meta = {}, {}, {}
    for seed in tqdm(SEEDS, desc=f"{grasp} grasp"):
        actions[seed], _ = record(SCENE, default, seed, STEPS, FORMER_TASK)
        for m in explicit + candidates:
            runs.setdefault(m.label, {})[seed] = replay(SCENE, m, seed, actions[seed], {"tip_height_mm": tip_height_mm},
                                                            changes=FORMER_TASK)
            meta[m.label] = {"size_mm": 1e3 * m.scene_args[0],
                             "edge_mm": None if m.scene_args[1] is None else 1e3 * m.scene_args[1],
                             "jaw_mm": None if m.scene_args[3] is None else 1e3 * m.scene_args[3],
                             "finest_mm": 1e3 * min(v for v in m.scene_args[:2] + m.scene_args[3:] if v),
                             "integrator": dict(m.physics)["integrator"]}
    return {"grasp": grasp, "seeds": list(SEEDS), "steps": STEPS, "reference": explicit[-1].label,
            "default": default.label, "explicit": [m.label for m in explicit],
            "candidates": [m.label for m in candidates], "meta": meta,
            "runs": {lab: {str(s): r for s, r in by.items()} for lab, by in runs.items()},
            "actions": {str(s): a.tolist() for s, a in actions.items()}}


def table(res: dict) -> list[dict]:
    ref = res["runs"][res["reference"]]
    rows = []
    for label in res["explicit"] + res["candidates"]:
        by_seed = res["runs"][label]
        errs = [errors(by_seed[s], ref[s], STEPS) for s in ref]
        hold = lambda k: float(np.mean([np.mean(by_seed[s][k][HOLD_FROM:]) for s in by_seed]))  # noqa: E731
        one = next(iter(by_seed.values()))
        cpu = np.concatenate([by_seed[s]["cpu_s"] for s in by_seed])
        rows.append({"model": label, **res["meta"][label], "n_tets": one["n_tets"], "held": one["held"],
                     "cpu_ms_per_step": 1e3 * float(np.median(cpu)),
                     "hold_force_N": hold("grasp_force"), "hold_exposure": hold("exposure"),
                     "hold_tip_height_mm": hold("tip_height_mm"),
                     "force_err": float(max(e["force"] for e in errs)),
                     "exposure_err": float(max(e["exposure"] for e in errs)),
                     "reference": label == res["reference"], "default": label == res["default"]})
    return rows


def markdown(results: dict, machine: dict, wall: float) -> str:
    out = [f"Generated by `benchmarks/accuracy/grasp_convergence.py` in {wall / 60:.0f} min on one thread of "
           f"{machine.get('cpu', 'this machine')}. Seeds {list(SEEDS)}, the scripted path of {STEPS} steps recorded "
           f"on each grasp's default (7 mm, quasi-Newton); hold = steps {HOLD_FROM + 1}-{STEPS}. Errors against "
           "each grasp's finest mesh (4 mm graded to 2 mm at the edge, explicit), over all steps, worst seed. "
           "Method: docs/studies/scene_convergence.md, \"Line and patch grasps\".", ""]
    for grasp, res in results.items():
        out += [f"### {grasp.capitalize()} grasp", ""]
        rows = [[("**" + r["model"] + "**" if r["default"] else r["model"]) + (" (reference)" if r["reference"] else ""),
                 r["n_tets"], r["held"], f"{r['cpu_ms_per_step']:.1f}", f"{r['hold_force_N']:.3f}",
                 f"{r['hold_tip_height_mm']:.1f}", f"{r['hold_exposure']:.2f}",
                 "-" if r["reference"] else f"{100 * r['force_err']:.1f}",
                 "-" if r["reference"] else f"{r['exposure_err']:.3f}"] for r in res["table"]]
        out += [markdown_table(["model", "tets", "held vertices", "CPU ms/step", "hold force (N)",
                                "thin edge height (mm)", "hold exposure", "force err %", "exposure err"], rows), ""]
    return "\n".join(out)


def chart(results: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    keys = [("hold_force_N", "grasp force in the hold (N)"), ("hold_tip_height_mm", "thin edge height in the hold (mm)"),
            ("hold_exposure", "exposure in the hold")]
    for (key, title), ax in zip(keys, axes):
        for grasp, res, colour in ((g, r, c) for (g, r), c in zip(results.items(), ("tab:red", "tab:blue"))):
            rows = [r for r in res["table"] if r["integrator"] == "explicit"]
            for uniform, marker in ((True, "o"), (False, "s")):
                pts = sorted((r["finest_mm"], r[key]) for r in rows if (r["edge_mm"] is None) == uniform)
                if pts:
                    ax.plot(*zip(*pts), marker=marker, color=colour, ls="-" if uniform else "--",
                            label=f"{grasp} grasp, {'uniform' if uniform else 'graded at the edge'}")
        ax.set_xlabel("finest element size (mm)")
        ax.invert_xaxis()
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("OrganRetraction: a held line has no fine-mesh limit, a held patch does "
                 f"(explicit, seeds {list(SEEDS)})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--from-json", action="store_true", help="rebuild the table and chart from the stored runs")
    args = ap.parse_args(argv)
    if args.from_json:
        if not (RESULTS / "grasp_convergence.json").is_file():  # the last run measured a former task: archived
            ap.error(f"--from-json: nothing stored at {RESULTS / 'grasp_convergence.json'} (the run of a former task "
                     "is kept in docs/benchmarks/archive/)")
        stored = json.loads((RESULTS / "grasp_convergence.json").read_text())
        machine, wall, results = stored["machine"], stored["wall_s"], stored["results"]
    else:
        numba.set_num_threads(1)
        start = time.perf_counter()
        results = {g: run(g) for g in ("line", "patch")}
        machine, wall = machine_info(), time.perf_counter() - start
    for res in results.values():
        res["table"] = table(res)
    write_json("grasp_convergence.json", {"machine": machine, "wall_s": wall, "results": results})
    md = markdown(results, machine, wall)
    (RESULTS / "grasp_convergence.md").write_text(md + "\n")
    chart(results, IMAGES / "grasp_convergence.png")
    print(md)


if __name__ == "__main__":
    main()
