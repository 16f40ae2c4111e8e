"""Cost-constrained PPO against PPO: success and tissue damage across seeds.

Trains, on one env, its PPO config and the same config with a damage budget
(PPO-Lagrangian, :mod:`heml_gym.agents.constraint`) for the same seeds and env steps on a
local Ray instance (one CPU per trial, finished trials are kept), then stores per seed
and method the final success on 20 fresh episodes (95 % Wilson interval) and the mean
episode damage (strain x s above the safe strain, the summed ``info["cost"]``) of those
episodes; across seeds the IQM of each with a 95 % bootstrap interval; and a chart:
success against damage for every seed (the Pareto view) beside damage and success
against env steps.

Writes docs/benchmarks/constrained_ENV.json, .md and docs/img/constrained_ENV.png.

    python -m heml_gym.benchmarks.learning.constrained --env tissue [--seeds 0,1,2,3,4] [--steps 240000] [--out runs/constrained-tissue]
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np

from heml_gym.benchmarks.common import IMAGES, RESULTS, ROOT, machine_info, markdown_table, store_and_report

#: per env: the unconstrained config and its constrained twin (same algorithm and settings)
CONFIGS = {
    "tissue": ("configs/quick.yaml", "configs/tissue_ppo_lagrangian.yaml"),
    "organ": ("configs/organ_ppo.yaml", "configs/organ_ppo_lagrangian.yaml"),
    "dissection": ("configs/dissection_ppo.yaml", "configs/dissection_ppo_lagrangian.yaml"),
}
METHODS = ("PPO", "PPO-Lagrangian")
#: per env: what its harm (the summed ``info["cost"]``) is counted in, and what it counts
HARM = {
    "tissue": ("strain x s", "strain x s above the safe strain"),
    "organ": ("strain x s", "strain x s above the safe strain"),
    "dissection": ("harm", "strain x s above the safe strain, plus 0.01 per joule of collateral heat, plus 10 "
                           "for energy near the common bile duct"),
}


def harm_of(result: dict) -> tuple[str, str]:
    """``(unit, what it counts)`` of a stored comparison's harm."""
    return HARM[result["name"].removeprefix("constrained_")]


def collect_seed(trial) -> dict:
    """One finished trial's final evaluation and histories (success, damage, multiplier)."""
    from heml_gym.agents.sweep import RESULT_FILE

    if not (trial.run_dir / RESULT_FILE).is_file():
        raise SystemExit(f"{trial.name} did not finish (no {trial.run_dir / RESULT_FILE}): see the sweep's "
                         "output above; run the same command again to resume")
    record = json.loads((trial.run_dir / RESULT_FILE).read_text())
    history = json.loads((trial.run_dir / "evaluations.json").read_text())
    final = history[-1]
    if "endings" not in final:  # (runs from before evaluations counted them) the final episodes again
        final = dict(final, endings=endings(trial.run_dir, final.get("seed", 10_000), final["episodes"]))
    out = {"seed": trial.seed, "env_steps": record["env_steps"], "wall_s": record["wall_s"],
           "success_rate": final["success_rate"], "success_ci95": final["success_ci95"],
           "mean_damage": final["mean_damage"], "episodes_with_damage": final["episodes_with_damage"],
           # the harm while learning: the evaluations' mean damage averaged over training
           "damage_while_training": float(np.mean([e["mean_damage"] for e in history])),
           "episodes": final["episodes"], "endings": final["endings"],
           "evaluations": [{"env_steps": e["timesteps"], "success_rate": e["success_rate"],
                            "mean_damage": e["mean_damage"], "mean_episode_length": e.get("mean_episode_length"),
                            "mean_final_exposure": e.get("mean_final_exposure")} for e in history]}
    constraint = trial.run_dir / "constraint.json"
    if constraint.is_file():
        steps = json.loads(constraint.read_text())["history"]
        out["multiplier_final"] = steps[-1]["multiplier"] if steps else 0.0
        out["multiplier"] = [{"env_steps": s["timesteps"], "multiplier": s["multiplier"],
                              "episode_cost": s["episode_cost"]} for s in steps]
    return out


def endings(run_dir: Path, seed: int, episodes: int) -> dict:
    """How the final policy of ``run_dir`` ends its evaluation episodes (seeds ``seed``,
    ``seed + 1``, ...; deterministic, so they are the final evaluation's episodes)."""
    from heml_gym.agents.evaluation import evaluate_policy
    from heml_gym.agents.train import load_policy

    policy, _, cfg = load_policy(run_dir)
    return evaluate_policy(policy, cfg.env.id, episodes, seed=seed, obs_mode=cfg.env.obs_mode,
                           env_kwargs=cfg.env.kwargs)["endings"]


def summarise(seeds: list[dict]) -> dict:
    from heml_gym.agents.stats import iqm, iqm_interval

    success = [s["success_rate"] for s in seeds]
    damage = [s["mean_damage"] for s in seeds]
    learning = [s["damage_while_training"] for s in seeds]
    return {"seeds": seeds, "seeds_at_90_percent": sum(x >= 0.9 for x in success),
            "success_iqm": iqm(success), "success_iqm_ci95": list(iqm_interval(success)),
            "damage_iqm": iqm(damage), "damage_iqm_ci95": list(iqm_interval(damage)),
            "damage_while_training_iqm": iqm(learning),
            "damage_while_training_iqm_ci95": list(iqm_interval(learning))}


def ending_text(seed: dict) -> str:
    """How a seed's final episodes ended, e.g. "12 torn, 8 out of time" ("-" when not recorded)."""
    words = {"success": "succeeded", "torn": "torn", "critical": "at the critical structure", "solver": "solver failed",
             "time": "out of time", "other": "other"}
    counts = seed.get("endings")
    if not counts:
        return "-"
    return ", ".join(f"{n} {words[k]}" for k, n in counts.items() if n)


def table(result: dict) -> str:
    m = result["machine"]
    unit, counts = harm_of(result)
    counts = counts.replace("safe strain", f"safe strain {result['safe_strain']:g}")
    head = (f"PPO and PPO-Lagrangian (damage budget {result['budget']:g} {unit} per episode) on "
            f"`{result['env_id']}`, {len(result['methods']['PPO']['seeds'])} seeds, {result['env_steps']:,} env "
            f"steps each, on {m['cpu']} ({m['cores']} cores), {m['date']}, one CPU per run "
            f"(`{result['command']}`). Final success and damage: 20 fresh seeded evaluation episodes, "
            f"deterministic policy; damage is the episode's summed `info[\"cost\"]` ({counts}), averaged over the "
            "episodes.\n\n")
    rows = []
    ended = any("endings" in s for method in METHODS for s in result["methods"][method]["seeds"])
    for method in METHODS:
        for s in result["methods"][method]["seeds"]:
            lo, hi = s["success_ci95"]
            rows.append([method, s["seed"], f"{s['success_rate']:.0%} ({lo:.0%}-{hi:.0%})", f"{s['mean_damage']:.4f}",
                         f"{s['damage_while_training']:.3f}",
                         f"{s['episodes_with_damage']} / {s['episodes']}", *([ending_text(s)] if ended else []),
                         f"{s['multiplier_final']:.2f}" if "multiplier_final" in s else "-",
                         f"{s['wall_s'] / 60:.1f}"])
    summary_rows = []
    for method in METHODS:
        r = result["methods"][method]
        harmed = sum(s["episodes_with_damage"] for s in r["seeds"])
        episodes = sum(s["episodes"] for s in r["seeds"])
        summary_rows.append([method, f"{r['seeds_at_90_percent']} of {len(r['seeds'])}",
                             f"{r['success_iqm']:.0%} ({r['success_iqm_ci95'][0]:.0%}-{r['success_iqm_ci95'][1]:.0%})",
                             f"{r['damage_iqm']:.4f} ({r['damage_iqm_ci95'][0]:.4f}-{r['damage_iqm_ci95'][1]:.4f})",
                             f"{harmed} / {episodes}",
                             f"{r['damage_while_training_iqm']:.3f} ({r['damage_while_training_iqm_ci95'][0]:.3f}-"
                             f"{r['damage_while_training_iqm_ci95'][1]:.3f})"])
    verdict = result["verdict"]
    text = (head + markdown_table(["method", "seed", "final success", f"mean damage ({unit})",
                                   "damage while training (mean over the evaluations)",
                                   "episodes with damage", *(["final episodes ended"] if ended else []),
                                   "final multiplier", "wall min"], rows)
            + "\n\nAcross seeds (IQM, 95 % bootstrap interval):\n\n"
            + markdown_table(["method", "seeds >= 90 %", "success", f"final damage ({unit})",
                              "final episodes with damage, all seeds", "damage while training"], summary_rows)
            + f"\n\n**{verdict['text']}**\n"
            + f"\n![success vs damage per seed; damage and success vs env steps](../img/{result['name']}.png)\n")
    return text


def verdict(result: dict) -> dict:
    """The issue's bar: PPO-Lagrangian lowers the mean damage against PPO at success within 10 points
    (missed where neither method learns the task: success IQM below 50 %)."""
    ppo, lag = result["methods"]["PPO"], result["methods"]["PPO-Lagrangian"]
    unit = harm_of(result)[0]
    learned = max(lag["success_iqm"], ppo["success_iqm"]) >= 0.5  # else harm would be compared between failures
    lower = lag["damage_iqm"] < ppo["damage_iqm"]
    close = learned and lag["success_iqm"] >= ppo["success_iqm"] - 0.10
    ratio = lag["damage_iqm"] / ppo["damage_iqm"] if ppo["damage_iqm"] > 0 else float("nan")
    ratio = ratio if learned else None  # (no ratio of the harms of failures)
    learning = lag["damage_while_training_iqm"] < ppo["damage_while_training_iqm"]
    if not learned:
        text = (f"Neither method learns the task (success IQM {ppo['success_iqm']:.0%} with PPO, "
                f"{lag['success_iqm']:.0%} with PPO-Lagrangian): the bar is missed, and their harms (IQM "
                f"{ppo['damage_iqm']:.4f} and {lag['damage_iqm']:.4f} {unit}) are those of policies that fail")
    else:
        text = (f"PPO-Lagrangian {'lowers' if lower else 'does not lower'} the final damage (IQM "
                f"{lag['damage_iqm']:.4f} vs {ppo['damage_iqm']:.4f} {unit}) at success {lag['success_iqm']:.0%} vs "
                f"{ppo['success_iqm']:.0%} ({'within' if close else 'not within'} 10 points): the bar is "
                f"{'met' if lower and close else 'missed'}; while training it "
                f"{'lowers' if learning else 'does not lower'} the damage (IQM "
                f"{lag['damage_while_training_iqm']:.3f} vs {ppo['damage_while_training_iqm']:.3f})")
    return {"damage_lower": bool(lower), "success_within_10_points": bool(close), "met": bool(lower and close),
            "damage_while_training_lower": bool(learning), "damage_ratio": ratio, "text": text,
            **({} if learned else {"learned": False})}


def chart(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {"PPO": "#1f77b4", "PPO-Lagrangian": "#d62728"}
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4))
    pareto, damage_ax, success_ax = axes
    for method in METHODS:
        r = result["methods"][method]
        c = colours[method]
        xs = [s["mean_damage"] for s in r["seeds"]]
        ys = [s["success_rate"] for s in r["seeds"]]
        pareto.scatter(xs, ys, color=c, alpha=0.6, label=f"{method}: each seed")
        pareto.errorbar([r["damage_iqm"]], [r["success_iqm"]],
                        xerr=[[r["damage_iqm"] - r["damage_iqm_ci95"][0]], [r["damage_iqm_ci95"][1] - r["damage_iqm"]]],
                        yerr=[[r["success_iqm"] - r["success_iqm_ci95"][0]],
                              [r["success_iqm_ci95"][1] - r["success_iqm"]]],
                        color=c, marker="D", markersize=8, capsize=4, label=f"{method}: IQM, 95 % CI")
        for i, s in enumerate(r["seeds"]):
            steps = [e["env_steps"] / 1e3 for e in s["evaluations"]]
            damage_ax.plot(steps, [e["mean_damage"] for e in s["evaluations"]], color=c, alpha=0.7, marker="o", ms=3,
                           label=method if i == 0 else None)
            success_ax.plot(steps, [e["success_rate"] for e in s["evaluations"]], color=c, alpha=0.7, marker="o", ms=3,
                            label=method if i == 0 else None)
    damage_ax.axhline(result["budget"], color="grey", ls="--", label=f"budget {result['budget']:g}")
    pareto.set_xlim(left=0)
    damage_ax.set_ylim(bottom=0)
    unit = harm_of(result)[0]
    pareto.set(xlabel=f"mean episode damage ({unit})", ylabel="final success rate", ylim=(-0.05, 1.05),
               title="success vs damage (up and left is better)")
    damage_ax.set(xlabel="env steps (k)", ylabel=f"mean episode damage ({unit})", title="damage while training")
    success_ax.set(xlabel="env steps (k)", ylabel="success rate", ylim=(-0.05, 1.05), title="success while training")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"{result['env_id']}: PPO vs PPO-Lagrangian, {len(result['methods']['PPO']['seeds'])} seeds each")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", choices=sorted(CONFIGS), required=True)
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--steps", type=int, default=240_000, help="env steps per run (both methods)")
    ap.add_argument("--out", default=None, help="run folders (default runs/constrained-ENV)")
    ap.add_argument("--from-json", action="store_true", help="rewrite the table and chart from the stored JSON")
    args = ap.parse_args(argv)
    if args.from_json:
        name = f"constrained_{args.env}"
        result = json.loads((RESULTS / f"{name}.json").read_text())
        result["verdict"] = verdict(result)
        store_and_report(name, result, table, envs=[result["env_id"]])
        IMAGES.mkdir(parents=True, exist_ok=True)
        chart(result, IMAGES / f"{name}.png")
        return 0
    if args.steps <= 0:
        ap.error(f"--steps: give a positive number of env steps, not {args.steps}")

    from heml_gym.agents.config import load_config
    from heml_gym.agents.sweep import plan_sweep, run_sweep
    from heml_gym.envs import TaskSettings

    seeds = [int(s) for s in args.seeds.split(",")]
    out = Path(args.out or ROOT / "runs" / f"constrained-{args.env}")
    plain, constrained = (ROOT / p for p in CONFIGS[args.env])
    sets = {"algorithm.total_timesteps": args.steps}
    arms = {"PPO": plan_sweep(plain, seeds, sets, {}, out), "PPO-Lagrangian": plan_sweep(constrained, seeds, sets, {}, out)}
    # seed by seed, both methods (PPO s0, PPO-Lagrangian s0, PPO s1, ...): an interrupted
    # comparison still pairs its seeds
    run_sweep([t for pair in zip(*arms.values()) for t in pair], out, verbose=True)
    cfg = load_config(constrained)
    name = f"constrained_{args.env}"
    result = {"name": name, "machine": machine_info(), "env_id": cfg.env.id, "env_steps": args.steps,
              "configs": {m: str(Path(p).relative_to(ROOT)) for m, p in zip(METHODS, (plain, constrained))},
              "budget": cfg.constraint.budget, "multiplier_lr": cfg.constraint.multiplier_lr,
              "safe_strain": TaskSettings().safe_strain, "cpus_per_trial": 1,
              "trials_at_once": os.cpu_count() or 1,
              "command": f"python -m heml_gym.benchmarks.learning.constrained --env {args.env}"
                         + (f" --seeds {args.seeds}" if args.seeds != ap.get_default("seeds") else "")
                         + (f" --steps {args.steps}" if args.steps != ap.get_default("steps") else ""),
              "methods": {m: summarise([collect_seed(t) for t in trials]) for m, trials in arms.items()}}
    result["verdict"] = verdict(result)
    store_and_report(name, result, table, envs=[cfg.env.id])
    IMAGES.mkdir(parents=True, exist_ok=True)
    chart(result, IMAGES / f"{name}.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
