"""``heml-gym demos``: demonstration datasets in Farama's Minari format.

Rolls a policy (the scripted fold, a shipped pretrained policy, a run folder or an exported
``.onnx``) out for N seeded episodes of an env and stores them as a Minari dataset
(observations, actions, rewards, terminations, truncations, and every step's ``info``:
grasp force, gauge strain, exposure, cost, ...), loadable with ``minari.load_dataset(NAME)``.
Datasets go under ``MINARI_DATASETS_PATH`` (``--root``), else ``~/.minari/datasets``.

``--action-noise SIGMA`` adds Gaussian noise of standard deviation SIGMA to each instrument's
motion commands the env executes (a grasper's three velocities, a paddle's tilt rate too;
grasp and energy commands are kept): the episodes then
visit the states around the demonstrator's path and show how it recovers from them, what
behaviour cloning needs to hold its course (DART, Laskey et al. 2017). ``actions`` are
what the env executed; the demonstrator's own action at step t is
``infos["expert_action"][t + 1]`` (``infos[0]`` is the reset's), the label to imitate.
The dataset's ``ref_max_score`` is the demonstrations' mean return; its ``ref_min_score``
is Minari's estimate from ``reference_episodes`` random episodes.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .dataset_ids import check_dataset_id, use_root

__all__ = ["collect_demos", "record_config_demos"]

def _motion_entries(task) -> list[np.ndarray]:
    """Each instrument's motion commands, as indices into the action: velocities and rates
    (a grasper's or hook's velocity, a port's tilt and insertion rates, a paddle's velocity
    and tilt rate), not its grasp or energy command."""
    out, offset = [], 0
    for instrument in list(task.instruments) + list(task.hooks):
        names = instrument.ACTION
        out.append(np.array([offset + k for k, name in enumerate(names)
                             if name.startswith("velocity_") or name.endswith("_rate")], dtype=np.int64))
        offset += len(names)
    return out


def _policy(spec: str, env_id: str, scene):
    """``(policy, name)`` for ``--policy`` (``scene``: the env's, for the scripted fold)."""
    if spec == "scripted":
        from heml_gym.envs.scripted import scripted_policy

        return scripted_policy(scene), "scripted fold (heml_gym.envs.scripted)"
    from .export import exported_policy

    policy = exported_policy(spec, env_id, env_id)
    if policy is not None:
        return policy, f"ONNX policy ({policy.metadata.get('run', spec)})"
    from .train import load_policy

    policy, _, cfg = load_policy(spec)
    if cfg is not None and cfg.env.id != env_id:
        raise ValueError(f"--policy {spec}: trained on {cfg.env.id}, not {env_id}")
    return policy, f"{cfg.algorithm.name if cfg else 'SB3'} run {spec}"


def record_config_demos(cfg, progress: bool = True) -> dict | None:
    """Record a BC run config's demonstrations (its ``demos`` section) when its dataset is
    not a local Minari dataset yet; None when it is."""
    d = cfg.demos
    if d.root is not None:
        use_root(d.root, "config key 'demos.root'")
    import minari

    if d.dataset in minari.list_local_datasets():
        return None
    if progress:
        print(f"demos: recording {d.episodes} episodes of {d.policy} in {cfg.env.id} as {d.dataset}", flush=True)
    return collect_demos(cfg.env.id, d.policy, d.episodes, d.dataset, seed=d.seed, action_noise=d.action_noise,
                         env_kwargs=cfg.env.kwargs)


def collect_demos(env_id: str, policy: str, episodes: int, dataset_id: str, seed: int = 0,
                  root: str | os.PathLike | None = None, reference_episodes: int = 5,
                  action_noise: float = 0.0, env_kwargs: dict | None = None) -> dict:
    """Write ``episodes`` episodes of ``policy`` in ``env_id`` (``gym.make(env_id,
    **env_kwargs)``) as Minari dataset ``dataset_id``; ``action_noise``: the standard
    deviation of the noise on the executed velocity commands (see the module's docstring)."""
    check_dataset_id(dataset_id)
    if episodes < 1:
        raise ValueError(f"--episodes: must be >= 1, got {episodes}")
    if seed < 0:
        raise ValueError(f"--seed: episode seeds are integers >= 0, got {seed}")
    if reference_episodes < 1:
        raise ValueError(f"--reference-episodes: Minari's ref_min_score needs >= 1 random episode, "
                         f"got {reference_episodes}")
    if not (isinstance(action_noise, (int, float)) and np.isfinite(action_noise) and action_noise >= 0):
        raise ValueError(f"--action-noise: a finite standard deviation >= 0, got {action_noise!r}")
    if root is not None:
        use_root(root)
    import gymnasium as gym
    import minari

    import heml_gym.envs  # noqa: F401  (registers the ids)

    if dataset_id in minari.list_local_datasets():
        raise ValueError(f"--out {dataset_id}: a local Minari dataset of that name exists")
    from minari.data_collector import EpisodeBuffer

    env = gym.make(env_id, **(env_kwargs or {}))
    act, name = _policy(policy, env_id, env.unwrapped.scene)
    motion = _motion_entries(env.unwrapped.task)
    buffers, returns, successes = [], [], 0
    noise = np.random.default_rng(seed)
    for k in range(episodes):  # (Minari's DataCollector would need jax; the buffers are written directly)
        obs, info = env.reset(seed=seed + k)
        if hasattr(act, "reset"):
            act.reset()
        observations, actions, rewards, terminations, truncations = [obs], [], [], [], []
        if action_noise:
            info = {**info, "expert_action": np.zeros(env.action_space.shape, dtype=np.float32)}
        infos = {key: [value] for key, value in info.items()}
        done = False
        while not done:
            action = np.asarray(act(obs), dtype=np.float32)
            expert = action
            if action_noise:
                action = action.copy()
                for entries in motion:  # each instrument's motion commands (a grasper's velocity: 3 entries)
                    action[entries] = np.clip(action[entries] + action_noise * noise.standard_normal(len(entries)),
                                              -1.0, 1.0)
            obs, reward, terminated, truncated, info = env.step(action)
            if action_noise:
                info = {**info, "expert_action": expert}
            observations.append(obs)
            actions.append(action)
            rewards.append(float(reward))
            terminations.append(bool(terminated))
            truncations.append(bool(truncated))
            for key, value in info.items():
                infos[key].append(value)
            done = terminated or truncated
        returns.append(float(np.sum(rewards)))
        successes += bool(info["is_success"])
        if isinstance(observations[0], dict):  # a goal task's dict: one array per key (what Minari stores)
            observations = {key: np.stack([o[key] for o in observations]) for key in observations[0]}
        buffers.append(EpisodeBuffer(id=k, seed=seed + k, observations=observations, actions=actions, rewards=rewards,
                                     terminations=terminations, truncations=truncations,
                                     infos={key: np.asarray(v) for key, v in infos.items()}))
    import warnings

    with warnings.catch_warnings():  # (Minari's advice to name an author e-mail and a code permalink)
        warnings.filterwarnings("ignore", message=".*(author_email|code_permalink).*", category=UserWarning)
        dataset = minari.create_dataset_from_buffers(
            dataset_id=dataset_id, buffer=buffers, env=env_id, eval_env=env_id, algorithm_name=name,
            author="heml-gym", ref_max_score=float(np.mean(returns)), num_episodes_average_score=reference_episodes,
            description=f"{episodes} episodes of {name} in {env_id} (seeds {seed}-{seed + episodes - 1})"
                        + (f", its velocity commands executed with Gaussian noise of standard deviation "
                           f"{action_noise:g} (its own action: infos['expert_action'][t + 1])" if action_noise else "")
                        + "; infos hold grasp_force (N), max_strain, exposure, cost and damage (strain x s) per step",
            requirements=["heml-gym"])
    env.close()
    return {"dataset": dataset_id, "episodes": dataset.total_episodes, "steps": int(dataset.total_steps),
            "success_rate": successes / episodes, "mean_return": float(np.mean(returns)), "action_noise": action_noise,
            "root": os.environ.get("MINARI_DATASETS_PATH", str(Path.home() / ".minari" / "datasets"))}
