"""RLlib PPO learning on either env: the distributed-sampling path learns the task.

Trains a run config (default ``configs/tissue_rllib_ppo.yaml`` on TissueRetraction-v1;
``configs/organ_rllib_ppo.yaml`` on OrganRetraction-v2) (RLlib PPO, env runners each holding a batched
vector env of 16 scenes) on a local Ray instance, once per seed, evaluating every 25 k
env steps on 20 fresh seeded episodes (deterministic policy, the same evaluation as
``heml-gym eval``), and stores each seed's evaluation history, wall time, median
sampling+training env steps per second and first evaluation at >= 90 % success, as each
seed finishes (an interrupted study keeps the seeds it ran), then the IQM of the final
success across seeds with its 95 % bootstrap interval.

Writes docs/benchmarks/NAME.{json,md} and docs/img/NAME.png (``--name``, default
rllib_learning; the lobe's study is rllib_learning_organ).

    python -m heml_gym.benchmarks.learning.rllib_learning [--seeds 0,1,2] [--config configs/tissue_rllib_ppo.yaml]
        [--name rllib_learning] [--out runs/rllib-learning] [--from-json]
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from heml_gym.benchmarks.common import (IMAGES, ROOT, command_line, generated_by, machine_info, markdown_table,
                                       store_and_report)

NAME = "rllib_learning"
BAR = 0.9


def seed_row(s: dict) -> list:
    first = s["first_eval_at_90_percent"]
    return [s["seed"], f"{s['final_success_rate']:.0%}", f"{s['env_steps']:,}",
            f"{first:,}" if first is not None else "not reached", f"{s['wall_s'] / 60:.1f}",
            f"{s['env_steps_per_s']:.0f}"]


def report(data: dict) -> str:
    from heml_gym.agents.stats import SEEDS_FOR_AN_IQM, iqm, iqm_interval

    seeds = data["seeds"]
    head = (f"{generated_by(data)}: `{data['config']}`, {data['env_runners']} env runners of "
            f"{data['scenes_per_runner']} scenes "
            f"on a local Ray instance, one seed after another. Each evaluation: 20 fresh seeded episodes, "
            "deterministic policy; env steps/s: sampling and training, median over iterations.\n\n")
    text = head + markdown_table(["seed", "final success", "env steps", "first evaluation at >= 90 %", "wall min",
                                  "env steps/s"], [seed_row(s) for s in seeds])
    finals = [s["final_success_rate"] for s in seeds]
    reached = sum(f >= BAR for f in finals)
    text += f"\nFinal success >= 90 % on **{reached} of {len(seeds)}** seeds"
    if len(finals) >= SEEDS_FOR_AN_IQM:
        lo, hi = iqm_interval(finals)
        text += f"; IQM {iqm(finals):.0%} (95 % bootstrap interval {lo:.0%}-{hi:.0%})"
    text += "."
    if data.get("note"):  # (what else ran on the machine, added to the stored result)
        text += f" {data['note']}"
    return text + f"\n\n![RLlib PPO success vs env steps, each seed](../img/{data.get('name', NAME)}.png)\n"


def plot(data: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.4, 3.4))
    for k, s in enumerate(data["seeds"]):
        steps = [e["timesteps"] for e in s["evaluations"]]
        ax.plot(steps, [e["success_rate"] for e in s["evaluations"]], color=f"C{k}", marker="o", ms=3,
                label=f"seed {s['seed']}")
    ax.axhline(BAR, color="0.5", ls="--", lw=1)
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("env steps")
    ax.set_ylabel("evaluated success rate (20 episodes)")
    ax.set_title(f"RLlib PPO on {data['env'].split('/')[-1]}\n({data['machine']['cpu']}, "
                 f"{data['machine'].get('vector_isa', '?')})", fontsize=9)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run_seed(cfg_path: str, seed: int, out: Path) -> dict:
    """Train one seed from step 0 (its run folder replaced) and summarise its evaluations."""
    from heml_gym.agents.config import load_config
    from heml_gym.agents.rllib_backend import train_rllib

    cfg = load_config(cfg_path, {"seed": seed})
    run_dir = out / f"{cfg.name}-seed{seed}"
    if run_dir.exists():
        shutil.rmtree(run_dir)  # a fresh run: RLlib's learning is measured from step 0
    started = time.perf_counter()
    result = train_rllib(cfg, run_dir)
    wall = time.perf_counter() - started
    history = json.loads((run_dir / "evaluations.json").read_text())
    return {"seed": seed, "env_steps": result["timesteps"], "wall_s": wall,
            "env_steps_per_s": result["env_steps_per_s"],
            "final_success_rate": history[-1]["success_rate"],
            "first_eval_at_90_percent": next((e["timesteps"] for e in history if e["success_rate"] >= BAR), None),
            "evaluations": history}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2", help="seeds, comma-separated, trained one after another")
    ap.add_argument("--config", default=str(ROOT / "configs" / "tissue_rllib_ppo.yaml"))
    ap.add_argument("--name", default=NAME, help="the stored result's name (docs/benchmarks/NAME.json)")
    ap.add_argument("--out", default=str(ROOT / "runs" / "rllib-learning"), help="folder of the runs (checkpoints)")
    ap.add_argument("--from-json", action="store_true", help="only rebuild the table and chart from the stored result")
    args = ap.parse_args(argv)
    if not args.name.isidentifier():
        ap.error(f"--name must be letters, digits and underscores (a file name), got {args.name!r}")
    if args.from_json:
        data = store_and_report(args.name, None, report)
    else:
        from heml_gym.agents.config import load_config

        try:
            seeds = [int(v) for v in args.seeds.split(",")]
        except ValueError:
            ap.error(f"--seeds must be integers separated by commas, got {args.seeds!r}")
        cfg = load_config(args.config, {})
        data = {"machine": machine_info(), "command": command_line(f"heml_gym.benchmarks.learning.{NAME}", ap, args),
                "name": args.name, "config": str(Path(args.config).resolve().relative_to(ROOT)), "env": cfg.env.id,
                "env_runners": int(cfg.algorithm.hyperparameters.get("num_env_runners", 1)),
                "scenes_per_runner": cfg.env.num_envs, "seeds": []}
        for seed in seeds:
            data["seeds"].append(run_seed(args.config, seed, Path(args.out).resolve()))
            data = store_and_report(args.name, data, report, envs=[cfg.env.id])  # each seed stored as it finishes
    IMAGES.mkdir(parents=True, exist_ok=True)
    plot(data, IMAGES / f"{args.name}.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
