"""The README's main job across seeds: configs/quick.yaml trained with several seeds.

Runs (or resumes: finished trials are kept) ``heml-gym sweep configs/quick.yaml`` on a
local Ray instance, one CPU per trial, then stores what the README and docs quote:
per seed its evaluation history, final success on 20 fresh episodes (95 % Wilson
interval), the first evaluation at >= 90 %, and wall time; across seeds the IQM of the
final success with a 95 % bootstrap interval.

Writes docs/benchmarks/quick_sweep.json, .md and docs/img/quick_sweep.png (``--name``
for another config's results).

    python benchmarks/learning/quick_sweep.py [--seeds 0,1,2,3,4,5,6,7,8,9] [--config configs/quick.yaml] [--out runs/sweep-quick] [--name quick_sweep] [--note TEXT]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from heml_gym.benchmarks.common import IMAGES, RESULTS, ROOT, machine_info, markdown_table, write_json


def collect(trials, summary: dict, config_path: Path, concurrent: int, command: str,
            cpus_per_trial: float = 1) -> dict:
    from heml_gym.agents.stats import iqm, iqm_interval

    seeds = []
    for t, record in zip(trials, summary["trials"]):
        if record["status"] != "finished":
            seeds.append({"seed": t.seed, "status": record["status"], "error": record.get("error")})
            continue
        history = json.loads((t.run_dir / "evaluations.json").read_text())
        evaluations = [{"env_steps": e["timesteps"], "success_rate": e["success_rate"],
                        **({"wall_s": e["wall_s"]} if "wall_s" in e else {})} for e in history]
        first = next((e["env_steps"] for e in evaluations if e["success_rate"] >= 0.9), None)
        seeds.append({"seed": t.seed, "status": "finished", "env_steps": record["env_steps"],
                      "wall_s": record["wall_s"], "success_rate": record["success_rate"],
                      "success_ci95": record["success_ci95"], "first_eval_at_90_percent": first,
                      "stopped_early": record.get("stopped_early", False), "evaluations": evaluations})
    finals = [s["success_rate"] for s in seeds if s["status"] == "finished"]
    from heml_gym.agents.config import load_config

    cfg = load_config(config_path)
    out = {"machine": machine_info(), "config": str(config_path.relative_to(ROOT)),
           "evaluation_every_steps": cfg.evaluation.every_steps,
           "trials_at_once": concurrent, "cpus_per_trial": cpus_per_trial, "command": command, "seeds": seeds,
           "seeds_at_90_percent": sum(f >= 0.9 for f in finals), "seeds_finished": len(finals)}
    if cfg.evaluation.stop_at_success is not None:
        out["stop_rule"] = {"stop_at_success": cfg.evaluation.stop_at_success, "stop_after": cfg.evaluation.stop_after,
                            "cap": cfg.algorithm.total_timesteps}
    if finals:
        out["iqm"] = iqm(finals)
        out["iqm_ci95"] = list(iqm_interval(finals))
    return out


def cpus(n: float) -> str:
    """``n`` CPUs in words: "one CPU", "2 CPUs"."""
    return "one CPU" if n == 1 else f"{n:g} CPUs"


def table(result: dict, name: str = "quick_sweep") -> str:
    from heml_gym.agents.stats import SEEDS_FOR_AN_IQM

    m = result["machine"]
    rows = []
    for s in result["seeds"]:
        if s["status"] != "finished":
            rows.append([s["seed"], s["status"], "-", "-", "-", s.get("error") or "-"])
            continue
        lo, hi = s["success_ci95"]
        history = " / ".join(f"{e['success_rate']:.0%}" for e in s["evaluations"])
        first = f"{s['first_eval_at_90_percent']:,}" if s["first_eval_at_90_percent"] is not None else "never"
        steps = f"{s['env_steps']:,}" + (" (stopped: learned)" if s.get("stopped_early") else "")
        rows.append([s["seed"], f"{s['success_rate']:.0%} ({lo:.0%}-{hi:.0%})", first, history,
                     steps, f"{s['wall_s'] / 60:.1f}"])
    stop = result.get("stop_rule")
    stopping = (f" Training stops once {stop['stop_after']} evaluations in a row reach {stop['stop_at_success']:.0%} "
                f"success (cap {stop['cap']:,} env steps); the final success is then measured on 20 episodes the "
                "evaluations never saw." if stop else "")
    head = (f"`{result['config']}` with {len(result['seeds'])} seeds on {m['cpu']} ({m['cores']} cores), "
            f"{m['date']}, {result['trials_at_once']} at a time with {cpus(result.get('cpus_per_trial', 1))} each "
            f"(`{result.get('command', 'python benchmarks/learning/quick_sweep.py')}`). Final success: 20 fresh seeded evaluation episodes, "
            "deterministic policy, 95 % Wilson interval." + stopping + (f" {result['note']}" if result.get("note") else "") + "\n\n")
    summary = f"\n**{result['seeds_at_90_percent']} of {result['seeds_finished']} seeds reach >= 90 %**"
    if "iqm" in result and result["seeds_finished"] >= SEEDS_FOR_AN_IQM:
        summary += (f"; IQM of the final success across seeds {result['iqm']:.0%} (95 % bootstrap interval "
                    f"{result['iqm_ci95'][0]:.0%}-{result['iqm_ci95'][1]:.0%})")
    summary += ".\n"
    chart = f"\n![success vs env steps, every seed and the IQM](../img/{name}.png)\n"
    return head + markdown_table(["seed", "final success", "first eval >= 90 % at (steps)",
                                  f"evaluations (every {result.get('evaluation_every_steps', 40000) // 1000} k steps)",
                                  "env steps", "wall min"], rows) + summary + chart


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2,3,4,5,6,7,8,9")
    ap.add_argument("--config", default=str(ROOT / "configs" / "quick.yaml"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "sweep-quick"))
    ap.add_argument("--cpus-per-trial", type=float, default=1)
    ap.add_argument("--name", default="quick_sweep", help="name of the results: docs/benchmarks/NAME.{json,md}")
    ap.add_argument("--note", default="", help="what else ran on the machine meanwhile (printed with the results)")
    ap.add_argument("--loaded", action="store_true",
                    help="other work shared the machine's cores meanwhile, so the wall times are high (stored as "
                         "machine_loaded; readme_results.py says so beside them)")
    args = ap.parse_args(argv)

    import os

    from heml_gym.agents.sweep import chart, plan_sweep, run_sweep

    trials = plan_sweep(args.config, [int(s) for s in args.seeds.split(",")], {}, {}, args.out)
    summary = run_sweep(trials, args.out, cpus_per_trial=args.cpus_per_trial, verbose=False)
    concurrent = max(1, int((os.cpu_count() or 1) // args.cpus_per_trial))
    config = Path(args.config).resolve()
    command = "python benchmarks/learning/quick_sweep.py" + (
        f" --config {config.relative_to(ROOT)} --name {args.name}" if args.name != "quick_sweep" else "") + (
        f" --seeds {args.seeds}" if args.seeds != ap.get_default("seeds") else "") + (
        f" --cpus-per-trial {args.cpus_per_trial:g}" if args.cpus_per_trial != 1 else "")
    result = collect(trials, summary, config, concurrent, command, args.cpus_per_trial)
    if args.note:
        result["note"] = args.note
    if args.loaded:
        result["machine_loaded"] = True
    from heml_gym.agents.config import load_config

    write_json(f"{args.name}.json", result, envs=[load_config(config).env.id])  # (the task version it measured)
    text = table(result, args.name)
    (RESULTS / f"{args.name}.md").write_text(text)
    IMAGES.mkdir(parents=True, exist_ok=True)
    chart(trials, summary, IMAGES / f"{args.name}.png")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
