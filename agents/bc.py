"""Behaviour cloning (BC): a small MLP policy regressed on demonstrations.

A run config with ``algorithm.name: BC`` trains on a Minari dataset (``heml-gym demos``)
instead of interacting with the env::

    env: {id: heml_gym/TissueRetraction-v1, obs_mode: state}
    algorithm:
      name: BC
      hyperparameters: {hidden: [256, 256], epochs: 200, batch_size: 256, learning_rate: 0.001}
    demos: {dataset: heml-gym/tissue-retraction-scripted-noisy-100-v0, policy: scripted, episodes: 100, action_noise: 0.3}
    evaluation: {episodes: 20}
    seed: 0

``demos.dataset`` is read from the local Minari datasets (``demos.root``, else
``MINARI_DATASETS_PATH``, else ``~/.minari/datasets``); when it is not there, ``heml-gym
train`` first records it (:func:`heml_gym.agents.demos.record_config_demos`) from ``demos.policy`` (``scripted``, ``pretrained``, a run folder or an
``.onnx``) for ``demos.episodes`` episodes seeded from ``demos.seed``, with
``demos.action_noise`` on the executed velocity commands: the policy then learns the
demonstrator's own actions (``infos["expert_action"]``) in the states that noise led to,
so it can recover from its own small errors (DART, Laskey et al. 2017; without noise, BC
from the scripted fold reached 100 % on some seeds and 0 % on others, drifting off the
fold while holding). The policy maps the
observation, normalised by the demonstrations' mean and standard deviation (clipped to
+-10 as the RL runs' statistics are), through ReLU layers to a tanh-squashed action in
[-1, 1]^4, fitted by Adam on the mean squared action error (Pomerleau 1991; the BC
baselines of D4RL / Minari). Seeded: the weights' initialisation and the minibatch order
follow ``seed``.

The run folder holds ``config.yaml``, ``policy.pt`` (the weights only, read back with
``torch.load(weights_only=True)``: nothing is unpickled), ``vecnormalize.json`` (the
observation statistics in the RL runs' format), ``bc.json`` (the dataset and the loss
per epoch) and ``evaluations.json`` (success on fresh episodes). ``heml-gym eval`` /
``rollout`` / ``export`` read it as they read an RL run.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from .bc_hyperparameters import BehaviourCloning
from .dataset_ids import use_root

__all__ = ["BehaviourCloning", "BCNetwork", "fit", "train_bc", "load_bc_policy", "flat_observation", "POLICY_FILE"]

POLICY_FILE = "policy.pt"
CLIP_OBS = 10.0  # as SB3's VecNormalize clips the RL runs' normalised observations
EPSILON = 1e-8


def BCNetwork(n_obs: int, n_act: int, hidden):
    """The policy: ``Linear`` + ``ReLU`` per hidden width, then ``Linear`` + ``Tanh``."""
    import torch.nn as nn

    layers, width = [], n_obs
    for h in hidden:
        layers += [nn.Linear(width, h), nn.ReLU()]
        width = h
    return nn.Sequential(*layers, nn.Linear(width, n_act), nn.Tanh())


def normalise(obs: np.ndarray, mean: np.ndarray, var: np.ndarray) -> np.ndarray:
    return np.clip((obs - mean) / np.sqrt(var + EPSILON), -CLIP_OBS, CLIP_OBS)


def fit(observations: np.ndarray, actions: np.ndarray, hp: BehaviourCloning, seed: int = 0,
        progress_bar: bool = False) -> tuple:
    """``(network, mean, var, losses)``: the BC policy of ``observations (T, d)`` ->
    ``actions (T, a)`` in [-1, 1] (mean squared error per epoch in ``losses``)."""
    import torch

    observations = np.asarray(observations, dtype=np.float64)
    actions = np.asarray(actions, dtype=np.float64)
    if observations.ndim != 2 or actions.ndim != 2 or len(observations) != len(actions) or not len(actions):
        raise ValueError(f"observations (T, d) and actions (T, a) of one length T >= 1, got "
                         f"{observations.shape} and {actions.shape}")
    if not (np.all(np.isfinite(observations)) and np.all(np.isfinite(actions))):
        raise ValueError("the demonstrations hold non-finite observations or actions")
    mean, var = observations.mean(axis=0), observations.var(axis=0)
    x = torch.as_tensor(normalise(observations, mean, var), dtype=torch.float32)
    # a tanh output cannot reach +-1: the +-1 commands (close / open the jaws) are aimed just inside
    y = torch.as_tensor(np.clip(actions, -0.999, 0.999), dtype=torch.float32)
    torch.manual_seed(seed)
    net = BCNetwork(x.shape[1], y.shape[1], hp.hidden)
    optimiser = torch.optim.Adam(net.parameters(), lr=hp.learning_rate, weight_decay=hp.weight_decay)
    order = np.random.default_rng(seed)
    losses = []
    epochs = range(hp.epochs)
    if progress_bar:
        from tqdm.auto import tqdm

        epochs = tqdm(epochs, desc="BC", unit="epoch")
    for _ in epochs:
        perm = torch.as_tensor(order.permutation(len(x)))
        total = 0.0
        for start in range(0, len(x), hp.batch_size):
            idx = perm[start:start + hp.batch_size]
            loss = torch.mean((net(x[idx]) - y[idx]) ** 2)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            total += loss.item() * len(idx)
        losses.append(total / len(x))
    net.eval()
    return net, mean, var, losses


class BCPolicy:
    """``obs -> action`` of a fitted BC network and its observation statistics."""

    def __init__(self, net, mean: np.ndarray, var: np.ndarray):
        self.net, self.mean, self.var = net, np.asarray(mean), np.asarray(var)

    def __call__(self, obs) -> np.ndarray:
        import torch

        state = flat_observation(obs)
        x = torch.as_tensor(normalise(np.asarray(state, dtype=np.float64), self.mean, self.var), dtype=torch.float32)
        with torch.no_grad():
            return self.net(x).numpy().astype(np.float32)


def flat_observation(obs) -> np.ndarray:
    """What BC reads: the state vector; a goal task's dict (``observation``,
    ``achieved_goal``, ``desired_goal``) as its arrays concatenated in key order (sorted, as
    SB3's ``MultiInputPolicy`` and the ONNX export concatenate them); a point-cloud dict's
    ``state``. Works on one observation or a leading batch axis."""
    if not isinstance(obs, dict):
        return np.asarray(obs)
    if "observation" in obs:
        return np.concatenate([np.asarray(obs[k], dtype=np.float64) for k in sorted(obs)], axis=-1)
    return np.asarray(obs["state"])


def _dataset(cfg, progress_bar: bool):
    """The config's Minari dataset (recorded first when it is not there) and its transitions."""
    d = cfg.demos
    if d.root is not None:
        use_root(d.root, "config key 'demos.root'")
    import minari

    from .config import ConfigError

    if d.dataset not in minari.list_local_datasets():
        raise ConfigError(f"config key 'demos.dataset': {d.dataset} is not a local Minari dataset "
                          f"({os.environ.get('MINARI_DATASETS_PATH', '~/.minari/datasets')}): `heml-gym train` records "
                          "it from the demos section, or record it with `heml-gym demos`")
    dataset = minari.load_dataset(d.dataset)
    if dataset.total_episodes != d.episodes:  # an existing dataset: is it the one the config describes?
        raise ConfigError(f"config key 'demos.dataset': {d.dataset} exists with {dataset.total_episodes} episodes, "
                          f"the config's demos.episodes is {d.episodes}: name a new dataset to record, or make them "
                          "agree")
    if dataset.spec.env_spec is not None and dataset.spec.env_spec.id != cfg.env.id:
        raise ConfigError(f"config key 'demos.dataset': {d.dataset} holds {dataset.spec.env_spec.id} episodes, "
                          f"not {cfg.env.id}")
    observations, actions = [], []
    for episode in dataset.iterate_episodes():
        observations.append(flat_observation(episode.observations)[:-1])
        # the demonstrator's own actions where the executed ones were perturbed (demos --action-noise)
        labels = episode.infos.get("expert_action")
        actions.append(np.asarray(labels)[1:] if labels is not None else np.asarray(episode.actions))
    return dataset, np.concatenate(observations), np.concatenate(actions)


def _write_statistics(path: Path, mean: np.ndarray, var: np.ndarray, count: int) -> None:
    """The observation statistics in the RL runs' JSON format (:mod:`heml_gym.agents.run_files`)."""
    from .run_files import FORMAT

    path.write_text(json.dumps({"format": FORMAT, "keys": None, "clip_obs": CLIP_OBS, "epsilon": EPSILON,
                                "stats": {"": {"mean": mean.tolist(), "var": var.tolist(), "count": float(count)}}}))


def train_bc(cfg, run_dir: Path, progress_bar: bool = True) -> dict:
    """Fit BC per ``cfg`` (a run config with ``algorithm.name: BC``) into ``run_dir`` and
    evaluate it on fresh episodes; returns what :func:`heml_gym.agents.train.train` does."""
    import torch
    import yaml

    from .evaluation import evaluate_policy
    from .run_files import NORMALIZER_FILE

    hp = BehaviourCloning(**cfg.algorithm.hyperparameters)
    torch.set_num_threads(1)
    started = time.perf_counter()
    dataset, observations, actions = _dataset(cfg, progress_bar)
    net, mean, var, losses = fit(observations, actions, hp, seed=cfg.seed, progress_bar=progress_bar)
    fitted = time.perf_counter() - started
    final = evaluate_policy(BCPolicy(net, mean, var), cfg.env.id, cfg.evaluation.episodes,
                            obs_mode=cfg.env.obs_mode, env_kwargs=cfg.env.kwargs)
    final["timesteps"] = int(len(observations))  # demonstration transitions
    final["wall_s"] = time.perf_counter() - started
    # the run folder is written once everything has run: an interrupted run leaves none
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    torch.save(net.state_dict(), run_dir / POLICY_FILE)
    _write_statistics(run_dir / NORMALIZER_FILE, mean, var, len(observations))
    (run_dir / "evaluations.json").write_text(json.dumps([final], indent=1))
    (run_dir / "bc.json").write_text(json.dumps({
        "dataset": cfg.demos.dataset, "episodes": int(dataset.total_episodes), "transitions": int(len(observations)),
        "demonstrator": dataset.storage.metadata.get("algorithm_name"), "loss_per_epoch": losses, "fit_s": fitted}, indent=1))
    return {"run_dir": str(run_dir), "timesteps": int(len(observations)), "final_evaluation": final}


def is_bc_run(path: Path) -> bool:
    return Path(path).is_dir() and (Path(path) / POLICY_FILE).is_file()


def load_bc_run(run_dir: Path, cfg):
    """``(network, normalizer)`` of a BC run folder, as :func:`heml_gym.agents.train.load_run`
    gives an RL run's: the weights read with ``torch.load(weights_only=True)`` into the
    network the config describes, the observation statistics from their JSON."""
    import torch

    from .config import ConfigError
    from .run_files import NORMALIZER_FILE, load_normalizer

    hp = BehaviourCloning(**cfg.algorithm.hyperparameters)
    stats = load_normalizer(Path(run_dir) / NORMALIZER_FILE)
    mean = stats.obs_rms.mean
    try:
        weights = torch.load(Path(run_dir) / POLICY_FILE, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable or unsafe file is refused the same way
        raise ConfigError(f"{Path(run_dir) / POLICY_FILE} cannot be read as weights ({type(exc).__name__}; "
                          "only tensors are read from it, nothing in it was run)") from None
    import gymnasium as gym

    import heml_gym.envs  # noqa: F401  (registers the environments)

    env = gym.make(cfg.env.id, **cfg.env.kwargs)
    n_actions = int(env.action_space.shape[0])  # 4 per grasper
    env.close()
    net = BCNetwork(len(mean), n_actions, hp.hidden)
    expected = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    found = ({k: tuple(getattr(v, "shape", ())) for k, v in weights.items()} if isinstance(weights, dict) else None)
    if found != expected:
        raise ConfigError(f"{Path(run_dir) / POLICY_FILE} does not hold the weights of its config's network "
                          f"({len(mean)} observations, hidden {hp.hidden}, {n_actions} actions): expected tensors "
                          f"{expected}, got {found if found is not None else type(weights).__name__}")
    if not all(bool(torch.isfinite(v).all()) for v in weights.values()):
        raise ConfigError(f"{Path(run_dir) / POLICY_FILE}: non-finite weights")
    net.load_state_dict(weights)
    net.eval()
    return net, stats


def load_bc_policy(run_dir: Path, cfg) -> BCPolicy:
    """The ``obs -> action`` policy of a BC run folder."""
    net, stats = load_bc_run(run_dir, cfg)
    return BCPolicy(net, stats.obs_rms.mean, stats.obs_rms.var)
