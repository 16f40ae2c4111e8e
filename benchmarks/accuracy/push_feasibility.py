"""Can a blunt paddle expose the target under OrganRetraction's lobe, without a grasp?

The physics question under a push-retraction task, measured before the task exists. The
lobe of OrganRetraction-v2 (its default mesh, no adhesion), E 4 or 8 kPa (the task's
range); a paddle 40 x 80 x 4 mm (a rigid box) under the lobe at ``x0``, its top face
rising from the floor at 10 mm/s to 90 mm (quasi_newton, 0.1 s steps). Each 0.1 s: the
target's exposure (the task's measure, camera and target as the task has them, the target
in the middle of its range), the largest gauge strain, the paddle's push.

    python benchmarks/accuracy/push_feasibility.py   # docs/benchmarks/push_feasibility.{json,md}
"""

from __future__ import annotations

import dataclasses

import numpy as np

import heml_gym as hg
from heml_gym.benchmarks.common import generated_by, markdown_table, study_main

PADDLE_HALF = (0.02, 0.04, 0.002)
PLACES = (-0.06, -0.05, -0.035)  # m: the paddle's centre in x (the lobe's thin edge is at -0.08)
MODULI = (4e3, 8e3)
STEPS = 92


def lift(x0: float, young_modulus: float) -> dict:
    from heml_gym.envs import TaskSettings, build_scene
    from heml_gym.envs.measures import Exposure
    from heml_gym.envs.organ_retraction import TARGET_HIGH, TARGET_LOW, organ_scene
    from heml_gym.envs.strain_gauges import StrainGauges
    from heml_gym.world import World

    scene = build_scene(dataclasses.replace(organ_scene(), adhesion=None))
    settings = TaskSettings()
    world = World.from_physics(scene.mesh, scene.physics, 1, settings.control_dt, fixed=scene.fixed,
                               supports=scene.supports, tools=[hg.Box(PADDLE_HALF)])
    world.reset(0)
    world.model.set_material(0, scene.physics.material_for(young_modulus))
    exposure, gauges = Exposure(scene, settings.exposure_samples), StrainGauges(scene.mesh, scene.strain_gauge)
    target = 0.5 * (np.array(TARGET_LOW) + np.array(TARGET_HIGH))
    rows = []
    for k in range(STEPS):
        top = 0.001 * k  # m: the paddle's top face
        world.control.pose_tool(0, 0, (x0, 0.0, top - PADDLE_HALF[2]))
        stats = world.step(settings.control_dt)
        rows.append({"height": top, "exposure": float(exposure(world.state.x, target[None])[0]),
                     "strain": float(gauges.max_strain(world.state.x)[0]), "force": stats.tool_force[0, 0].tolist(),
                     "converged": bool(stats.converged[0])})
    return {"x0": x0, "young_modulus": young_modulus, "steps": rows}


def report(data: dict) -> str:
    damage = data["damage_strain"]
    table = []
    for run in data["runs"]:
        steps = run["steps"]
        exposed = next((s for s in steps if s["exposure"] >= 0.8), None)
        over = next((s for s in steps if s["strain"] >= damage), None)
        table.append([f"{run['x0'] * 1e3:.0f}", f"{run['young_modulus'] / 1e3:g}",
                      f"{exposed['height'] * 1e3:.0f}" if exposed else "never",
                      f"{exposed['strain']:.2f}" if exposed else "-",
                      f"{np.linalg.norm(exposed['force']):.2f}" if exposed else "-",
                      f"{max(s['strain'] for s in steps):.2f}", f"{over['height'] * 1e3:.0f}" if over else "never",
                      sum(not s["converged"] for s in steps)])
    return "\n".join([
        f"{generated_by(data)}.\n",
        "OrganRetraction-v2's lobe (default mesh, no adhesion) lifted by a 40 x 80 x 4 mm paddle under it, its top "
        f"face rising from the floor at 10 mm/s; the target in the middle of its range. Damage strain {damage:g}.\n",
        markdown_table(["paddle centre x (mm)", "E (kPa)", "height where exposure first >= 0.8 (mm)",
                        "gauge strain there", "push there (N)", "peak strain up to 91 mm", "height where the strain "
                        "first reaches the damage strain (mm)", "unconverged steps"], table)]) + "\n"


def main(argv=None):
    def measure():
        from heml_gym.envs import TaskSettings

        return {"command": "python benchmarks/accuracy/push_feasibility.py",
                "damage_strain": TaskSettings().damage_strain,
                "runs": [lift(x0, E) for x0 in PLACES for E in MODULI]}

    study_main("push_feasibility", __doc__, measure, report, argv)


if __name__ == "__main__":
    main()
