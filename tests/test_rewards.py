"""Reward and termination logic against values computed here from the actions, the
settings and the measurements, not by re-adding the env's own terms."""

from __future__ import annotations

import numpy as np
import pytest

from heml_gym.envs.core import RewardWeights, TaskSettings
from heml_gym.envs.scripted import scripted_policy
from heml_gym.envs.tissue_retraction import TissueRetractionEnv

W = RewardWeights(exposure=7.0, lift=3.0, grasp=0.8, strain=4.0, effort=0.05, success=9.0)


def test_effort_is_the_squared_clipped_velocity_command():
    env = TissueRetractionEnv(weights=W)
    env.reset(seed=0)
    rng = np.random.default_rng(1)
    for _ in range(10):
        a = rng.uniform(-3, 3, 4)  # out of range: the env clips to [-1, 1]
        *_, info = env.step(a.astype(np.float32))
        expected = -W.effort * float((np.clip(a[:3], -1, 1) ** 2).sum())
        assert info["reward_effort"] == pytest.approx(expected, rel=1e-6)


def test_the_grasp_bonus_is_paid_once_per_episode():
    env = TissueRetractionEnv(weights=W)
    bonuses = []
    env.reset(seed=2)
    for action in ([0, 0, 0, 1], [0, 0, 0, 1], [0, 0, 0, -1], [0, 0, 0, 1], [0, 0, 0.5, 1]):
        *_, info = env.step(np.array(action, dtype=np.float32))
        bonuses.append(info["reward_grasp"])
    assert bonuses == [W.grasp, 0.0, 0.0, 0.0, 0.0]  # the re-grasp earns nothing
    env.reset(seed=3)
    *_, info = env.step(np.array([0, 0, 0, 1], dtype=np.float32))
    assert info["reward_grasp"] == W.grasp  # a new episode pays again
    env.reset(seed=4)
    env.unwrapped.task.gripper[0] = [0.06, 0.06, 0.05]  # far from the grasp line: nothing held
    *_, info = env.step(np.array([0, 0, 0, 1], dtype=np.float32))
    assert info["reward_grasp"] == 0.0 and not info["grasping"]


def _pull(env, seed, steps, action=(0.6, 0.0, 1.0, 1.0)):
    env.reset(seed=seed)
    out = []
    for _ in range(steps):
        obs, reward, terminated, truncated, info = env.step(np.array(action, dtype=np.float32))
        out.append((reward, terminated, truncated, info))
        if terminated or truncated:
            break
    return out


def test_the_strain_penalty_is_the_strain_above_damage():
    settings = TaskSettings(damage_strain=0.02, tear_strain=5.0)
    env = TissueRetractionEnv(settings=settings, weights=W)
    steps = _pull(env, seed=5, steps=12)
    above = [info for _, _, _, info in steps if info["max_strain"] > settings.damage_strain]
    assert above, "the pull never strained the tissue past the damage threshold"
    for _, _, _, info in steps:
        expected = -W.strain * max(0.0, info["max_strain"] - settings.damage_strain)
        assert info["reward_strain"] == pytest.approx(expected, rel=1e-9, abs=1e-12)


def test_tearing_ends_the_episode_without_success():
    settings = TaskSettings(damage_strain=0.01, tear_strain=0.03)
    env = TissueRetractionEnv(settings=settings, weights=W)
    steps = _pull(env, seed=6, steps=30)
    reward, terminated, truncated, info = steps[-1]
    assert terminated and not truncated
    assert info["tissue_torn"] and info["max_strain"] >= settings.tear_strain
    assert not info["is_success"] and info["reward_success"] == 0.0
    assert all(not i["tissue_torn"] for *_, i in steps[:-1])  # it ends at the first tearing step


def test_success_needs_the_strain_below_damage():
    """The scripted fold exposes the target; with a damage threshold below the strain the
    fold needs, exposure alone does not end the episode and pays no success bonus."""
    strict = TaskSettings(damage_strain=1e-4, tear_strain=10.0, max_steps=40)
    for settings, should_succeed in ((TaskSettings(max_steps=40), True), (strict, False)):
        env = TissueRetractionEnv(settings=settings, weights=W, difficulty=0)  # success at once
        obs, _ = env.reset(seed=7)
        policy = scripted_policy(env.scene)
        exposed, succeeded = False, False
        for _ in range(40):
            obs, reward, terminated, truncated, info = env.step(policy(obs))
            exposed |= info["exposure"] >= settings.success_exposure
            if info["is_success"]:
                succeeded = True
                assert info["max_strain"] < settings.damage_strain
                assert info["reward_success"] == W.success and terminated
            else:
                assert info["reward_success"] == 0.0
            if terminated or truncated:
                break
        assert exposed
        assert succeeded == should_succeed


def test_exposure_and_lift_rewards_telescope_to_the_changes_of_the_measurements():
    env = TissueRetractionEnv(weights=W)
    obs, start = env.reset(seed=8)
    policy = scripted_policy(env.scene)
    total_exposure = total_lift = 0.0
    for _ in range(30):
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        total_exposure += info["reward_exposure"]
        total_lift += info["reward_lift"]
        if terminated or truncated:
            break
    assert total_exposure == pytest.approx(W.exposure * (info["exposure"] - start["exposure"]), abs=1e-9)
    assert total_lift == pytest.approx(W.lift * (info["lift"] - start["lift"]), abs=1e-9)


def _scripted_episode(settings, seed, release_at=None):
    """The scripted fold; ``release_at``: (steps after the condition is first met, steps)
    to open the gripper for, to break the hold."""
    env = TissueRetractionEnv(settings=settings, weights=W, difficulty=0)  # the settings' own hold time
    obs, _ = env.reset(seed=seed)
    policy = scripted_policy(env.scene)
    steps, met_at = [], None
    for k in range(settings.max_steps):
        action = policy(obs)
        if release_at is not None and met_at is not None and 0 <= k - met_at - release_at[0] < release_at[1]:
            action = np.array([0.0, 0.0, 0.0, -1.0], dtype=np.float32)  # open: the flap falls back
            policy.reset()
        obs, reward, terminated, truncated, info = env.step(action)
        steps.append((terminated, truncated, info))
        meets = info["exposure"] >= settings.success_exposure and info["max_strain"] < settings.damage_strain
        if meets and met_at is None:
            met_at = k
        if terminated or truncated:
            break
    return steps


@pytest.mark.parametrize("release_at", [None, (2, 1)])
def test_success_needs_the_condition_held_for_the_hold_time(release_at):
    """With ``hold_time`` = 1 s (10 steps of 0.1 s) success comes on the step the
    condition (exposure >= threshold, strain below damage) has held for 10 steps after
    first being met; breaking it restarts the timer. The run lengths are counted here
    from the measurements in ``info``; the hold reward is paid per held step before success."""
    settings = TaskSettings(hold_time=1.0, max_steps=100)
    steps = _scripted_episode(settings, seed=7, release_at=release_at)
    run, broken = 0, False
    for terminated, truncated, info in steps:
        meets = info["exposure"] >= settings.success_exposure and info["max_strain"] < settings.damage_strain
        broken |= run > 0 and not meets
        run = run + 1 if meets else 0
        held = max(run - 1, 0) * settings.control_dt
        assert info["hold_time"] == pytest.approx(held, abs=1e-12)
        success = run - 1 >= 10
        assert info["is_success"] == success and (terminated == success)
        assert info["reward_success"] == (W.success if success else 0.0)
        expected_hold = W.hold * settings.control_dt if meets and not success else 0.0
        assert info["reward_hold"] == pytest.approx(expected_hold, abs=1e-12)
    # the fold holds the target exposed and succeeds; released 0.2 s into the hold, the flap
    # falls back, the timer restarts and the episode runs out without success
    assert steps[-1][2]["is_success"] == (release_at is None)
    assert broken == (release_at is not None), "the release should (only) break the hold"
    # without a hold time the same fold succeeds at the first step the condition is met
    first = _scripted_episode(TaskSettings(max_steps=100), seed=7)
    met = [k for k, (_, _, i) in enumerate(steps) if i["exposure"] >= 0.8 and i["max_strain"] < 0.5]
    if release_at is None:
        assert len(first) == met[0] + 1 and len(steps) == met[0] + 11


def test_hold_time_is_checked():
    with pytest.raises(Exception, match="hold_time"):
        TaskSettings(hold_time=-1.0)
    with pytest.raises(Exception, match="hold_time"):
        TaskSettings(hold_time=float("nan"))


def test_the_stretch_cost_charges_each_rise_of_the_gauge_strain_and_favours_folding():
    """``reward_stretch`` is -w times each step's change of the reported gauge strain (the
    first step from the strain at reset); stretching the flap away from its hinge costs,
    folding it back about the hinge (the scripted path) costs far less, and the term is
    absent at weight 0."""
    weights = RewardWeights(stretch=6.0)
    env = TissueRetractionEnv(weights=weights)
    _, start = env.reset(seed=5)
    previous = start["max_strain"]
    for _ in range(12):  # up and away from the hinge: stretches
        *_, info = env.step(np.array([1.0, 0.0, 1.0, 1.0], dtype=np.float32))
        assert info["reward_stretch"] == pytest.approx(-6.0 * (info["max_strain"] - previous), abs=1e-12)
        previous = info["max_strain"]
    stretched = -6.0 * (info["max_strain"] - start["max_strain"])
    assert info["max_strain"] > 0.3 and stretched < -1.5

    obs, start = env.reset(seed=5)
    policy = scripted_policy(env.scene)
    total = 0.0
    for _ in range(12):
        obs, _, terminated, truncated, info = env.step(policy(obs))
        total += info["reward_stretch"]
    assert total > stretched / 2

    env = TissueRetractionEnv(weights={"stretch": 0.0})
    env.reset(seed=5)
    *_, info = env.step(np.array([1.0, 0.0, 1.0, 1.0], dtype=np.float32))
    assert info["reward_stretch"] == 0.0
