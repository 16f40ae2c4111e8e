"""The flap's line grasp has no fine-mesh limit next to the jaws.

TissueRetraction's jaws hold a *line* of tissue, the flap's free edge along its top (x =
120 mm, z = 8 mm), so that the flap can turn about it as it folds. In 3-D elasticity a
held line is a singular boundary condition: the tissue next to it stretches more on every
finer mesh, without limit (the displacement of a line load grows as the logarithm of the
distance from it), while the rest of the flap converges. The lobe moved to a held patch
for this reason (grasp_convergence.py); this measures what the line does on the flap, and
so why calibration from the flap's tracked points depends on the mesh whatever the
element (docs/studies/calibration.md).

Protocol: the calibration benchmark's tissue (E 5.5 kPa, nu 0.43) along its scripted
retraction and hold (30 steps, seed 1): the scripted policy runs on the default model
and its actions are replayed on every model, so every mesh follows the same gripper
path. Models: linear tets (HEML, quasi-Newton) on 12 x 12 x 2 to 48 x 48 x 8 cells and
quadratic tets (Newton) on 6 x 6 x 1 to 16 x 16 x 3 cells, all in 0.025 s steps. At the
end of the hold: the distance from the held line's middle (x 120 mm, y 60 mm, z 8 mm) to
the material points of the top face's mid-line 1, 2, 5, 10, 20, 40 and 60 mm from it
(interpolated in each model's tets: the same material points on every mesh), so the
stretch of each stretch of tissue; the jaws' force; and how far calibration.py's 10
tracked points (noise-free) are from those of the finest model of the same element.

Writes docs/benchmarks/flap_grasp_line.{json,md} and docs/img/flap_grasp_line.png.

    python benchmarks/accuracy/flap_grasp_line.py              # about 20 minutes on one thread
    python benchmarks/accuracy/flap_grasp_line.py --from-json
"""

from __future__ import annotations

import argparse
import time

import numba
import numpy as np
from tqdm import tqdm

from heml_gym.benchmarks.accuracy.calibration import SEED, STEPS, TRUTH, observe, truth_env
from heml_gym.benchmarks.common import IMAGES, machine_info, markdown_table, store_and_report

ENV = "heml_gym/TissueRetraction-v1"
DT = 0.025  # s: every model's step
#: (element, cells): coarsest first within each element
MODELS = [("linear", (12, 12, 2)), ("linear", (24, 24, 4)), ("linear", (36, 36, 6)), ("linear", (48, 48, 8)),
          ("quadratic", (6, 6, 1)), ("quadratic", (8, 8, 1)), ("quadratic", (12, 12, 2)),
          ("quadratic", (16, 16, 3))]
#: m: the material points' rest distances from the held line along the top face's mid-line
DISTANCES = (0.001, 0.002, 0.005, 0.01, 0.02, 0.04, 0.06)
EDGE_X, MID_Y, TOP_Z = 0.12, 0.06, 0.008  # m: the held line's middle


def model_kwargs(element: str, cells) -> dict:
    physics = {"max_dt": DT}
    if element == "quadratic":
        physics.update(field="quadratic", integrator="implicit")
    return {"cells": list(cells), "physics": physics}


def node_spacing(element: str, cells) -> float:
    """m: the spacing of the nodes along the flap (x)."""
    return 0.12 / cells[0] / (2 if element == "quadratic" else 1)


def scripted_actions() -> list[np.ndarray]:
    """The scripted retraction's actions, recorded on the default model (truth's tissue)."""
    env, policy = truth_env(ENV, {})
    obs, _ = env.reset(seed=SEED)
    actions = []
    for _ in range(STEPS):
        actions.append(np.asarray(policy(obs), dtype=np.float64).copy())
        obs, *_ = env.step(actions[-1])
    env.close()
    return actions


def run_model(element: str, cells, actions, tracked_rest: np.ndarray) -> dict:
    """Replay ``actions`` on the model; the mid-line's distances, the force and the tracked
    points at the end of the hold."""
    from heml_gym.calibration import embed_points

    env, _ = truth_env(ENV, model_kwargs(element, cells))
    task = env.unwrapped.task
    line = np.array([[EDGE_X - s, MID_Y, TOP_Z] for s in (0.0, *DISTANCES)])
    B_line = embed_points(task.scene.mesh, line)
    B_tracked = embed_points(task.scene.mesh, tracked_rest)
    env.reset(seed=SEED)
    t0 = time.perf_counter()
    converged = True
    for a in actions:
        _, _, _, _, info = env.step(a)
        converged &= bool(info["solver_converged"])
    wall = time.perf_counter() - t0
    x = task.x[0]
    p = B_line @ x
    env.close()
    return {"element": element, "cells": list(cells), "node_spacing_m": node_spacing(element, cells),
            "n_nodes": int(task.scene.mesh.n_vertices), "distance_m": np.linalg.norm(p[1:] - p[0], axis=1).tolist(),
            "grasp_force_N": float(np.linalg.norm(task.grasp_force[0])), "tracked_m": (B_tracked @ x).tolist(),
            "solver_converged": converged, "wall_s": wall}


def measure() -> dict:
    numba.set_num_threads(1)
    actions = scripted_actions()
    tracked_rest = observe(ENV, {}, SEED, 0.0, 0.0).rest_points
    rows = [run_model(e, c, actions, tracked_rest) for e, c in tqdm(MODELS, desc="models")]
    return {"machine": machine_info(), "env": ENV, "truth": TRUTH, "seed": SEED, "steps": STEPS, "dt_s": DT,
            "distances_m": list(DISTANCES), "rows": rows}


def _stretch(row: dict, a: float, b: float, distances) -> float:
    """The stretch (deformed / rest length) of the mid-line between ``a`` and ``b`` m from the line."""
    d = dict(zip(distances, [0.0] + row["distance_m"]))
    return (d[b] - d[a]) / (b - a)


def _finest(rows, element):
    return [r for r in rows if r["element"] == element][-1]


def report(data: dict) -> str:
    m, rows, dist = data["machine"], data["rows"], [0.0] + data["distances_m"]
    table = []
    for r in rows:
        finest = _finest(rows, r["element"])
        gap = np.linalg.norm(np.array(r["tracked_m"]) - np.array(finest["tracked_m"]), axis=1)
        table.append([f"{r['element']}, {' x '.join(map(str, r['cells']))} cells", f"{1e3 * r['node_spacing_m']:.2f}",
                      r["n_nodes"], f"{_stretch(r, 0.0, 0.002, dist):.3f}", f"{_stretch(r, 0.0, 0.01, dist):.3f}",
                      f"{_stretch(r, 0.01, 0.06, dist):.4f}", f"{r['grasp_force_N']:.3f}",
                      "-" if r is finest else f"{1e3 * np.sqrt((gap ** 2).mean()):.2f} / {1e3 * gap.max():.2f}",
                      "yes" if r["solver_converged"] else "NO", f"{r['wall_s']:.0f}"])
    head = (f"Generated by `benchmarks/accuracy/flap_grasp_line.py` on {m['cpu']} ({m['vector_isa']}, one thread), "
            f"{m['date']}. {data['env'].split('/')[-1]}, tissue E {data['truth']['young_modulus']:,.0f} Pa, nu "
            f"{data['truth']['poisson_ratio']}, the scripted retraction's actions (seed {data['seed']}, recorded on "
            f"the default model) replayed on every model in {data['dt_s']} s steps; at the end of the hold. Stretch: "
            "deformed over rest length of the top face's mid-line, from the held line out to 2 mm and 10 mm, and "
            "from 10 to 60 mm. Tracked points: calibration.py's 10, noise-free, against the finest model of the "
            "same element (RMS / max). Method: the script's docstring.\n\n")
    return head + markdown_table(["model", "node spacing (mm)", "nodes", "stretch 0-2 mm", "stretch 0-10 mm",
                                  "stretch 10-60 mm", "jaws' force (N)", "tracked points vs finest (mm)",
                                  "converged", "wall s"], table)


def chart(data: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dist = [0.0] + data["distances_m"]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for element, marker, style in (("linear", "o", "-"), ("quadratic", "s", "--")):
        rows = [r for r in data["rows"] if r["element"] == element]
        h = [1e3 * r["node_spacing_m"] for r in rows]
        for (a, b), color in (((0.0, 0.002), "C3"), ((0.0, 0.01), "C1"), ((0.01, 0.06), "C0")):
            axes[0].plot(h, [_stretch(r, a, b, dist) for r in rows], style, marker=marker, color=color,
                         label=f"{element} tets, {1e3 * a:g}-{1e3 * b:g} mm from the line")
        axes[1].plot(h, [r["grasp_force_N"] for r in rows], style, marker=marker, color="k", label=f"{element} tets")
    for ax in axes:
        ax.set_xscale("log")
        ax.set_xticks([2, 3, 5, 10], labels=["2", "3", "5", "10"])
        ax.minorticks_off()
        ax.invert_xaxis()
        ax.set_xlabel("node spacing along the flap (mm), finer to the right")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("stretch of the top face's mid-line")
    axes[0].set_title("next to the held line: no limit; away from it: converges")
    axes[0].legend(fontsize=7)
    axes[1].set_ylabel("jaws' force at the end of the hold (N)")
    axes[1].set_title("jaws' force")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    IMAGES.mkdir(exist_ok=True)
    fig.savefig(IMAGES / "flap_grasp_line.png", dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--from-json", action="store_true", help="rewrite the table and chart from the stored JSON")
    args = ap.parse_args(argv)
    data = store_and_report("flap_grasp_line", None if args.from_json else measure(), report, envs=[ENV])
    chart(data)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
