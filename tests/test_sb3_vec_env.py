"""The SB3 VecEnv adapter: same-step auto-reset semantics, and PPO runs on it."""

from __future__ import annotations

import numpy as np

from heml_gym.agents.vec_env import RetractionSb3VecEnv
from heml_gym.envs.core import TaskSettings
from heml_gym.envs.tissue_retraction import TissueRetractionEnv, TissueRetractionVectorEnv


def test_autoreset_and_terminal_observation_match_single_env():
    settings = TaskSettings(max_steps=5)
    venv = RetractionSb3VecEnv(TissueRetractionVectorEnv(num_envs=2, settings=settings))
    venv.seed(7)
    obs = venv.reset()
    single = TissueRetractionEnv(settings=TaskSettings(max_steps=5))
    first, _ = single.reset(seed=7)
    np.testing.assert_array_equal(obs[0], first)
    rng = np.random.default_rng(0)
    for step in range(5):
        a = rng.uniform(-1, 1, (2, 4)).astype(np.float32)
        obs, reward, done, infos = venv.step(a)
        ref_obs, ref_reward, terminated, truncated, _ = single.step(a[0])
        assert reward[0] == np.float32(ref_reward)
        if done[0]:
            np.testing.assert_allclose(infos[0]["terminal_observation"], ref_obs, rtol=1e-6)
            assert infos[0]["TimeLimit.truncated"] == (truncated and not terminated)
            assert not np.array_equal(obs[0], ref_obs)  # already the next episode's start
            break
        np.testing.assert_allclose(obs[0], ref_obs, rtol=1e-6)
    assert done[0]  # the 5-step time limit ended it


def test_ppo_runs_on_the_batched_env():
    from stable_baselines3 import PPO

    venv = RetractionSb3VecEnv(TissueRetractionVectorEnv(num_envs=4, settings=TaskSettings(max_steps=20)))
    model = PPO("MlpPolicy", venv, n_steps=16, batch_size=32, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=128)
    assert model.num_timesteps >= 128
    action, _ = model.predict(venv.reset(), deterministic=True)
    assert action.shape == (4, 4)
