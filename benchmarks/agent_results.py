"""Learning results: PPO and SAC on both retraction tasks, success rate vs env steps.

Trains every run of ``RUNS`` with the shipped configs (``heml_gym.agents.train.train``,
exactly what ``heml-gym train CONFIG --seed S`` does) into ``runs/results/``, skipping runs
whose folder already holds a ``model.zip``; then evaluates each final policy on
``--episodes`` fresh seeded episodes (seeds 20000+, unseen in training and in the
periodic evaluations) and the scripted baseline on the same seeds. Writes
docs/benchmarks/agent_results.{json,md} and docs/img/agent_results.png (success rate vs
env steps and vs wall time, mean over seeds with each seed drawn thin).

    python benchmarks/agent_results.py [--episodes 100] [--only tissue_ppo] [--summarise]

Budget on the shared 2-core machine: about an hour for all runs.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before Numba / PyTorch start OpenMP

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import IMAGES, RESULTS, ROOT, machine_info, markdown_table, write_json  # noqa: E402

#: (config name, seeds)
RUNS = [("tissue_ppo", (0, 1, 2)), ("organ_ppo", (0,)), ("tissue_sac", (0,)), ("organ_sac", (0,))]
RUN_ROOT = ROOT / "runs" / "results"
EVAL_SEED = 20_000
BAR_SUCCESS, BAR_STEPS = 0.9, 1_000_000
LAPGYM_STEPS = 10_000_000  # LapGym's PPO budget for tissue retraction (8 processes)


def run_folder(config: str, seed: int) -> Path:
    return RUN_ROOT / f"{config}-seed{seed}"


def train_all(only) -> None:
    from heml_gym.agents.config import load_config
    from heml_gym.agents.train import train

    for config, seeds in RUNS:
        if only and config not in only:
            continue
        for seed in seeds:
            folder = run_folder(config, seed)
            if (folder / "model.zip").is_file():
                print(f"{folder}: done already, skipped")
                continue
            cfg = load_config(ROOT / "configs" / f"{config}.yaml", {"seed": seed})
            print(f"== training {config} seed {seed} -> {folder}", flush=True)
            start = time.perf_counter()
            train(cfg, run_dir=folder, progress_bar=False)
            print(f"   {time.perf_counter() - start:.0f} s", flush=True)


def first_crossing(history: list[dict], level: float):
    """(env steps, wall s) of the first evaluation at or above ``level``, or (None, None)."""
    for h in history:
        if h["success_rate"] >= level:
            return h["timesteps"], h.get("wall_s")
    return None, None


def evaluate_all(episodes: int, only) -> dict:
    import json

    from heml_gym.agents.train import evaluate_policy, load_policy
    from heml_gym.envs.scripted import scripted_policy

    out = {"runs": [], "scripted": {}}
    for config, seeds in RUNS:
        if only and config not in only:
            continue
        for seed in seeds:
            folder = run_folder(config, seed)
            if not (folder / "model.zip").is_file():
                continue
            policy, model, cfg = load_policy(folder)
            history = json.loads((folder / "evaluations.json").read_text())
            final = evaluate_policy(policy, cfg.env.id, episodes, seed=EVAL_SEED, obs_mode=cfg.env.obs_mode,
                                    env_kwargs=cfg.env.kwargs)
            steps90, wall90 = first_crossing(history, BAR_SUCCESS)
            out["runs"].append({
                "config": config, "seed": seed, "env": cfg.env.id, "algorithm": cfg.algorithm.name,
                "num_envs": cfg.env.num_envs, "total_timesteps": int(model.num_timesteps),
                "wall_s": history[-1].get("wall_s"), "history": history, "final": final,
                "first_eval_at_90pct_steps": steps90, "first_eval_at_90pct_wall_s": wall90,
            })
            print(f"{config} seed {seed}: success {final['success_rate']:.0%} over {episodes} episodes; "
                  f"first >= 90 % evaluation at {steps90} steps", flush=True)
            if cfg.env.id not in out["scripted"]:
                import gymnasium as gym

                scene = gym.make(cfg.env.id, **cfg.env.kwargs).unwrapped.scene
                out["scripted"][cfg.env.id] = evaluate_policy(
                    scripted_policy(scene), cfg.env.id, episodes, seed=EVAL_SEED, env_kwargs=cfg.env.kwargs)
    return out


def chart(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    envs = sorted({r["env"] for r in results["runs"]}, reverse=True)
    fig, axes = plt.subplots(2, len(envs), figsize=(6.2 * len(envs), 8.2), squeeze=False)
    colours = {"PPO": "tab:blue", "SAC": "tab:orange"}
    for col, env in enumerate(envs):
        for row, (key, label, scale) in enumerate([("timesteps", "env steps", 1e3), ("wall_s", "wall time (min)", 60.0)]):
            ax = axes[row, col]
            for algo in ("PPO", "SAC"):
                runs = [r for r in results["runs"] if r["env"] == env and r["algorithm"] == algo]
                if not runs:
                    continue
                for r in runs:
                    xs = [h[key] / scale for h in r["history"]]
                    ax.plot(xs, [h["success_rate"] for h in r["history"]], color=colours[algo], alpha=0.35, lw=1)
                n = min(len(r["history"]) for r in runs)
                xs = np.mean([[h[key] / scale for h in r["history"][:n]] for r in runs], axis=0)
                ys = np.mean([[h["success_rate"] for h in r["history"][:n]] for r in runs], axis=0)
                ax.plot(xs, ys, color=colours[algo], lw=2.2, marker="o", ms=3,
                        label=f"{algo} ({len(runs)} seed{'s' if len(runs) > 1 else ''}"
                              f"{', mean' if len(runs) > 1 else ''})")
            scripted = results["scripted"].get(env)
            if scripted:
                ax.axhline(scripted["success_rate"], color="k", ls=":", lw=1.2,
                           label=f"scripted baseline ({scripted['success_rate']:.0%})")
            ax.axhline(BAR_SUCCESS, color="tab:red", ls="--", lw=1, label="bar: 90 %")
            ax.set_ylim(-0.03, 1.03)
            ax.set_xlabel(label + (" (thousands)" if key == "timesteps" else ""))
            ax.set_ylabel("evaluated success rate (20 episodes)")
            ax.set_title(f"{env.split('/')[-1]}: success vs {label}")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8, loc="lower right")
    fig.suptitle("Training on the shared 2-core machine (periodic deterministic evaluations)", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown(results: dict) -> str:
    rows = []
    for r in results["runs"]:
        f = r["final"]
        lo, hi = f["success_ci95"]
        rows.append([r["env"].split("/")[-1], r["algorithm"], r["seed"], r["num_envs"], f"{r['total_timesteps']:,}",
                     f"{r['wall_s'] / 60:.1f}" if r["wall_s"] else "-",
                     f"{r['first_eval_at_90pct_steps']:,}" if r["first_eval_at_90pct_steps"] else "never",
                     f"{r['first_eval_at_90pct_wall_s'] / 60:.1f}" if r["first_eval_at_90pct_wall_s"] else "-",
                     f"{f['success_rate']:.0%} ({lo:.0%}-{hi:.0%})", f"{f['mean_final_exposure']:.2f}",
                     f"{f['mean_max_strain']:.2f}", f"{f['mean_episode_length']:.1f}"])
    for env, s in results["scripted"].items():
        lo, hi = s["success_ci95"]
        rows.append([env.split("/")[-1], "scripted", "-", "-", "-", "-", "-", "-",
                     f"{s['success_rate']:.0%} ({lo:.0%}-{hi:.0%})", f"{s['mean_final_exposure']:.2f}",
                     f"{s['mean_max_strain']:.2f}", f"{s['mean_episode_length']:.1f}"])
    n = results["episodes"]
    return (
        "# Learning results\n\n"
        f"Written by `benchmarks/agent_results.py`. Final success over {n} fresh seeded episodes "
        f"(seeds {EVAL_SEED}+, 95 % Wilson interval), deterministic policies. LapGym's PPO budget for "
        f"its retraction task: {LAPGYM_STEPS:,} env steps on 8 processes.\n\n"
        + markdown_table(["env", "agent", "seed", "scenes", "env steps", "wall min", "first eval >= 90 % at (steps)",
                          "(wall min)", f"final success ({n} episodes)", "final exposure", "max strain",
                          "episode length"], rows)
        + "\nChart: `docs/img/agent_results.png`.\n"
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=100, help="final evaluation episodes per run")
    ap.add_argument("--only", nargs="*", help="config names to train / evaluate (default: all)")
    ap.add_argument("--summarise", action="store_true", help="do not train; evaluate and chart what exists")
    args = ap.parse_args(argv)
    if not args.summarise:
        train_all(args.only)
    results = {"machine": machine_info(), "episodes": args.episodes, "eval_seed": EVAL_SEED,
               **evaluate_all(args.episodes, args.only)}
    write_json("agent_results.json", results)
    (RESULTS / "agent_results.md").write_text(markdown(results))
    IMAGES.mkdir(parents=True, exist_ok=True)
    chart(results, IMAGES / "agent_results.png")
    print(f"wrote {RESULTS / 'agent_results.md'} and {IMAGES / 'agent_results.png'}")


if __name__ == "__main__":
    main()
