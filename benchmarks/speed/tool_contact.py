"""What rigid tool contact costs today, and how its force depends on its penalty stiffness.

The flap of TissueRetraction (120 x 120 x 8 mm, 12 x 12 x 2 cells, E 4 kPa, its edge x = 0
fixed, on the plane z = 0), stepped as the tasks step it (quasi_newton, 0.1 s in two
sub-steps). Two tools, each timed against the same run without it:

* ``paddle``: a flat box 40 x 40 x 4 mm pressed 2 mm into the flap's top over 2 s, then held;
* ``probe``: a capsule of radius 5 mm across the flap (its axis along y), pressed 4 mm over
  2 s, then rolled along x at 20 mm/s.

For each, at tool_stiffness 10 and 100: ms per env step, L-BFGS iterations per env step,
and the tool's force at the end. Medians of ``--repeats`` runs.

    python benchmarks/speed/tool_contact.py          # docs/benchmarks/tool_contact.{json,md}
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import heml_gym as hg
from heml_gym import materials as M
from heml_gym.benchmarks.common import generated_by, machine_info, markdown_table, store_and_report
from heml_gym.control import rotation

STEPS = 50


def _run(tool: str | None, tool_stiffness: float) -> dict:
    mesh = hg.box_mesh((0.12, 0.12, 0.008), (12, 12, 2))
    fixed = np.flatnonzero(mesh.vertices[:, 0] == 0.0)
    shapes = {"paddle": hg.Box((0.02, 0.02, 0.002)), "probe": hg.Capsule(0.005, 0.03)}
    model = hg.Model(mesh, M.NeoHookean(E=4e3, nu=0.45), density=950.0, fixed=fixed, damping=2.0,
                     supports=[hg.PlaneSupport(height=0.0)], tools=[shapes[tool]] if tool else [])
    solver = hg.QuasiNewtonSolver(model, tool_stiffness=tool_stiffness)
    state, control = model.state(), model.control()
    along_y = rotation(np.array([1.0, 0.0, 0.0]), np.pi / 2)
    wall, iterations, unconverged = 0.0, 0, 0
    stats = None
    for k in range(STEPS):
        if tool == "paddle":
            control.pose_tool(0, 0, (0.07, 0.06, 0.010 - min(k, 20) * 1e-4))
        elif tool == "probe":
            control.pose_tool(0, 0, (0.04 + 0.002 * max(0, k - 20), 0.06, 0.013 - min(k, 20) * 2e-4), along_y)
        t0 = time.perf_counter()
        stats = solver.step(state, state, control, 0.1, substeps=2)
        wall += time.perf_counter() - t0
        iterations += int(stats.newton_iterations[0])
        unconverged += int(not stats.converged[0])
    force = stats.tool_force[0, 0].tolist() if tool else None
    return {"ms_per_step": 1e3 * wall / STEPS, "iterations_per_step": iterations / STEPS, "force": force,
            "unconverged_steps": unconverged}


def measure(repeats: int) -> list[dict]:
    rows = []
    for tool in ("paddle", "probe"):
        for stiffness in (10.0, 100.0):
            runs = {"with": [], "without": []}
            for _ in range(repeats):  # the two alternate, so that they share the machine's load
                runs["with"].append(_run(tool, stiffness))
                runs["without"].append(_run(None, stiffness))
            med = {k: float(np.median([r["ms_per_step"] for r in v])) for k, v in runs.items()}
            rows.append({"tool": tool, "tool_stiffness": stiffness, "ms_with": med["with"],
                         "ms_without": med["without"], "ratio": med["with"] / med["without"],
                         "iterations_with": runs["with"][0]["iterations_per_step"],
                         "iterations_without": runs["without"][0]["iterations_per_step"],
                         "force": runs["with"][0]["force"],
                         "unconverged_steps": runs["with"][0]["unconverged_steps"], "runs": runs})
    return rows


def report(data: dict) -> str:
    table = [[r["tool"], f"{r['tool_stiffness']:g}", f"{r['ms_with']:.1f}", f"{r['ms_without']:.1f}",
              f"{r['ratio']:.1f}x", f"{r['iterations_with']:.0f} / {r['iterations_without']:.0f}",
              " / ".join(f"{f:.3f}" for f in r["force"]), r["unconverged_steps"]] for r in data["rows"]]
    return "\n".join([
        f"{generated_by(data)}; {data['note']}\n",
        f"The TissueRetraction flap (12 x 12 x 2 cells, E 4 kPa, on the plane z = 0), quasi_newton, 0.1 s steps "
        f"in two sub-steps, {STEPS} steps; medians of {data['repeats']} runs, with and without the tool in turn.\n",
        markdown_table(["tool", "tool_stiffness", "ms per step with it", "without", "cost", "L-BFGS iterations "
                        "per step (with / without)", "its force at the end (x / y / z, N)",
                        "unconverged steps"], table)]) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3, help="runs per configuration (default 3)")
    ap.add_argument("--note", default="nothing else running", help="what else ran on the machine")
    ap.add_argument("--from-json", action="store_true", help="rewrite the table from the stored result")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats must be a positive integer, got {args.repeats}")
    data = None
    if not args.from_json:
        data = {"machine": machine_info(), "command": "python benchmarks/speed/tool_contact.py",
                "repeats": args.repeats, "note": args.note, "rows": measure(args.repeats)}
    store_and_report("tool_contact", data, report)


if __name__ == "__main__":
    main()
