"""Every live task's scripted expert on episodes nobody has run.

For each registered task (``heml_gym.envs.ENV_IDS``): its scripted expert
(:func:`heml_gym.envs.scripted.scripted_policy`, what ``heml-gym eval scripted`` runs) on
``--episodes`` seeded episodes from ``--seed`` (default 40,000: no training, evaluation or
other stored result uses these seeds): success with its 95 % Wilson interval, median
episode length, the mean of each episode's largest gauge strain and the mean damage.

Writes docs/benchmarks/scripted_experts.{json,md}.

    python benchmarks/learning/scripted_experts.py [--episodes 20] [--seed 40000]
"""

from __future__ import annotations

import argparse
import time


from heml_gym.benchmarks.common import machine_info, markdown_table, store_and_report


def measure(env_id: str, episodes: int, seed: int) -> dict:
    import gymnasium as gym

    from heml_gym.agents.evaluation import evaluate_policy
    from heml_gym.envs.scripted import scripted_policy

    env = gym.make(env_id)
    policy = scripted_policy(env.unwrapped.scene)
    env.close()
    t0 = time.perf_counter()
    result = evaluate_policy(policy, env_id, episodes, seed=seed)
    return {"env": env_id, "seed": seed, "cpu_s": time.perf_counter() - t0, **result}


def report(data: dict) -> str:
    m = data["machine"]
    rows = [[f"`{r['env']}`", f"{round(r['success_rate'] * r['episodes'])} of {r['episodes']} "
             f"({100 * r['success_ci95'][0]:.0f}%-{100 * r['success_ci95'][1]:.0f}%)",
             f"{r['mean_episode_length']:.1f}", f"{r['mean_max_strain']:.3f}", f"{r['mean_damage']:.3f}"]
            for r in data["results"]]
    return (f"Each task's scripted expert on episodes seeded {data['seed']} onwards, which no training, evaluation "
            f"or other result uses ({m['cpu']}, {m['date']}; `python benchmarks/learning/scripted_experts.py`). "
            "Success as each task defines it; damage: the episode's summed `info[\"cost\"]` (strain x s).\n\n"
            + markdown_table(["task", "success (95 % interval)", "mean episode length (steps)",
                              "mean peak gauge strain", "mean damage (strain x s)"], rows))


def main(argv=None) -> int:
    from heml_gym.envs import ENV_IDS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--seed", type=int, default=40_000)
    ap.add_argument("--from-json", action="store_true", help="only rewrite the table from the stored result")
    args = ap.parse_args(argv)
    if args.episodes < 1:
        ap.error(f"--episodes: must be >= 1, got {args.episodes}")
    data = None
    if not args.from_json:
        data = {"machine": machine_info(), "seed": args.seed, "episodes": args.episodes,
                "results": [measure(env_id, args.episodes, args.seed) for env_id in ENV_IDS]}
    store_and_report("scripted_experts", data, report, envs=list(ENV_IDS))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
