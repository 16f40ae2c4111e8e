"""Gymnasium retraction environments (``heml_gym.envs``), built on the HEML backend.

Importing this package registers:

* ``heml_gym/TissueRetraction-v0`` (:class:`~heml_gym.envs.tissue_retraction.TissueRetractionEnv`)
* ``heml_gym/OrganRetraction-v0`` (:class:`~heml_gym.envs.organ_retraction.OrganRetractionEnv`)

each with a batched implementation for ``gymnasium.make_vec(...,
vectorization_mode="vector_entry_point")``.
"""

import gymnasium as gym

from .core import RetractionScene, RewardWeights, TaskSettings

__all__ = ["RetractionScene", "RewardWeights", "TaskSettings"]

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
