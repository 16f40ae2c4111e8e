"""Cost-constrained training: the penalised reward and the multiplier's dual ascent."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest
import yaml

from heml_gym.agents.cli import main
from heml_gym.agents.config import ConfigError, config_from_dict
from heml_gym.agents.constraint import CostPenalty
from heml_gym.agents.vec_env import RetractionSb3VecEnv
from heml_gym.envs import TISSUE_RETRACTION
from test_agents import tiny_config


def test_the_learner_sees_the_reward_minus_the_multiplier_times_the_cost():
    vec = gym.make_vec(TISSUE_RETRACTION, num_envs=3, vectorization_mode="vector_entry_point",
                       settings={"safe_strain": 0.0, "max_steps": 6}, max_episode_steps=6)
    env = CostPenalty(RetractionSb3VecEnv(vec.unwrapped), multiplier=2.5)
    env.reset()
    rng = np.random.default_rng(0)
    ended = 0
    for _ in range(8):
        _, reward, done, infos = env.step(rng.uniform(-1, 1, (3, 4)).astype(np.float32))
        for i, info in enumerate(infos):
            raw = sum(v for k, v in info.items() if k.startswith("reward_"))  # the env's own terms
            assert info["cost"] > 0.0  # (safe strain 0: the sagging tissue costs)
            assert reward[i] == pytest.approx(raw - 2.5 * info["cost"], abs=1e-5)
        ended += int(done.sum())
    assert len(env.ended_costs) == ended == 3  # each env's 6-step episode ended once
    assert all(c > 0 for c in env.ended_costs)


def test_a_constrained_run_raises_its_multiplier_while_episodes_exceed_the_budget(tmp_path):
    config = tiny_config(tmp_path, algorithm__total_timesteps=512)
    cfg = yaml.safe_load(config.read_text())
    cfg["env"]["kwargs"]["settings"]["safe_strain"] = 0.0
    cfg["constraint"] = {"budget": 0.0, "multiplier_lr": 0.5}
    config.write_text(yaml.safe_dump(cfg))
    assert main(["train", str(config), "--run-dir", str(tmp_path / "run"), "--no-progress"]) == 0
    record = json.loads((tmp_path / "run" / "constraint.json").read_text())
    history = record["history"]
    assert history and all(h["episode_cost"] > 0 for h in history)
    multipliers = [h["multiplier"] for h in history]
    expected, lam = [], 0.0
    for h in history:  # dual ascent from 0, as documented
        lam = max(0.0, lam + 0.5 * (h["episode_cost"] - 0.0))
        expected.append(lam)
    assert multipliers == pytest.approx(expected) and multipliers[-1] > 0


@pytest.mark.parametrize("constraint, key", [({"budget": -1.0}, "constraint.budget"),
                                             ({"budget": 0.1, "multiplier_lr": 0.0}, "constraint.multiplier_lr"),
                                             ({"budget": "low"}, "constraint.budget"),
                                             ({"budgett": 0.1}, "constraint.budgett")])
def test_bad_constraints_name_the_key(constraint, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        config_from_dict({"constraint": constraint})
