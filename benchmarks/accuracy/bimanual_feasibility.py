"""Does a wide flap need two graspers? One grasper's scripted fold against two.

The question a bimanual retraction task rests on: a flap twice as wide as the
TissueRetraction flap (120 x 240 x 8 mm, attached along x = 0, its underside stuck 10 mm
out, a tumour under the middle of its free half), folded back by jaws shorter than its
free edge (weighted ends), once by one grasper at the edge's middle and once by two at
its quarter points. Each grasper runs the flap's scripted fold (``FoldBackPolicy`` with
the flap's partial-jaw radius, ``heml_gym.envs.scripted``) on the same
:class:`heml_gym.World`: the instruments compose on one world (``Grasper(spec=...)``),
without a task class.

Per configuration and tissue stiffness (E = 4, 6, 8 kPa, the flap's range): whether the
tumour is exposed (>= 80 % of its camera-facing samples) with the gauge strain below the
damage strain (0.5) for 2 s in a row (TissueRetraction's success), the largest exposure,
the peak gauge strain, the damage (the summed ``info["cost"]``: 0.1 s times the gauge
strain above the safe strain 0.18, strain x s) and each grasper's mean hold force over the
last second (N).

Writes docs/benchmarks/bimanual_feasibility.{json,md} (``--cells`` with ``--name``: the
same on another mesh, e.g. a finer one, to see whether the answer holds as the mesh is refined).

    python benchmarks/accuracy/bimanual_feasibility.py [--steps 80] [--cells 12,24,2] [--name NAME] [--from-json]
"""

from __future__ import annotations

import argparse
import dataclasses
import math

import numpy as np
from tqdm import tqdm

from heml_gym.benchmarks.common import machine_info, markdown_table, store_and_report
from heml_gym.world import World

FLAP = (0.12, 0.24, 0.008)  # m: twice TissueRetraction's width
CELLS = (12, 24, 2)  # TissueRetraction's cell size (10 x 10 x 4 mm)
TARGET = (0.07, FLAP[1] / 2, -0.02)  # m: under the middle of the flap's free half
ADHESION = 0.01  # m: the underside stuck this far out from the attachment (the middle of the flap's range)
STIFFNESS = (4e3, 6e3, 8e3)  # Pa
SUCCESS_HOLD = 2.0  # s
#: configuration -> [(jaw length m, y of the jaws' centre m), ...]
CONFIGS = {
    "one grasper, 40 mm jaws at the middle": [(0.04, FLAP[1] / 2)],
    "one grasper, 80 mm jaws at the middle": [(0.08, FLAP[1] / 2)],
    "two graspers, 40 mm jaws at the quarter points": [(0.04, FLAP[1] / 4), (0.04, 3 * FLAP[1] / 4)],
}


def wide_flap(cells=CELLS):
    """The built wide-flap scene: TissueRetraction's, twice as wide, its target fixed;
    ``cells``: its hex grid (6 tets per cell)."""
    from heml_gym.envs import RegionSpec, TargetSpec, TissueSpec, build_scene
    from heml_gym.envs.tissue_retraction import tissue_scene

    lx, ly, lz = FLAP
    base = tissue_scene()
    spec = dataclasses.replace(
        base, name="WideFlap",
        tissue=dataclasses.replace(base.tissue, size=FLAP, cells=tuple(cells)),
        tracked=RegionSpec(points=[(lx, 0.0, lz), (lx, ly / 2, lz), (lx, ly, lz), (lx / 2, ly / 2, lz)]),
        target=TargetSpec(low=TARGET, high=TARGET, radius=0.008),
        gripper=dataclasses.replace(base.gripper, workspace_high=(0.20, ly + 0.05, 0.15)),
        camera=dataclasses.replace(base.camera, eye=(0.06, ly / 2, 0.30)))
    assert isinstance(spec.tissue, TissueSpec)
    return build_scene(spec)


def run(scene, jaws, young_modulus: float, steps: int) -> dict:
    """One scripted fold of the wide flap by the graspers ``jaws`` [(length, y), ...]."""
    from heml_gym.envs import STATE_FIELDS, TaskSettings
    from heml_gym.envs.instruments import Grasper
    from heml_gym.envs.measures import Exposure
    from heml_gym.envs.scripted import PARTIAL_JAWS_RADIUS_SCALE, MAX_FOLD_ANGLE, FoldBackPolicy
    from heml_gym.envs.strain_gauges import StrainGauges

    settings = TaskSettings()
    dt = settings.control_dt
    world = World.from_physics(scene.mesh, scene.physics, 1, dt, fixed=scene.fixed, supports=scene.supports)
    world.reset(0)
    world.model.set_material(0, scene.physics.material_for(young_modulus))
    world.stick(0, scene.adhesion_vertices[scene.adhesion_distance <= ADHESION + 1e-9])
    graspers, policies = [], []
    for k, (length, y) in enumerate(jaws):
        spec = dataclasses.replace(scene.spec.gripper, jaw_length=length, jaw_ends="weighted",
                                   workspace_high=tuple(scene.workspace_high))
        g = Grasper(world, scene, settings, name=f"grasper{k}", spec=spec)
        g.place(0, (FLAP[0] - 0.008, y, FLAP[2] + 0.002))  # over the free edge, inside the grasp reach
        graspers.append(g)
        policies.append(FoldBackPolicy(hinge=scene.hinge, direction=scene.fold_direction,
                                       max_angle=MAX_FOLD_ANGLE["TissueRetraction"],
                                       radius_scale=PARTIAL_JAWS_RADIUS_SCALE["TissueRetraction"]))
    exposure_of = Exposure(scene, settings.exposure_samples)
    gauges = StrainGauges(scene.mesh, scene.strain_gauge)
    targets = np.array([TARGET])
    exposure = float(exposure_of(world.x, targets)[0])
    state = np.zeros(len(STATE_FIELDS), dtype=np.float32)
    held_for, success_at, peak, damage, best, forces, failed_any = 0, None, 0.0, 0.0, exposure, [], False
    for step in range(steps):
        actions = []
        for g, policy in zip(graspers, policies):
            state[0:3], state[3] = g.position[0], float(g.grasping[0])
            state[STATE_FIELDS.index("exposure")] = exposure
            actions.append(np.asarray(policy(state), dtype=np.float64)[None, :])
        for g, a in zip(graspers, actions):
            g.grasp(a)
        for g, a in zip(graspers, actions):
            g.move(a)
        stats = world.step(dt)
        failed = stats.diverged | ~stats.converged
        failed_any |= bool(failed[0])
        for g in graspers:
            g.after_step(stats.reaction, failed)
        exposure = float(exposure_of(world.x, targets)[0])
        strain = float(gauges.max_strain(world.x)[0])
        peak, best = max(peak, strain), max(best, exposure)
        damage += dt * max(0.0, strain - settings.safe_strain)
        meets = exposure >= settings.success_exposure and strain < settings.damage_strain and not failed[0]
        held_for = held_for + 1 if meets else 0
        if success_at is None and held_for > math.ceil(SUCCESS_HOLD / dt - 1e-9):
            success_at = (step + 1) * dt
        forces.append([float(np.linalg.norm(g.force[0])) for g in graspers])
    last = np.array(forces[-int(round(1.0 / dt)):])
    return {"young_modulus": young_modulus, "success": success_at is not None, "success_at_s": success_at,
            "max_exposure": best, "peak_strain": peak, "damage": damage, "failed": failed_any,
            "hold_force_n": last.mean(axis=0).tolist(), "grasped": [bool(g.grasped_once[0]) for g in graspers]}


def measure(steps: int, cells=CELLS) -> dict:
    scene = wide_flap(cells)
    results = {"machine": machine_info(), "flap_m": list(FLAP), "cells": list(cells), "n_tets": scene.mesh.n_tets,
               "target_m": list(TARGET), "adhesion_m": ADHESION, "steps": steps, "configs": {}}
    with tqdm(total=len(CONFIGS) * len(STIFFNESS), desc="folds") as bar:
        for name, jaws in CONFIGS.items():
            rows = []
            for E in STIFFNESS:
                rows.append(run(scene, jaws, E, steps))
                bar.update()
            results["configs"][name] = {"jaws": [{"length_m": length, "y_m": y} for length, y in jaws],
                                        "runs": rows}
    return results


def report(data: dict) -> str:
    rows = []
    for name, c in data["configs"].items():
        for r in c["runs"]:
            rows.append([name, f"{r['young_modulus'] / 1e3:g}", "yes" if r["success"] else "no",
                         f"{r['max_exposure']:.2f}", f"{r['peak_strain']:.3f}", f"{r['damage']:.3f}",
                         " / ".join(f"{f:.2f}" for f in r["hold_force_n"])])
    m = data["machine"]
    cells = " x ".join(str(c) for c in data["cells"])
    command = "python benchmarks/accuracy/bimanual_feasibility.py" + (
        "" if data["cells"] == list(CELLS) else f" --cells {','.join(str(c) for c in data['cells'])} --name {data['name']}")
    head = (f"A {data['flap_m'][0] * 1e3:.0f} x {data['flap_m'][1] * 1e3:.0f} x {data['flap_m'][2] * 1e3:.0f} mm "
            f"flap ({cells} cells, {data['n_tets']:,} tets), folded back by the scripted fold of each grasper, "
            f"{data['steps']} env steps of 0.1 s ({m['cpu']}, {m['date']}; "
            f"`{command}`). Success as TissueRetraction's: exposure >= 0.8 "
            "with the gauge strain below 0.5 for 2 s. Damage: the summed strain above 0.18 times 0.1 s.\n\n")
    return head + markdown_table(["graspers", "E (kPa)", "success", "max exposure", "peak gauge strain",
                                  "damage (strain x s)", "hold force per grasper, last 1 s (N)"], rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=80)
    ap.add_argument("--cells", default=",".join(str(c) for c in CELLS), help="the flap's hex grid, x,y,z")
    ap.add_argument("--name", default="bimanual_feasibility", help="store as docs/benchmarks/NAME.{json,md}")
    ap.add_argument("--from-json", action="store_true", help="only rewrite the table from the stored result")
    args = ap.parse_args(argv)
    if args.steps < 1:
        ap.error(f"--steps: must be >= 1, got {args.steps}")
    try:
        cells = tuple(int(c) for c in args.cells.split(","))
    except ValueError:
        cells = ()
    if len(cells) != 3 or min(cells) < 1:
        ap.error(f"--cells: three positive integers x,y,z, got {args.cells!r}")
    data = None
    if not args.from_json:
        data = {**measure(args.steps, cells), "name": args.name}
    store_and_report(args.name, data, report, envs=["heml_gym/TissueRetraction-v1"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
