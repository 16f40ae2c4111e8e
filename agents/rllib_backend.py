"""Distributed sampling for one run: RLlib PPO whose env runners each hold a batched vector
env of this project (``algorithm.name: RLlibPPO``).

Each RLlib env runner builds ``gym.make_vec(env_id, num_envs=env.num_envs,
vectorization_mode="vector_entry_point", **env.kwargs)``: the envs of a runner are
stepped by one Numba call, as in ``heml-gym train``, and ``algorithm.hyperparameters.
num_env_runners`` runners sample in parallel, on this machine or across a Ray cluster
(``heml-gym train CONFIG --address ADDRESS``). Observations are normalised by each
runner's running mean and variance (gymnasium's ``NormalizeObservation`` on the vector
env; runner 0's statistics are saved with every checkpoint, as ``obs_stats.json``).

The run folder matches the SB3 one where it can: ``config.yaml``, ``evaluations.json``
(success rate, exposure, strain, wall time at each evaluation, by the same
:func:`~heml_gym.agents.evaluation.evaluate_policy`), ``checkpoints/rllib_<steps>_steps/``
and ``rllib_checkpoint/`` (RLlib checkpoints, each with its ``obs_stats.json``).
``heml-gym eval`` and ``rollout`` load the policy from the RLModule in a checkpoint and
those statistics; what differs from the SB3 path: the checkpoints are RLlib folders, not
``.zip`` files, and ``--resume`` takes such a folder.

Hyperparameters: ``num_env_runners`` (default 1), ``num_cpus_per_env_runner`` (default
1), ``fcnet_hiddens`` (default [64, 64]) and any argument of ``PPOConfig.training``
(``lr``, ``gamma``, ``lambda_``, ``train_batch_size_per_learner``, ``minibatch_size``,
``num_epochs``, ``entropy_coeff``, ...).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import yaml

from .config import ConfigError, RunConfig, check_rllib_hyperparameters, import_rllib
from .evaluation import evaluate_policy

__all__ = ["train_rllib", "load_rllib_policy", "is_rllib_run"]

STATS_FILE = "obs_stats.json"
#: training iterations in a row without a sample (each waits RLlib's sample_timeout_s,
#: 60 s by default) before a run stops with an error
MAX_IDLE_ITERATIONS = 10
#: the gymnasium id RLlib's env runners make: ``"<this module>:<id>"`` imports this module
#: (and so registers the id) in every runner process, on any node
VECTOR_ENV_ID = "heml_gym_rllib/NormalizedRetraction-v0"
RUNNER_ENV = f"{__name__}:{VECTOR_ENV_ID}"


def make_vector_env(num_envs: int, env_id: str, **kwargs):
    """The env runners' env: the project's vector env of ``env_id`` (``num_envs`` envs,
    one Numba call per step), observations normalised by their running mean and variance."""
    import gymnasium as gym
    from gymnasium.wrappers.vector import NormalizeObservation

    from heml_gym.envs import episode_steps  # (registers the environments in the runner)

    return NormalizeObservation(gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point",
                                             max_episode_steps=episode_steps(kwargs), **kwargs))


def _register() -> None:
    import gymnasium as gym

    if VECTOR_ENV_ID not in gym.registry:
        gym.register(VECTOR_ENV_ID, entry_point=None, vector_entry_point=f"{__name__}:make_vector_env")


_register()


def _runner_stats(algo) -> dict:
    """Observation mean and variance of env runner 0 (the remote one, else the local)."""

    def get(runner):
        env = runner.env
        while env is not None and not hasattr(env, "obs_rms"):
            env = getattr(env, "env", None)
        if env is None:
            return None
        return {"mean": env.obs_rms.mean.tolist(), "var": env.obs_rms.var.tolist(), "count": float(env.obs_rms.count)}

    remote = algo.env_runner_group.foreach_env_runner(get, local_env_runner=False)
    found = [s for s in remote if s is not None]
    if not found:
        local = algo.env_runner_group.foreach_env_runner(get, local_env_runner=True)
        found = [s for s in local if s is not None]
    return found[0]


class RLlibPolicy:
    """``obs -> action``: an RLModule's deterministic action (the mean of its Gaussian), on
    observations normalised with saved statistics (as the runners saw them)."""

    def __init__(self, module, stats: dict):
        import torch

        self.module = module
        self.mean = np.asarray(stats["mean"], dtype=np.float64)
        self.std = np.sqrt(np.asarray(stats["var"], dtype=np.float64) + 1e-8)
        self._torch = torch

    def __call__(self, obs):
        x = (np.asarray(obs, dtype=np.float64) - self.mean) / self.std
        batch = self._torch.from_numpy(x.astype(np.float32)[None])
        with self._torch.no_grad():
            out = self.module.forward_inference({"obs": batch})
        inputs = out["action_dist_inputs"].numpy()[0]
        action = inputs[: len(inputs) // 2]
        return np.clip(action, -1.0, 1.0).astype(np.float32)


def _module_path(checkpoint: Path) -> Path:
    return checkpoint / "learner_group" / "learner" / "rl_module" / "default_policy"


def load_rllib_policy(checkpoint: str | Path) -> RLlibPolicy:
    """The policy of an RLlib checkpoint folder written by :func:`train_rllib`."""
    import_rllib()
    from ray.rllib.core.rl_module.rl_module import RLModule

    checkpoint = Path(checkpoint)
    stats = checkpoint / STATS_FILE
    if not _module_path(checkpoint).is_dir() or not stats.is_file():
        raise FileNotFoundError(f"{checkpoint} is not an RLlib checkpoint of heml-gym (no RLModule or {STATS_FILE})")
    module = RLModule.from_checkpoint(str(_module_path(checkpoint)))
    return RLlibPolicy(module, json.loads(stats.read_text()))


def is_rllib_run(path: str | Path) -> bool:
    path = Path(path)
    return (path / "rllib_checkpoint").is_dir() or _module_path(path).is_dir()


def _save(algo, path: Path) -> None:
    algo.save_to_path(str(path.resolve()))
    (path / STATS_FILE).write_text(json.dumps(_runner_stats(algo)))


def train_rllib(cfg: RunConfig, run_dir: str | Path, resume: str | Path | None = None, address: str | None = None,
                progress_bar: bool = True, trust_pickle: bool = False) -> dict:
    """Train ``cfg`` (``algorithm.name: RLlibPPO``) into ``run_dir``; ``resume``: an RLlib
    checkpoint folder to continue from (its step count kept)."""

    ray, PPOConfig = import_rllib()

    check_rllib_hyperparameters(cfg)
    run_dir = Path(run_dir)
    if resume is not None and not _module_path(Path(resume)).is_dir():
        raise ConfigError(f"--resume: {resume} is not an RLlib checkpoint folder")
    if resume is not None and not trust_pickle:
        raise ConfigError(f"--resume: {resume} is an RLlib checkpoint, which RLlib reads by unpickling (code in it "
                          "would run): pass --trust-pickle if you trust where it came from")
    hp = dict(cfg.algorithm.hyperparameters)
    runners = int(hp.pop("num_env_runners", 1))
    cpus = float(hp.pop("num_cpus_per_env_runner", 1))
    hidden = list(hp.pop("fcnet_hiddens", [64, 64]))
    started_ray = not ray.is_initialized()
    if started_ray:
        ray.init(address=address, include_dashboard=False, log_to_driver=False,
                 runtime_env={"env_vars": {"OMP_WAIT_POLICY": "PASSIVE"}})
    try:
        env_config = {"env_id": cfg.env.id, "obs_mode": cfg.env.obs_mode, **cfg.env.kwargs}
        from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig

        config = (PPOConfig()
                  .environment(RUNNER_ENV, env_config=env_config)
                  .env_runners(num_env_runners=runners, num_envs_per_env_runner=cfg.env.num_envs,
                               num_cpus_per_env_runner=cpus, gym_env_vectorize_mode="vector_entry_point")
                  .rl_module(model_config=DefaultModelConfig(fcnet_hiddens=hidden))
                  .training(**hp)
                  .debugging(seed=cfg.seed)
                  .framework("torch"))
        try:
            algo = config.build_algo()
        except (ValueError, TypeError, AssertionError) as exc:
            raise ConfigError(f"config key 'algorithm.hyperparameters': RLlib rejects them: {exc}") from None
        if resume is not None:
            algo.restore_from_path(str(Path(resume).resolve()))
        (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
        (run_dir / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))
        history_path = run_dir / "evaluations.json"
        history = json.loads(history_path.read_text()) if history_path.exists() else []
        wall_before = history[-1].get("wall_s", 0.0) if history else 0.0
        started = time.perf_counter()
        steps = int(history[-1]["timesteps"]) if (history and resume is not None) else 0
        next_eval = steps + cfg.evaluation.every_steps
        next_ckpt = steps + cfg.checkpoint.every_steps
        rates = []
        bar = None
        if progress_bar:
            from tqdm import tqdm

            bar = tqdm(total=cfg.algorithm.total_timesteps, initial=steps, unit="step", desc="RLlib PPO")

        def evaluate():
            module = algo.get_module()
            policy = RLlibPolicy(module, _runner_stats(algo))
            result = evaluate_policy(policy, cfg.env.id, cfg.evaluation.episodes, obs_mode=cfg.env.obs_mode,
                                     env_kwargs=cfg.env.kwargs)
            result["timesteps"] = steps
            result["wall_s"] = wall_before + time.perf_counter() - started
            history.append(result)
            history_path.write_text(json.dumps(history, indent=1))
            return result

        idle = 0  # train() calls in a row that sampled nothing
        while steps < cfg.algorithm.total_timesteps:
            t0 = time.perf_counter()
            result = algo.train()
            # no "env_runners" entry: the runners returned no samples within RLlib's
            # sample_timeout_s (e.g. while a cold Numba cache compiles the kernels)
            new = int(result.get("env_runners", {}).get("num_env_steps_sampled_lifetime", steps))
            idle = idle + 1 if new == steps else 0
            if idle >= MAX_IDLE_ITERATIONS:
                raise RuntimeError(f"RLlib's env runners returned no samples in {idle} training iterations in a row "
                                   f"(at {steps} env steps): check the Ray workers' logs")
            rates.append((new - steps) / (time.perf_counter() - t0))
            if bar is not None:
                bar.update(new - steps)
            steps = new
            if steps >= next_ckpt:
                next_ckpt += cfg.checkpoint.every_steps
                _save(algo, run_dir / "checkpoints" / f"rllib_{steps}_steps")
            if steps >= next_eval:
                next_eval += cfg.evaluation.every_steps
                evaluate()
        if bar is not None:
            bar.close()
        _save(algo, run_dir / "rllib_checkpoint")
        final = history[-1] if history and history[-1]["timesteps"] == steps else evaluate()
        algo.stop()
    finally:
        if started_ray:
            ray.shutdown()
    return {"run_dir": str(run_dir), "timesteps": steps, "final_evaluation": final,
            "env_steps_per_s": float(np.median(rates)) if rates else None}
