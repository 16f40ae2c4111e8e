"""The one registry of learning algorithms: config names to their classes (Stable-Baselines3,
RLlib, and behaviour cloning's hyperparameters)."""

from __future__ import annotations

import importlib

#: Algorithm name (``algorithm.name`` in a run config) -> "module:Class".
ALGORITHMS = {"PPO": "stable_baselines3:PPO", "SAC": "stable_baselines3:SAC",
              "RLlibPPO": "ray.rllib.algorithms.ppo:PPO", "BC": "heml_gym.agents.bc_hyperparameters:BehaviourCloning"}
#: Which training path runs each algorithm: Stable-Baselines3, RLlib (distributed sampling),
#: or behaviour cloning from demonstrations (:mod:`heml_gym.agents.bc`).
BACKENDS = {"PPO": "sb3", "SAC": "sb3", "RLlibPPO": "rllib", "BC": "bc"}


def algorithm_class(name: str):
    """The class of algorithm ``name`` (one of :data:`ALGORITHMS`)."""
    if name not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {name!r} (known: {', '.join(ALGORITHMS)})")
    module, cls = ALGORITHMS[name].split(":")
    try:
        return getattr(importlib.import_module(module), cls)
    except ImportError:
        hint = "pip install -e '.[ray]'" if BACKENDS[name] == "rllib" else "pip install -e '.[train]'"
        raise ImportError(f"algorithm {name} needs {module.split('.')[0]}: {hint}") from None


#: Replay buffers an off-policy run may name (``algorithm.hyperparameters.replay_buffer_class``):
#: HER relabels goals of a goal-conditioned task (``GoalEnv`` observations).
REPLAY_BUFFERS = {"HerReplayBuffer": "stable_baselines3:HerReplayBuffer"}


def sb3_hyperparameters(name: str, hyperparameters: dict) -> dict:
    """``hyperparameters`` of SB3 algorithm ``name`` as its constructor takes them: a
    ``replay_buffer_class`` given by name (one of :data:`REPLAY_BUFFERS`) becomes the class.
    ``ValueError`` names what is wrong."""
    hp = dict(hyperparameters)
    buffer = hp.get("replay_buffer_class")
    if buffer is not None:
        if name != "SAC":
            raise ValueError(f"replay_buffer_class: only an off-policy algorithm (SAC) has a replay buffer, not {name}")
        if buffer not in REPLAY_BUFFERS:
            raise ValueError(f"replay_buffer_class: one of {', '.join(REPLAY_BUFFERS)}, got {buffer!r}")
        module, cls = REPLAY_BUFFERS[buffer].split(":")
        hp["replay_buffer_class"] = getattr(importlib.import_module(module), cls)
    return hp
