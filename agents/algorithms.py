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
