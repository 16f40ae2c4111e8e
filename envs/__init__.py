"""Gymnasium retraction environments (``heml_gym.envs``), built on the HEML backend.

Importing this package registers:

* ``heml_gym/TissueRetraction-v1`` (:class:`~heml_gym.envs.tissue_retraction.TissueRetractionEnv`)
* ``heml_gym/OrganRetraction-v2`` (:class:`~heml_gym.envs.organ_retraction.OrganRetractionEnv`)
* ``heml_gym/BimanualRetraction-v0`` (:class:`~heml_gym.envs.bimanual_retraction.BimanualRetractionEnv`):
  two graspers
* ``heml_gym/TissueManipulation-v0`` (:class:`~heml_gym.envs.tissue_manipulation.TissueManipulationEnv`):
  goal-conditioned (``GoalEnv``)
* ``heml_gym/PushRetraction-v0`` (:class:`~heml_gym.envs.push_retraction.PushRetractionEnv`): a
  paddle retractor, no grasp
* ``heml_gym/GallbladderDissection-v0``
  (:class:`~heml_gym.envs.gallbladder_dissection.GallbladderDissectionEnv`): a grasper and an
  electrosurgical hook, to the critical view of safety (200 steps)

each with a batched implementation for ``gymnasium.make_vec(...,
vectorization_mode="vector_entry_point")`` and ``max_episode_steps`` its settings'
``max_steps`` (100; 50 for TissueManipulation). The version changes whenever a task's behaviour does (each
env's docstring keeps a version history); ``-v0`` named several former tasks and is
no longer registered, nor is ``OrganRetraction-v1`` (its camera images were turned 90
degrees). Asking for a retired id is an error naming today's id (:data:`RETIRED_IDS`):
``TissueRetraction-v1`` for the flap, ``OrganRetraction-v2`` for the lobe (gymnasium's
``DeprecatedEnv`` from ``gym.make``; one line from the CLI and run configs).
"""

from pathlib import Path as _Path

import gymnasium as gym

from heml_gym.numba_cache import stamp_with_package_sources

stamp_with_package_sources(_Path(__file__).parent)  # (before any kernel here is loaded: see heml_gym.numba_cache)

from .core import STATE_FIELDS, STATE_SPEC, RewardWeights, TaskSettings
from .manipulation import ManipulationSettings
from .scene import (AdhesionSpec, CameraSpec, FoldSpec, GripperSpec, PhysicsSpec, RegionSpec, Scene, SupportSpec,
                    TargetSpec, TissueSpec, build_scene)
from .spec import SpecError

__all__ = ["Scene", "TissueSpec", "PhysicsSpec", "RegionSpec", "FoldSpec", "AdhesionSpec", "TargetSpec", "GripperSpec",
           "CameraSpec", "SupportSpec", "build_scene", "check_env_kwargs", "RewardWeights", "TaskSettings", "ManipulationSettings", "SpecError", "STATE_FIELDS", "STATE_SPEC",
           "TISSUE_RETRACTION", "ORGAN_RETRACTION", "BIMANUAL_RETRACTION", "TISSUE_MANIPULATION", "PUSH_RETRACTION", "GALLBLADDER_DISSECTION", "ENV_IDS", "GOAL_ENV_IDS", "RETIRED_IDS", "SAME_STATE_TASK", "MAX_EPISODE_STEPS", "episode_steps",
           "unknown_env_message"]

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
        raise SpecError(unknown_env_message(env_id))
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


#: The registered ids of today's tasks, and the episode length their specs register
#: (``TaskSettings.max_steps``'s default: gym.make's TimeLimit and the env's own
#: truncation agree).
TISSUE_RETRACTION = "heml_gym/TissueRetraction-v1"
ORGAN_RETRACTION = "heml_gym/OrganRetraction-v2"
BIMANUAL_RETRACTION = "heml_gym/BimanualRetraction-v0"
TISSUE_MANIPULATION = "heml_gym/TissueManipulation-v0"
PUSH_RETRACTION = "heml_gym/PushRetraction-v0"
GALLBLADDER_DISSECTION = "heml_gym/GallbladderDissection-v0"
ENV_IDS = (TISSUE_RETRACTION, ORGAN_RETRACTION, BIMANUAL_RETRACTION, TISSUE_MANIPULATION, PUSH_RETRACTION,
           GALLBLADDER_DISSECTION)
#: The goal-conditioned tasks (``GoalEnv`` observations: observation, achieved_goal, desired_goal).
GOAL_ENV_IDS = (TISSUE_MANIPULATION,)
MAX_EPISODE_STEPS = TaskSettings().max_steps

#: Ids no longer registered: what replaced them, and why.
RETIRED_IDS = {"heml_gym/TissueRetraction-v0": (TISSUE_RETRACTION, "-v0 meant several former tasks"),
               "heml_gym/OrganRetraction-v0": (ORGAN_RETRACTION, "-v0 meant several former tasks"),
               "heml_gym/OrganRetraction-v1": (ORGAN_RETRACTION, "its camera images were turned 90 degrees")}

#: Retired ids whose state observations, actions, dynamics and rewards equal their
#: successor's (only images changed): a state policy made for one runs on the other.
SAME_STATE_TASK = {"heml_gym/OrganRetraction-v1": ORGAN_RETRACTION}


def unknown_env_message(env_id: str) -> str:
    """The one-line error for an id that is not registered: a retired version names its
    successor, anything else lists the known heml_gym ids."""
    if env_id in RETIRED_IDS:
        successor, why = RETIRED_IDS[env_id]
        return (f"{env_id} is retired ({why}): use {successor}, "
                "today's task (its version history is in the env's docstring)")
    return f"unknown environment {env_id!r} (known: {', '.join(ENV_IDS)})"


def episode_steps(kwargs: dict) -> int | None:
    """The episode length that env keyword arguments ask for (``settings.max_steps``,
    given as a mapping or a :class:`TaskSettings`), or None when they leave the default.
    Pass it to ``gym.make`` / ``gym.make_vec`` as ``max_episode_steps`` so that gymnasium's
    TimeLimit and the env's own truncation agree."""
    settings = (kwargs or {}).get("settings")
    if isinstance(settings, dict) and "max_steps" in settings:
        return settings["max_steps"]
    if isinstance(settings, TaskSettings) and settings.max_steps != MAX_EPISODE_STEPS:
        return settings.max_steps
    return None


gym.register(
    id=TISSUE_RETRACTION,
    entry_point="heml_gym.envs.tissue_retraction:TissueRetractionEnv",
    vector_entry_point="heml_gym.envs.tissue_retraction:TissueRetractionVectorEnv",
    max_episode_steps=MAX_EPISODE_STEPS,
)

gym.register(
    id=ORGAN_RETRACTION,
    entry_point="heml_gym.envs.organ_retraction:OrganRetractionEnv",
    vector_entry_point="heml_gym.envs.organ_retraction:OrganRetractionVectorEnv",
    max_episode_steps=MAX_EPISODE_STEPS,
)

gym.register(
    id=BIMANUAL_RETRACTION,
    entry_point="heml_gym.envs.bimanual_retraction:BimanualRetractionEnv",
    vector_entry_point="heml_gym.envs.bimanual_retraction:BimanualRetractionVectorEnv",
    max_episode_steps=MAX_EPISODE_STEPS,
)

gym.register(
    id=TISSUE_MANIPULATION,
    entry_point="heml_gym.envs.tissue_manipulation:TissueManipulationEnv",
    vector_entry_point="heml_gym.envs.tissue_manipulation:TissueManipulationVectorEnv",
    max_episode_steps=ManipulationSettings().max_steps,
)

gym.register(
    id=PUSH_RETRACTION,
    entry_point="heml_gym.envs.push_retraction:PushRetractionEnv",
    vector_entry_point="heml_gym.envs.push_retraction:PushRetractionVectorEnv",
    max_episode_steps=MAX_EPISODE_STEPS,
)

gym.register(
    id=GALLBLADDER_DISSECTION,
    entry_point="heml_gym.envs.gallbladder_dissection:GallbladderDissectionEnv",
    vector_entry_point="heml_gym.envs.gallbladder_dissection:GallbladderDissectionVectorEnv",
    max_episode_steps=200,
)
