"""Demonstration datasets: what Minari stores is what the policy did in the env (checked
against a direct rollout of the same seeds), loadable with minari.load_dataset."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np

from heml_gym.agents.cli import main
from heml_gym.envs import TISSUE_RETRACTION
from heml_gym.envs.scripted import scripted_policy


def test_a_scripted_demo_dataset_loads_and_equals_a_direct_rollout(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    name = "heml-gym/tissue-retraction/scripted-v0"
    assert main(["demos", TISSUE_RETRACTION, "--out", name, "--episodes", "2", "--seed", "3",
                 "--root", str(tmp_path)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["episodes"] == 2 and summary["success_rate"] == 1.0

    import minari

    dataset = minari.load_dataset(name)
    assert dataset.total_episodes == 2
    env = gym.make(TISSUE_RETRACTION)
    policy = scripted_policy(env.unwrapped.scene)
    for k, episode in enumerate(dataset.iterate_episodes()):
        obs, _ = env.reset(seed=3 + k)
        policy.reset()
        np.testing.assert_array_equal(episode.observations[0], obs)
        for t in range(len(episode.actions)):
            action = policy(obs)
            np.testing.assert_allclose(episode.actions[t], action, atol=1e-6)
            obs, reward, terminated, truncated, info = env.step(episode.actions[t])
            np.testing.assert_array_equal(episode.observations[t + 1], obs)
            assert episode.rewards[t] == reward and episode.terminations[t] == terminated
            for key in ("grasp_force", "max_strain", "exposure", "cost", "damage"):
                assert episode.infos[key][t + 1] == info[key]
        assert episode.terminations[-1] and info["is_success"]
    # a second dataset of the same name is refused, nothing overwritten
    assert main(["demos", TISSUE_RETRACTION, "--out", name, "--episodes", "1", "--root", str(tmp_path)]) == 2
    assert "exists" in capsys.readouterr().err
