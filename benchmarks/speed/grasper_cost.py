"""What a second grasper costs: BimanualRetraction-v0 with its two graspers against the same
mesh with one grasper of the task's jaws (40 mm, at the middle of the free edge).

A step's time is the L-BFGS iterations it takes times the time per iteration, plus what the
task and its instruments do in Python. So besides env steps per second this counts the
iterations per env step and times an iteration: if a second grasper cost bookkeeping, the
time per iteration (everything in the step divided by its iterations) would rise; if it
costs physics (two patches held and pulled take more iterations to solve), the iterations
rise. Single env, one thread, the same seeded random-action streams for both (the
one-grasper env gets the first 4 of the 8 entries), and the scripted experts' folds; the
two envs alternate per stream, so they share the machine's load.

    python benchmarks/speed/grasper_cost.py            # docs/benchmarks/grasper_cost.{json,md}
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np

from heml_gym.benchmarks.common import generated_by, machine_info, markdown_table, store_and_report

ENV_ID = "heml_gym/BimanualRetraction-v0"
VARIANTS = ("two graspers (the task)", "one grasper (same mesh)")


def _make(variant: str):
    import heml_gym.envs  # noqa: F401  (registers the ids)
    from heml_gym.benchmarks.accuracy.bimanual_task import variant_scene

    kwargs = {} if variant == VARIANTS[0] else {"scene": variant_scene(0.04)}
    return gym.make(ENV_ID, **kwargs).unwrapped


def _holding(info: dict) -> bool:
    return any(bool(np.asarray(v).any()) for k, v in info.items() if k.endswith("grasping"))


def _stream(env, mode: str, seed: int, steps: int) -> dict:
    """``steps`` env steps from ``reset(seed)``: random actions drawn from ``seed`` (8 entries,
    the env takes its own), or the scripted expert; a new episode (seed + 1000 k) when one ends."""
    from heml_gym.envs import scripted

    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1.0, 1.0, (steps, 8)).astype(np.float32)[:, :env.action_space.shape[0]]
    policy = scripted.scripted_policy(env.scene) if mode == "scripted" else None
    obs, _ = env.reset(seed=seed)
    if policy is not None:
        policy.reset()
    episodes, wall, iterations, holding = 1, 0.0, 0.0, 0
    for k in range(steps):
        a = policy(obs) if policy is not None else actions[k]
        t0 = time.perf_counter()
        obs, _, terminated, truncated, info = env.step(a)
        wall += time.perf_counter() - t0
        iterations += float(np.sum(info["newton_iterations"]))
        holding += _holding(info)
        if terminated or truncated:
            obs, _ = env.reset(seed=seed + 1000 * episodes)
            episodes += 1
            if policy is not None:
                policy.reset()
    return {"wall_s": wall, "iterations": iterations, "holding_steps": holding, "steps": steps}


def measure(streams: int, steps: int) -> dict:
    import numba

    numba.set_num_threads(1)
    envs = {v: _make(v) for v in VARIANTS}
    for env in envs.values():  # compile and warm up outside the timing
        _stream(env, "random", 999, 20)
    rows = {}
    for mode in ("random", "scripted"):
        per = {v: [] for v in VARIANTS}
        for s in range(streams):
            for v, env in envs.items():
                per[v].append(_stream(env, mode, 7000 + s, steps))
        for v, runs in per.items():
            ms = [1e3 * r["wall_s"] / r["steps"] for r in runs]
            its = [r["iterations"] / r["steps"] for r in runs]
            us = [1e6 * r["wall_s"] / r["iterations"] for r in runs]
            rows[f"{mode}|{v}"] = {"mode": mode, "variant": v, "streams": runs,
                                   "ms_per_step": float(np.median(ms)), "iterations_per_step": float(np.median(its)),
                                   "us_per_iteration": float(np.median(us)),
                                   "holding_fraction": float(sum(r["holding_steps"] for r in runs)
                                                             / sum(r["steps"] for r in runs))}
        # ratios per stream (each pair ran back to back), then their median
        two, one = per[VARIANTS[0]], per[VARIANTS[1]]
        rows[f"{mode}|ratio"] = {
            "mode": mode, "step_cost_ratio": float(np.median([a["wall_s"] / b["wall_s"] for a, b in zip(two, one)])),
            "iteration_ratio": float(np.median([a["iterations"] / b["iterations"] for a, b in zip(two, one)])),
            "per_iteration_ratio": float(np.median([(a["wall_s"] / a["iterations"]) / (b["wall_s"] / b["iterations"])
                                                    for a, b in zip(two, one)]))}
    return rows


def report(data: dict) -> str:
    rows = data["rows"]
    table = []
    for mode in ("random", "scripted"):
        for v in VARIANTS:
            r = rows[f"{mode}|{v}"]
            table.append([mode, v, f"{r['ms_per_step']:.2f}", f"{r['iterations_per_step']:.1f}",
                          f"{r['us_per_iteration']:.0f}", f"{r['holding_fraction']:.2f}"])
    lines = [f"{generated_by(data)}; {data['note']}\n",
             f"{ENV_ID}, single env, one thread, {data['streams']} streams of {data['steps']} env steps per mode "
             "(seeds 7000+), the two envs alternating per stream. Medians over the streams.\n",
             markdown_table(["actions", "env", "ms per env step", "L-BFGS iterations per env step",
                             "us per iteration (whole step)", "fraction of steps holding tissue"], table)]
    for mode in ("random", "scripted"):
        r = rows[f"{mode}|ratio"]
        lines.append(f"- {mode} actions: a two-grasper step costs {r['step_cost_ratio']:.2f}x a one-grasper step; "
                     f"it takes {r['iteration_ratio']:.2f}x the iterations, each costing {r['per_iteration_ratio']:.2f}x.")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--streams", type=int, default=8, help="seeded streams per mode and env (default 8)")
    ap.add_argument("--steps", type=int, default=300, help="env steps per stream (default 300)")
    ap.add_argument("--note", default="nothing else running", help="what else ran on the machine")
    ap.add_argument("--from-json", action="store_true", help="rewrite the table from the stored result")
    args = ap.parse_args(argv)
    for name in ("streams", "steps"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be a positive integer, got {getattr(args, name)}")
    data = None
    if not args.from_json:
        t0 = time.perf_counter()
        rows = measure(args.streams, args.steps)
        data = {"machine": machine_info(), "command": "python benchmarks/speed/grasper_cost.py",
                "streams": args.streams, "steps": args.steps, "note": args.note, "rows": rows,
                "wall_s": time.perf_counter() - t0}
    store_and_report("grasper_cost", data, report, envs=[ENV_ID])


if __name__ == "__main__":
    main()
