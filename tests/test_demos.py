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


def test_noisy_demos_keep_the_demonstrators_own_actions_as_labels(tmp_path, monkeypatch):
    """With --action-noise the env executes perturbed velocity commands (the stored
    actions: replaying them reproduces the episode) while infos['expert_action'] holds what
    the scripted policy itself chose at each stored observation (recomputed here by a fresh
    scripted policy fed the stored observations); the grasp command is never perturbed."""
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    name = "heml-gym/tissue-retraction/noisy-v0"
    assert main(["demos", TISSUE_RETRACTION, "--out", name, "--episodes", "2", "--seed", "7",
                 "--action-noise", "0.3", "--root", str(tmp_path)]) == 0

    import minari

    env = gym.make(TISSUE_RETRACTION)
    policy = scripted_policy(env.unwrapped.scene)
    perturbed = 0
    for k, episode in enumerate(minari.load_dataset(name).iterate_episodes()):
        expert = np.asarray(episode.infos["expert_action"])
        assert expert.shape == (len(episode.actions) + 1, 4)
        policy.reset()
        obs, _ = env.reset(seed=7 + k)
        for t in range(len(episode.actions)):
            np.testing.assert_allclose(expert[t + 1], policy(episode.observations[t]), atol=1e-6)
            assert episode.actions[t][3] == expert[t + 1][3]  # the grasp command as chosen
            perturbed += bool(np.abs(episode.actions[t][:3] - expert[t + 1][:3]).max() > 1e-3)
            obs, *_ = env.step(episode.actions[t])
            np.testing.assert_array_equal(episode.observations[t + 1], obs)
    assert perturbed > 10


def test_bad_action_noise_is_refused(tmp_path, capsys):
    assert main(["demos", TISSUE_RETRACTION, "--out", "heml-gym/x/y-v0", "--action-noise", "-1",
                 "--root", str(tmp_path)]) == 2
    assert "--action-noise" in capsys.readouterr().err


def test_a_bad_dataset_id_or_root_is_refused_before_anything_is_recorded(tmp_path, capsys):
    root = tmp_path / "minari"
    for name in ("bad name", "heml-gym/no-version", "../escape-v0", "heml-gym/x-v-1"):
        assert main(["demos", TISSUE_RETRACTION, "--out", name, "--episodes", "1", "--root", str(root)]) == 2
        assert "--out" in capsys.readouterr().err
    assert not root.exists() or not any(root.iterdir())
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert main(["demos", TISSUE_RETRACTION, "--out", "heml-gym/a-v0", "--episodes", "1", "--root", str(afile)]) == 2
    assert "--root" in capsys.readouterr().err
