"""Stability on the env scenes: where each integrator diverges, stalls or refines, over the
stiffness and compressibility users randomise and beyond.

For each scene, integrator setting, Young's modulus E and Poisson ratio nu: a vector env
of ``--scenes`` scenes, all with that E and nu, plays ``--steps`` vector steps of random
and extreme actions (every third step bang-bang, grasp toggling) and counts per env step:
divergences (``info["simulation_diverged"]``), unconverged implicit solves
(``info["solver_converged"]`` False), steps that had to be re-taken with finer (explicit)
or shorter (quasi-Newton) sub-steps (``info["substep_refinement"] > 1``), plus the CPU
time per env step. Both scenes at their default meshes (the 12 x 12 x 1 flap, the 8 mm
lobe refined to 2.5 mm at the jaws). The default randomisation range of each scene is marked on the chart.

Writes docs/benchmarks/scene_stability.{json,md} and docs/img/scene_stability.png.

    python benchmarks/reliability/scene_stability.py [--steps 100] [--scenes 8] [--quick] [--from-json]
    python benchmarks/reliability/scene_stability.py --only "Organ:explicit s=0.5"   # one setting, merged into the stored run
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import gymnasium as gym
import numba
import numpy as np
from tqdm import tqdm
from heml_gym.benchmarks.common import IMAGES, RESULTS, machine_info, markdown_table, write_json

E_GRID = (1e3, 4e3, 8e3, 3e4, 1e5)  # Pa: 4-8 kPa is the scenes' randomisation range
NU_GRID = (0.3, 0.45, 0.49)
SCENES = {
    "heml_gym/TissueRetraction-v1": {"range": (4e3, 8e3, 0.45), "integrators": {
        "quasi-Newton dt=0.05 (default)": {"integrator": "quasi_newton"},
        "quasi-Newton dt=0.1": {"integrator": "quasi_newton", "max_dt": 0.1},
        "explicit s=0.75": {"integrator": "explicit", "safety": 0.75},
        "explicit s=1.0": {"integrator": "explicit", "safety": 1.0},
        "Newton dt=0.1": {"integrator": "implicit", "max_dt": 0.1, "newton_tol": 1e-3, "max_newton": 20}}},
    "heml_gym/OrganRetraction-v2": {"range": (4e3, 8e3, 0.45), "integrators": {
        "quasi-Newton dt=0.05 (default)": {"integrator": "quasi_newton"},
        "quasi-Newton dt=0.1": {"integrator": "quasi_newton", "max_dt": 0.1},
        # explicit: on the default mesh (2.5 mm at the jaws) one setting costs about 40 min
        # of one core
        "explicit s=0.5": {"integrator": "explicit", "safety": 0.5},
        "explicit s=0.75": {"integrator": "explicit", "safety": 0.75}}},
}


def run(env_id: str, physics: dict, E: float, nu: float, scenes: int, steps: int, extra: dict) -> dict:
    env = gym.make_vec(env_id, num_envs=scenes, vectorization_mode="vector_entry_point",
                       physics={**physics, "young_modulus": [E, E], "poisson": nu}, **extra)
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    counts = {"env_steps": 0, "diverged": 0, "unconverged": 0, "refined": 0, "non_finite": 0}
    cpu = []
    for k in range(steps):
        if k % 3 == 0:
            a = rng.choice([-1.0, 1.0], size=(scenes, 4))
        else:
            a = rng.uniform(-1, 1, (scenes, 4))
        c0 = time.thread_time()
        obs, reward, terminated, truncated, info = env.step(a.astype(np.float32))
        cpu.append(time.thread_time() - c0)
        counts["env_steps"] += scenes
        counts["diverged"] += int(np.sum(info["simulation_diverged"]))
        counts["unconverged"] += int(np.sum(~np.asarray(info["solver_converged"])
                                            & ~np.asarray(info["simulation_diverged"])))
        counts["refined"] += int(np.sum(np.asarray(info["substep_refinement"]) > 1))
        counts["non_finite"] += int(not (np.all(np.isfinite(obs)) and np.all(np.isfinite(reward))))
    env.close()
    return {"env": env_id, "E": E, "nu": nu, **counts, "cpu_ms_per_env_step": 1e3 * float(np.median(cpu)) / scenes}


def chart(rows: list, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(env, name) for env, spec in SCENES.items() for name in spec["integrators"]]
    panels = [(e, n) for e, n in panels if any(r["env"] == e and r["setting"] == n for r in rows)]
    cols = 3
    nrows = int(np.ceil(len(panels) / cols))
    fig, axes = plt.subplots(nrows, cols, figsize=(4.6 * cols, 3.6 * nrows), squeeze=False)
    for ax, (env_id, name) in zip(axes.ravel(), panels):
        sub = [r for r in rows if r["env"] == env_id and r["setting"] == name]
        es = sorted({r["E"] for r in sub})
        nus = sorted({r["nu"] for r in sub})
        grid = np.full((len(nus), len(es)), np.nan)
        text = {}
        for r in sub:
            i, j = nus.index(r["nu"]), es.index(r["E"])
            failures = r["diverged"] + r["unconverged"] + r["non_finite"]
            grid[i, j] = failures / r["env_steps"]
            text[(i, j)] = f"{failures}" + (f"\nref {r['refined']}" if r["refined"] else "")
        ax.imshow(grid, cmap="RdYlGn_r", vmin=0, vmax=0.05, origin="lower", aspect="auto")
        for (i, j), t in text.items():
            ax.text(j, i, t, ha="center", va="center", fontsize=7)
        lo, hi, nu0 = SCENES[env_id]["range"]
        ax.add_patch(plt.Rectangle((np.interp(lo, es, range(len(es))) - 0.1, nus.index(nu0) - 0.45),
                                   np.interp(hi, es, range(len(es))) - np.interp(lo, es, range(len(es))) + 0.2,
                                   0.9, fill=False, ec="blue", lw=2))
        ax.set_xticks(range(len(es)), [f"{e / 1e3:g}" for e in es])
        ax.set_yticks(range(len(nus)), [f"{n:g}" for n in nus])
        ax.set_xlabel("E (kPa)")
        ax.set_ylabel("nu")
        ax.set_title(f"{env_id.split('/')[-1].rsplit('-v', 1)[0]}: {name}", fontsize=9)
    for ax in axes.ravel()[len(panels):]:
        ax.axis("off")
    fig.suptitle("Failures (divergences + unconverged solves) per run of random and extreme actions; "
                 "'ref': steps re-taken finer; blue: the scene's randomisation range", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=100, help="vector steps per run")
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--quick", action="store_true", help="the flap only, 2 E x 1 nu, 10 steps (smoke run)")
    ap.add_argument("--from-json", action="store_true", help="rewrite the table and chart from the stored results")
    ap.add_argument("--only", default=None, metavar="ENV:SETTING",
                    help="run only the settings whose env id contains ENV and whose name is SETTING, and merge "
                         "their rows into the stored results (same steps and scenes as the stored run)")
    args = ap.parse_args(argv)
    only = None
    if args.only is not None:
        env_part, _, setting = args.only.partition(":")
        only = (env_part, setting)
        if not any(env_part in e and setting in spec["integrators"] for e, spec in SCENES.items()):
            known = "; ".join(f"{e}: {', '.join(spec['integrators'])}" for e, spec in SCENES.items())
            ap.error(f"--only: no setting matches {args.only!r} (known: {known})")
        if not (RESULTS / "scene_stability.json").is_file():
            ap.error("--only merges into docs/benchmarks/scene_stability.json, which does not exist: run without it")
    if args.from_json:
        data = json.loads((RESULTS / "scene_stability.json").read_text())
        chart(data["rows"], IMAGES / "scene_stability.png")
        write_markdown(data)
        return 0
    warnings.simplefilter("ignore")
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    jobs = []
    for env_id, spec in SCENES.items():
        if args.quick and "Organ" in env_id:
            continue
        for name, physics in spec["integrators"].items():
            if only is not None and not (only[0] in env_id and only[1] == name):
                continue
            for E in (E_GRID[1:3] if args.quick else E_GRID):
                for nu in ((0.45,) if args.quick else NU_GRID):
                    jobs.append((env_id, name, physics, E, nu, spec.get("kwargs", {})))
    rows = []
    t0 = time.perf_counter()
    for env_id, name, physics, E, nu, extra in tqdm(jobs, desc="scene stability", unit="run"):
        row = run(env_id, physics, E, nu, args.scenes, 10 if args.quick else args.steps, extra)
        row["setting"] = name
        rows.append(row)
    data = {"machine": machine_info(), "wall_s": time.perf_counter() - t0, "steps": args.steps,
            "scenes": args.scenes, "rows": rows, "ranges": {k: v["range"] for k, v in SCENES.items()}}
    if only is not None:  # merge: replace the stored rows of this setting, keep the rest
        stored = json.loads((RESULTS / "scene_stability.json").read_text())
        if (stored["steps"], stored["scenes"]) != (args.steps, args.scenes):
            ap.error(f"--only: the stored run used --steps {stored['steps']} --scenes {stored['scenes']}; give the same")
        keep = [r for r in stored["rows"] if not (only[0] in r["env"] and r["setting"] == only[1])]
        order = [(e, n) for e, spec in SCENES.items() for n in spec["integrators"]]
        merged = sorted(keep + rows, key=lambda r: (order.index((r["env"], r["setting"])), r["E"], r["nu"]))
        stored["added"] = stored.get("added", []) + [{"setting": args.only, "machine": data["machine"],
                                                       "wall_s": data["wall_s"]}]
        data = {**stored, "rows": merged, "ranges": data["ranges"],
                "wall_s": stored["wall_s"] + data["wall_s"]}
    if args.quick:
        print(markdown_table(["env", "setting", "E", "nu", "diverged", "unconverged", "refined"],
                             [[r["env"], r["setting"], r["E"], r["nu"], r["diverged"], r["unconverged"], r["refined"]]
                              for r in rows]))
        return 0
    write_json("scene_stability.json", data)
    chart(data["rows"], IMAGES / "scene_stability.png")
    write_markdown(data)
    return 0


def write_markdown(data: dict) -> None:
    """docs/benchmarks/scene_stability.md from the stored results."""
    m, rows = data["machine"], data["rows"]
    lines = [f"Generated by `benchmarks/reliability/scene_stability.py` in {data['wall_s'] / 60:.0f} min on {m['cpu']} "
             f"({m['cores']} cores), {m['date']}: {data['scenes']} scenes x {data['steps']} vector steps of random "
             "and extreme actions per run, every scene with the run's E and nu. A failure is a diverged simulation "
             "or an unconverged implicit solve (the episode ends, reported in `info`); *re-taken finer*: steps "
             "that needed finer explicit sub-steps or shorter quasi-Newton steps (and got them)."]
    for added in {a["setting"]: a for a in data.get("added", [])}.values():  # the last run of each
        am = added["machine"]
        lines[0] += (f" `{added['setting']}` was last re-run (`--only`) on {am['cpu']} ({am['cores']} cores), "
                     f"{am['date']}.")
    lines[0] += "\n"
    for env_id, spec in SCENES.items():
        sub = [r for r in rows if r["env"] == env_id]
        lo, hi, nu0 = spec["range"]
        mesh = "".join(f", {k} = {v * 1e3:g} mm" for k, v in spec.get("kwargs", {}).items())
        lines.append(f"\n### {env_id}\n\nDefault randomisation: E {lo / 1e3:g}-{hi / 1e3:g} kPa, nu {nu0}{mesh}.\n")
        lines.append(markdown_table(
            ["setting", "E (kPa)", "nu", "env steps", "diverged", "unconverged", "re-taken finer", "CPU ms / env step"],
            [[r["setting"], f"{r['E'] / 1e3:g}", r["nu"], r["env_steps"], r["diverged"], r["unconverged"],
              r["refined"], f"{r['cpu_ms_per_env_step']:.2f}"] for r in sub]))
        summary = []
        for name in spec["integrators"]:
            inside = [r for r in sub if r["setting"] == name and lo <= r["E"] <= hi and r["nu"] == nu0]
            if inside:
                bad = sum(r["diverged"] + r["unconverged"] + r["non_finite"] for r in inside)
                summary.append(f"{name}: {bad} failures in {sum(r['env_steps'] for r in inside):,} env steps")
        if summary:
            lines.append("Inside the default range: " + "; ".join(summary) + ".\n")
    (RESULTS / "scene_stability.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    raise SystemExit(main())
