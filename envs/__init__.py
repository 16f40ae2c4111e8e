"""Gymnasium retraction environments (``heml_gym.envs``), built on the HEML backend.

Importing this package registers:

* ``heml_gym/TissueRetraction-v0`` (:class:`~heml_gym.envs.tissue_retraction.TissueRetractionEnv`)
* ``heml_gym/OrganRetraction-v0`` (:class:`~heml_gym.envs.organ_retraction.OrganRetractionEnv`)

each with a batched implementation for ``gymnasium.make_vec(...,
vectorization_mode="vector_entry_point")``.
"""

import gymnasium as gym

from .core import STATE_FIELDS, STATE_SPEC, RewardWeights, TaskSettings
from .scene import (AdhesionSpec, CameraSpec, FoldSpec, GripperSpec, PhysicsSpec, RegionSpec, Scene, SupportSpec,
                    TargetSpec, TissueSpec, build_scene)
from .spec import SpecError

__all__ = ["Scene", "TissueSpec", "PhysicsSpec", "RegionSpec", "FoldSpec", "AdhesionSpec", "TargetSpec", "GripperSpec",
           "CameraSpec", "SupportSpec", "build_scene", "check_env_kwargs", "RewardWeights", "TaskSettings", "SpecError", "STATE_FIELDS", "STATE_SPEC"]

#: Arguments set by other means than ``env.kwargs`` (the run config's own keys, gym.make's).
RESERVED_KWARGS = ("obs_mode", "num_envs", "render_mode", "max_episode_steps")


def check_env_kwargs(env_id: str, kwargs: dict, path: str = "env.kwargs"):
    """Validate ``kwargs`` for ``gym.make(env_id, **kwargs)`` of a heml_gym env without
    building it: every key is an argument of the env, and the scene, physics, settings
    and weights they give are valid. Returns the resolved :class:`Scene`; raises
    :class:`SpecError` naming the key (under ``path``)."""
    import inspect

    from gymnasium.envs.registration import load_env_creator

    if not isinstance(kwargs, dict):
        raise SpecError(f"{path}: must be a mapping of keyword arguments, got {type(kwargs).__name__}")
    if env_id not in gym.registry:
        raise SpecError(f"unknown environment {env_id!r}")
    cls = load_env_creator(gym.registry[env_id].entry_point)
    known = [p for p in inspect.signature(cls.__init__).parameters if p != "self"]
    for key in kwargs:
        if key in RESERVED_KWARGS:
            raise SpecError(f"{path}.{key}: set it with the config's own key, not in {path}")
        if key not in known:
            raise SpecError(f"{path}.{key}: not an argument of {cls.__name__} (known: {', '.join(known)})")
    data = {k: v for k, v in kwargs.items() if k not in ("obs_mode", "render_mode")}
    try:
        return cls.check_kwargs(**data)
    except SpecError as exc:
        message = str(exc)
        raise SpecError(message if message.startswith(path) else f"{path}.{message}") from None


gym.register(
    id="heml_gym/TissueRetraction-v0",
    entry_point="heml_gym.envs.tissue_retraction:TissueRetractionEnv",
    vector_entry_point="heml_gym.envs.tissue_retraction:TissueRetractionVectorEnv",
)

gym.register(
    id="heml_gym/OrganRetraction-v0",
    entry_point="heml_gym.envs.organ_retraction:OrganRetractionEnv",
    vector_entry_point="heml_gym.envs.organ_retraction:OrganRetractionVectorEnv",
)
