"""Scale-out on Ray: RLlib sampling with 1, 2 and 4 env runners on a local 2-node cluster.

Starts a real 2-node Ray cluster on this machine (``ray.cluster_utils.Cluster``: a head and
a worker node, ``--cpus-per-node`` logical CPUs each; it is shut down at the end), builds
RLlib PPO on ``heml_gym/TissueRetraction-v1`` with ``N`` env runners of ``--scenes``
scenes each (one batched Numba call per step per runner), and measures

* sampling: env steps per second of all runners sampling in parallel (no learning);
* training: env steps per second of whole ``algo.train()`` iterations (sampling and the
  PPO update on the driver),

median over ``--rounds`` rounds. The machine's physical cores bound what more runners
can give: the result says how many there are.

Writes docs/benchmarks/scale_out.{json,md}.

    python -m heml_gym.benchmarks.speed.scale_out [--runners 1,2,4] [--rounds 5] [--from-json]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from heml_gym.benchmarks.common import command_line, generated_by, machine_info, markdown_table, store_and_report

ENV = "heml_gym/TissueRetraction-v1"


def measure(address: str, runners: int, scenes: int, rounds: int, batch: int) -> dict:
    import ray
    from ray.rllib.algorithms.ppo import PPOConfig

    from heml_gym.agents.rllib_backend import RUNNER_ENV

    ray.init(address=address, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {"OMP_WAIT_POLICY": "PASSIVE", "NUMBA_NUM_THREADS": "1"}})
    try:
        config = (PPOConfig()
                  .environment(RUNNER_ENV, env_config={"env_id": ENV, "obs_mode": "state"})
                  .env_runners(num_env_runners=runners, num_envs_per_env_runner=scenes, num_cpus_per_env_runner=1,
                               gym_env_vectorize_mode="vector_entry_point")
                  .training(train_batch_size_per_learner=batch, minibatch_size=256, num_epochs=1)
                  .framework("torch"))
        algo = config.build_algo()
        per_runner = max(1, batch // runners)
        group = algo.env_runner_group
        group.foreach_env_runner(lambda r: r.sample(num_timesteps=scenes * 4), local_env_runner=False)  # warm-up
        nodes = sorted(set(group.foreach_env_runner(lambda r: __import__("ray").get_runtime_context().get_node_id(),
                                                    local_env_runner=False)))
        sample_rates, train_rates = [], []
        for _ in range(rounds):
            t0 = time.perf_counter()
            episodes = group.foreach_env_runner(lambda r: r.sample(num_timesteps=per_runner), local_env_runner=False)
            dt = time.perf_counter() - t0
            steps = sum(sum(len(e) for e in eps) for eps in episodes)
            sample_rates.append(steps / dt)
        # the runners count the direct samples above in their lifetime step metric too: the
        # first train() reports them, so it is a warm-up and the rounds start after it
        lifetime = algo.train()["env_runners"]["num_env_steps_sampled_lifetime"]
        for _ in range(rounds):
            t0 = time.perf_counter()
            new = algo.train()["env_runners"]["num_env_steps_sampled_lifetime"]
            train_rates.append((new - lifetime) / (time.perf_counter() - t0))
            lifetime = new
        algo.stop()
    finally:
        ray.shutdown()
    return {"env_runners": runners, "scenes_per_runner": scenes, "nodes_used": len(nodes),
            "sampling_env_steps_per_s": float(np.median(sample_rates)), "sampling_rounds": sample_rates,
            "training_env_steps_per_s": float(np.median(train_rates)), "training_rounds": train_rates}


def report(data: dict) -> str:
    rows = data["rows"]
    base = rows[0]["sampling_env_steps_per_s"]
    table = markdown_table(
        ["env runners", "scenes each", "nodes used", "sampling env steps/s", "x 1 runner", "training env steps/s"],
        [[r["env_runners"], r["scenes_per_runner"], r["nodes_used"], f"{r['sampling_env_steps_per_s']:.0f}",
          f"{r['sampling_env_steps_per_s'] / base:.2f}", f"{r['training_env_steps_per_s']:.0f}"] for r in rows])
    cores, per_node, scenes = data["physical_cores"], data["cpus_per_node"], rows[0]["scenes_per_runner"]
    return (f"{generated_by(data)}: a local 2-node Ray cluster ({per_node} logical CPUs per node, {cores} "
            f"physical cores in all), RLlib PPO on {data['env'].split('/')[-1]} (state observations), {scenes} "
            f"scenes per env runner, one Numba thread each, medians of {data['rounds']} rounds. Sampling: all "
            f"runners sample {data['batch']} env steps in all, in parallel, episodes returned to the driver (no "
            f"learning); training: whole `algo.train()` iterations ({data['batch']}-step batch, one PPO epoch of "
            f"256-step minibatches on the driver). With {cores} physical cores, more than {cores} runners only share "
            "them.\n\n" + table)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runners", default="1,2,4", help="env runner counts (comma-separated)")
    ap.add_argument("--scenes", type=int, default=16, help="scenes per env runner")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--batch", type=int, default=4096, help="env steps per round (all runners)")
    ap.add_argument("--cpus-per-node", type=int, default=2, help="logical CPUs of each of the 2 nodes")
    ap.add_argument("--from-json", action="store_true", help="only rebuild the table from the stored result")
    args = ap.parse_args(argv)
    if args.from_json:
        store_and_report("scale_out", None, report)
        return 0
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": args.cpus_per_node})
    cluster.add_node(num_cpus=args.cpus_per_node)
    cluster.wait_for_nodes()
    rows = []
    try:
        for n in [int(v) for v in args.runners.split(",")]:
            rows.append(measure(cluster.address, n, args.scenes, args.rounds, args.batch))
            print(rows[-1]["env_runners"], f"{rows[-1]['sampling_env_steps_per_s']:.0f} sampling,",
                  f"{rows[-1]['training_env_steps_per_s']:.0f} training env steps/s", flush=True)
    finally:
        cluster.shutdown()
    data = {"machine": machine_info(), "command": command_line("heml_gym.benchmarks.speed.scale_out", ap, args),
            "env": ENV, "physical_cores": os.cpu_count(), "cpus_per_node": args.cpus_per_node, "rounds": args.rounds,
            "batch": args.batch, "rows": rows}
    store_and_report("scale_out", data, report, envs=[ENV])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
