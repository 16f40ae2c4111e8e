"""RLlib PPO learning on TissueRetraction-v1: the distributed-sampling path learns the task.

Trains ``configs/tissue_rllib_ppo.yaml`` (RLlib PPO, env runners each holding a batched
vector env of 16 scenes) on a local Ray instance, evaluating every 25 k env steps on 20
fresh seeded episodes (deterministic policy, the same evaluation as ``heml-gym eval``),
and stores the evaluation history, wall time, median sampling+training env steps per
second and the first evaluation at >= 90 % success.

Writes docs/benchmarks/rllib_learning.{json,md} and docs/img/rllib_learning.png.

    python benchmarks/learning/rllib_learning.py [--seed 0] [--config configs/tissue_rllib_ppo.yaml] [--out runs/rllib-learning]
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path
from heml_gym.benchmarks.common import IMAGES, RESULTS, ROOT, machine_info, markdown_table, write_json


def table(result: dict) -> str:
    m = result["machine"]
    rows = [[f"{e['timesteps']:,}", f"{e['success_rate']:.0%} ({e['success_ci95'][0]:.0%}-{e['success_ci95'][1]:.0%})",
             f"{e['wall_s'] / 60:.1f}"] for e in result["evaluations"]]
    first = result["first_eval_at_90_percent"]
    head = (f"`{result['config']}`, seed {result['seed']}, {result['env_runners']} env runners of "
            f"{result['scenes_per_runner']} scenes on a local Ray instance, {m['cpu']} ({m['cores']} cores), "
            f"{m['date']} (`python benchmarks/learning/rllib_learning.py`). Each evaluation: 20 fresh seeded episodes, "
            "deterministic policy, 95 % Wilson interval.\n\n")
    tail = (f"\nFirst evaluation at >= 90 %: **{first:,} env steps** " if first is not None
            else "\n**No evaluation reached 90 %** ")
    tail += (f"(final {result['final_success_rate']:.0%} at {result['env_steps']:,} steps; "
             f"{result['wall_s'] / 60:.1f} min in all, {result['env_steps_per_s']:.0f} env steps/s "
             "while training, median over iterations).\n")
    return head + markdown_table(["env steps", "success (95 % interval)", "wall min"], rows) + tail


def plot(result: dict, path: Path) -> None:
    try:
        import matplotlib
    except ImportError:
        return
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [e["timesteps"] for e in result["evaluations"]]
    rate = [e["success_rate"] for e in result["evaluations"]]
    lo = [e["success_ci95"][0] for e in result["evaluations"]]
    hi = [e["success_ci95"][1] for e in result["evaluations"]]
    fig, ax = plt.subplots(figsize=(5, 3.4))
    ax.fill_between(steps, lo, hi, color="C1", alpha=0.2, label="95 % Wilson interval")
    ax.plot(steps, rate, color="C1", marker="o", label=f"RLlib PPO, seed {result['seed']}")
    ax.axhline(0.9, color="0.5", ls="--", lw=1)
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("env steps")
    ax.set_ylabel("evaluated success rate")
    ax.set_title(f"RLlib PPO on TissueRetraction-v1 ({result['machine']['cpu']})", fontsize=9)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--config", default=str(ROOT / "configs" / "tissue_rllib_ppo.yaml"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "rllib-learning"))
    args = ap.parse_args(argv)

    from heml_gym.agents.config import load_config
    from heml_gym.agents.rllib_backend import train_rllib

    cfg = load_config(args.config, {"seed": args.seed})
    run_dir = Path(args.out).resolve() / f"{cfg.name}-seed{args.seed}"
    if run_dir.exists():
        shutil.rmtree(run_dir)  # a fresh run: RLlib's learning is measured from step 0
    started = time.perf_counter()
    out = train_rllib(cfg, run_dir)
    wall = time.perf_counter() - started
    history = json.loads((run_dir / "evaluations.json").read_text())
    first = next((e["timesteps"] for e in history if e["success_rate"] >= 0.9), None)
    hp = cfg.algorithm.hyperparameters
    result = {"machine": machine_info(), "config": str(Path(args.config).resolve().relative_to(ROOT)),
              "seed": args.seed, "env_runners": int(hp.get("num_env_runners", 1)),
              "scenes_per_runner": cfg.env.num_envs, "env_steps": out["timesteps"], "wall_s": wall,
              "env_steps_per_s": out["env_steps_per_s"], "final_success_rate": history[-1]["success_rate"],
              "first_eval_at_90_percent": first, "evaluations": history}
    write_json("rllib_learning.json", result)
    text = table(result)
    (RESULTS / "rllib_learning.md").write_text(text + "\n![RLlib PPO success vs env steps](../img/rllib_learning.png)\n")
    IMAGES.mkdir(parents=True, exist_ok=True)
    plot(result, IMAGES / "rllib_learning.png")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
