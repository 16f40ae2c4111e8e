"""Difficulty levels: what each level changes, against the scene's own data and the hold
time's step count, and their errors."""

from __future__ import annotations

import gymnasium as gym
import pytest

import heml_gym.envs  # noqa: F401
from heml_gym.envs import check_env_kwargs
from heml_gym.envs.scripted import scripted_policy
from heml_gym.envs.spec import SpecError
from heml_gym.envs.tissue_retraction import TissueRetractionEnv, TissueRetractionVectorEnv


def _scripted_length(env, seed):
    obs, _ = env.reset(seed=seed)
    policy = scripted_policy(env.unwrapped.scene)
    for k in range(env.unwrapped.task.settings.max_steps):
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        if terminated or truncated:
            return k + 1, info
    raise AssertionError("the episode did not end")


def test_level_1_holds_the_success_condition_for_two_seconds():
    """The scripted fold holds the target exposed once it is: level 1 ends it 2 s / 0.1 s
    = 20 steps later than level 0, with success."""
    for seed in (0, 1):
        n0, info0 = _scripted_length(TissueRetractionEnv(difficulty=0), seed)
        n1, info1 = _scripted_length(TissueRetractionEnv(), seed)  # level 1 is the default
        assert info0["is_success"] and info1["is_success"]
        assert n1 == n0 + 20
        assert info1["hold_time"] == pytest.approx(2.0)


def test_level_2_widens_the_stiffness_range_of_the_scene():
    base = TissueRetractionEnv().scene.physics.young_modulus
    env = TissueRetractionVectorEnv(num_envs=64, difficulty=2)
    env.reset(seed=0)
    E = env.task.young_modulus
    assert E.min() >= 0.5 * base[0] and E.max() <= 1.5 * base[1]
    # uniform in the wider range: about 1/3 of 64 draws fall outside the original range
    outside = ((E < base[0]) | (E > base[1])).sum()
    assert 8 <= outside <= 40
    assert env.task.settings.hold_time == 2.0


def test_bad_difficulty_is_refused_naming_it():
    with pytest.raises(SpecError, match="difficulty: must be one of"):
        gym.make("heml_gym/TissueRetraction-v1", difficulty=3)
    with pytest.raises(SpecError, match="env.kwargs.difficulty: must be one of"):
        check_env_kwargs("heml_gym/OrganRetraction-v2", {"difficulty": "hard"})
    # a hold time the settings give replaces the level's; without one the level's applies
    assert TissueRetractionEnv(difficulty=1, settings={"hold_time": 0.5}).task.settings.hold_time == 0.5
    assert TissueRetractionEnv(difficulty=2, settings={"max_steps": 50}).task.settings.hold_time == 2.0
    assert TissueRetractionEnv(difficulty=0).task.settings.hold_time == 0.0


@pytest.mark.parametrize("env_id", ["heml_gym/TissueRetraction-v1", "heml_gym/OrganRetraction-v2"])
def test_level_2_hides_the_target_halfway_deeper_towards_the_hinge(env_id):
    """The target region's x moves half the way to the fold hinge (from the scene's own
    numbers), every drawn target lies in it, and the scripted fold still exposes it and
    holds it, later than at level 1 (the fold must go further; the hold is the same 2 s)."""
    base = gym.make(env_id).unwrapped.scene
    env = gym.make(env_id, difficulty=2)
    scene = env.unwrapped.scene
    hinge_x = base.fold.hinge[0]
    expected = sorted(x + 0.5 * (hinge_x - x) for x in (base.target.low[0], base.target.high[0]))
    assert [scene.target.low[0], scene.target.high[0]] == pytest.approx(expected)
    assert scene.target.low[1:] == base.target.low[1:] and scene.target.high[1:] == base.target.high[1:]
    for seed in range(5):
        env.reset(seed=seed)
        x = env.unwrapped.task.target[0, 0]
        assert expected[0] - 1e-12 <= x <= expected[1] + 1e-12
    lengths = {}
    for level in (1, 2):
        lengths[level], info = _scripted_length(gym.make(env_id, difficulty=level), seed=0)
        assert info["is_success"] and info["hold_time"] == pytest.approx(2.0)
    assert lengths[2] >= lengths[1] + 2
