"""The one registry of learning algorithms: config names to Stable-Baselines3 classes."""

from __future__ import annotations

import importlib

#: Algorithm name (``algorithm.name`` in a run config) -> "module:Class".
ALGORITHMS = {"PPO": "stable_baselines3:PPO", "SAC": "stable_baselines3:SAC"}


def algorithm_class(name: str):
    """The class of algorithm ``name`` (one of :data:`ALGORITHMS`)."""
    if name not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {name!r} (known: {', '.join(ALGORITHMS)})")
    module, cls = ALGORITHMS[name].split(":")
    return getattr(importlib.import_module(module), cls)
