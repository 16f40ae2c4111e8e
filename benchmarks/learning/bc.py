"""Behaviour cloning across seeds: BC from 100 noisy scripted episodes per env.

Records each env's demonstration dataset once (``heml-gym demos ENV --policy scripted
--episodes 100 --action-noise 0.3``, seeds 0-99, into ``runs/minari``), then fits ``configs/<env>_bc.yaml``
for each seed on a local Ray instance (one CPU per trial, ``heml-gym sweep``; finished
trials are kept) and stores per seed the final success on 20 fresh episodes (the same
evaluation seeds as the RL results), as ``docs/benchmarks/<env>_bc_sweep.{json,md}``
(the RL sweeps' format, so ``agent_results.py`` lists BC beside PPO and SAC and charts it).

    python -m heml_gym.benchmarks.learning.bc [--envs tissue,organ] [--seeds 0,1,2,3,4]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from heml_gym.benchmarks.common import ROOT, markdown_table, store_and_report

#: env name -> its BC config
CONFIGS = {"tissue": "configs/tissue_bc.yaml", "organ": "configs/organ_bc.yaml", "bimanual": "configs/bimanual_bc.yaml",
           "manipulation": "configs/manipulation_bc.yaml", "push": "configs/push_bc.yaml",
           "dissection": "configs/dissection_bc.yaml"}


def table(result: dict, name: str) -> str:
    """The seeds' final success (BC has one evaluation: no curve over env steps)."""
    m, d = result["machine"], result["demos"]
    head = (f"`{result['config']}` with {len(result['seeds'])} seeds on {m['cpu']} ({m['cores']} cores), {m['date']}, "
            f"one CPU per seed (`{result['command']}`). BC from {d['episodes']} episodes ({d['transitions']:,} "
            f"transitions) of the {d['policy']} policy, its velocity commands executed with Gaussian noise of "
            f"standard deviation {d['action_noise']:g} (its own actions the labels: Minari dataset "
            f"`{d['dataset']}`); no env steps while it learns. Final success: 20 fresh seeded evaluation "
            "episodes (the RL results' evaluation seeds), deterministic policy, 95 % Wilson interval.\n\n")
    rows = []
    for s in result["seeds"]:
        if s["status"] != "finished":
            rows.append([s["seed"], s["status"], "-"])
            continue
        lo, hi = s["success_ci95"]
        rows.append([s["seed"], f"{s['success_rate']:.0%} ({lo:.0%}-{hi:.0%})", f"{s['wall_s'] / 60:.1f}"])
    summary = (f"\n**{result['seeds_at_90_percent']} of {result['seeds_finished']} seeds reach >= 90 %**; IQM of the "
               f"final success across seeds {result['iqm']:.0%} (95 % bootstrap interval "
               f"{result['iqm_ci95'][0]:.0%}-{result['iqm_ci95'][1]:.0%}).\n" if "iqm" in result else "")
    return head + markdown_table(["seed", "final success", "wall min (fit and evaluation)"], rows) + summary


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", default="tissue,organ", help=f"comma-separated, of {', '.join(CONFIGS)}")
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--out", default=str(ROOT / "runs"), help="where the run folders and datasets go")
    ap.add_argument("--from-json", action="store_true", help="rewrite the reports from the stored results")
    args = ap.parse_args(argv)
    envs = [e for e in args.envs.split(",") if e]
    unknown = [e for e in envs if e not in CONFIGS]
    if unknown or not envs:
        ap.error(f"--envs: give names among {', '.join(CONFIGS)}, got {args.envs!r}")
    if args.from_json:
        for env in envs:
            name = f"{env}_bc_sweep"
            store_and_report(name, None, lambda result, name=name: table(result, name))
        return 0
    seeds = [int(s) for s in args.seeds.split(",")]
    out = Path(args.out)
    root = str((out / "minari").resolve())

    import minari

    from heml_gym.agents.demos import record_config_demos
    from heml_gym.agents.sweep import plan_sweep, run_sweep
    from heml_gym.benchmarks.learning.quick_sweep import collect

    for env in envs:
        config = ROOT / CONFIGS[env]
        sweep_dir = out / f"sweep-{env}_bc"
        trials = plan_sweep(config, seeds, {"demos.root": root}, {}, sweep_dir)
        cfg = trials[0].config
        summary = record_config_demos(cfg)  # once, before the trials read it in parallel
        if summary is not None:
            print(f"{cfg.demos.dataset}: {summary['episodes']} episodes, {summary['steps']} steps, demonstrator "
                  f"success {summary['success_rate']:.0%}", flush=True)
        summary = run_sweep(trials, sweep_dir, verbose=False)
        name = f"{env}_bc_sweep"
        command = f"python -m heml_gym.benchmarks.learning.bc --envs {env}" + (
            f" --seeds {args.seeds}" if args.seeds != ap.get_default("seeds") else "")
        result = collect(trials, summary, config, max(1, os.cpu_count() or 1), command)
        dataset = minari.load_dataset(cfg.demos.dataset)
        result["demos"] = {"dataset": cfg.demos.dataset, "policy": cfg.demos.policy,
                           "action_noise": cfg.demos.action_noise,
                           "episodes": int(dataset.total_episodes), "transitions": int(dataset.total_steps)}
        result["note"] = (f"BC from {dataset.total_episodes} episodes ({dataset.total_steps:,} transitions) of the "
                          f"{cfg.demos.policy} policy, its velocity commands executed with Gaussian noise of "
                          f"standard deviation {cfg.demos.action_noise:g} (its own actions the labels); it takes no env steps while it learns (the env steps column: "
                          "demonstration transitions).")
        store_and_report(name, result, lambda result, name=name: table(result, name), envs=[cfg.env.id])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
