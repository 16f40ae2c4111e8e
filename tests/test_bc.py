"""Behaviour cloning: the fit recovers a known policy; a BC run trains from a Minari
dataset, loads without unpickling anything, evaluates and exports like an RL run; bad
BC configs fail naming the key."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
import yaml

from heml_gym.agents.bc import BCPolicy, BehaviourCloning, fit
from heml_gym.agents.config import ConfigError, config_from_dict, load_config
from heml_gym.envs import TISSUE_RETRACTION


def test_the_fit_recovers_a_known_policy_on_fresh_observations():
    """Observations of very different scales and offsets, actions from a fixed tanh-linear
    teacher: on 1,000 fresh observations the fitted policy is within 0.05 of the teacher on
    average, ten times closer than the best constant action."""
    rng = np.random.default_rng(1)
    d, a = 12, 4
    scale, offset = rng.uniform(1e-3, 10, d), rng.uniform(-5, 5, d)
    weights = rng.normal(size=(a, d)) * 2 / np.sqrt(d)

    def teacher(obs):
        return np.tanh(((obs - offset) / scale) @ weights.T)

    train = offset + scale * rng.normal(size=(3000, d))
    net, mean, var, losses = fit(train, teacher(train), BehaviourCloning(hidden=[64, 64], epochs=30, batch_size=128))
    assert losses[-1] < 0.05 * losses[0]
    fresh = offset + scale * rng.normal(size=(1000, d))
    error = np.abs(BCPolicy(net, mean, var)(fresh) - teacher(fresh)).mean()
    constant = np.abs(teacher(train).mean(axis=0) - teacher(fresh)).mean()
    assert error < 0.05 and error < 0.1 * constant


def test_the_fit_is_seeded():
    rng = np.random.default_rng(2)
    obs, act = rng.normal(size=(200, 5)), np.tanh(rng.normal(size=(200, 4)))
    hp = BehaviourCloning(hidden=[16], epochs=3, batch_size=32)
    probe = rng.normal(size=(10, 5))
    runs = [BCPolicy(*fit(obs, act, hp, seed=s)[:3])(probe) for s in (0, 0, 1)]
    np.testing.assert_array_equal(runs[0], runs[1])
    assert np.abs(runs[0] - runs[2]).max() > 1e-4


def _bc_config(tmp_path, **demos):
    return {"env": {"id": TISSUE_RETRACTION, "num_envs": 1, "obs_mode": "state"},
            "algorithm": {"name": "BC", "hyperparameters": {"hidden": [32, 32], "epochs": 200, "batch_size": 64}},
            "demos": {"dataset": "heml-gym/test-tissue-scripted-v0", "policy": "scripted", "episodes": 2, "seed": 5,
                      "root": str(tmp_path / "minari"), **demos},
            "evaluation": {"episodes": 2}, "seed": 0, "name": "bc-test"}


def test_a_bc_run_trains_from_demos_loads_without_pickle_and_exports(tmp_path):
    from heml_gym.agents.cli import main
    from heml_gym.agents.train import load_policy

    config = tmp_path / "bc.yaml"
    config.write_text(yaml.safe_dump(_bc_config(tmp_path)))
    run = tmp_path / "run"
    assert main(["train", str(config), "--run-dir", str(run)]) == 0
    record = json.loads((run / "bc.json").read_text())
    assert record["episodes"] == 2 and record["transitions"] > 10
    assert record["loss_per_epoch"][-1] < record["loss_per_epoch"][0]
    (final,) = json.loads((run / "evaluations.json").read_text())
    assert final["episodes"] == 2 and 0.0 <= final["success_rate"] <= 1.0 and np.isfinite(final["mean_damage"])

    import minari

    episode = next(minari.load_dataset("heml-gym/test-tissue-scripted-v0").iterate_episodes())
    policy, _, cfg = load_policy(run)
    assert cfg.algorithm.name == "BC"
    actions = np.stack([policy(o) for o in episode.observations[:-1]])
    assert actions.shape == episode.actions.shape and np.all(np.abs(actions) <= 1.0)
    # it imitates: closer to the demonstrated actions than their mean is
    assert np.abs(actions - episode.actions).mean() < np.abs(episode.actions.mean(axis=0) - episode.actions).mean()

    pytest.importorskip("onnxruntime")
    from heml_gym.agents.export import OnnxPolicy

    onnx_path = tmp_path / "bc.onnx"
    assert main(["export", str(run), "--out", str(onnx_path)]) == 0
    exported = OnnxPolicy(onnx_path)
    onnx_actions = np.stack([exported(o) for o in episode.observations[:-1]])
    np.testing.assert_allclose(onnx_actions, actions, atol=1e-5)

    # a planted pickle in place of the weights is refused, and never run
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    (run / "policy.pt").write_bytes(pickle.dumps({"weight": Payload()}, protocol=2))
    with pytest.raises(ConfigError, match="policy.pt cannot be read as weights"):
        load_policy(run)
    assert not marker.exists()


@pytest.mark.parametrize("change, key", [
    ({"env": {"obs_mode": "rgb"}}, "env.obs_mode"),
    ({"algorithm": {"hyperparameters": {"epochz": 3}}}, "algorithm.hyperparameters.epochz"),
    ({"algorithm": {"hyperparameters": {"hidden": [0]}}}, "hidden"),
    ({"demos": {"dataset": None}}, "demos.dataset"),
    ({"demos": {"episodes": 0}}, "demos.episodes"),
    ({"demos": {"action_noise": -0.1}}, "demos.action_noise"),
    ({"algorithm": {"name": "PPO", "hyperparameters": {}}}, "demos"),
])
def test_a_bad_bc_config_fails_naming_the_key(tmp_path, change, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        config_from_dict(_merged(_bc_config(tmp_path), change))


def _merged(base: dict, change: dict) -> dict:
    out = dict(base)
    for k, v in change.items():
        out[k] = _merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def test_the_shipped_bc_configs_load():
    for name in ("tissue_bc", "organ_bc"):
        cfg = load_config(f"configs/{name}.yaml")
        assert cfg.algorithm.name == "BC" and cfg.demos.episodes == 100


def test_an_existing_dataset_that_is_not_the_configs_is_refused(tmp_path, capsys):
    """The config says 3 episodes; a dataset of that name with 2 exists: a one-line error,
    not a silent fit on other demonstrations, and no run folder."""
    from heml_gym.agents.cli import main

    cfg = _bc_config(tmp_path)
    assert main(["demos", TISSUE_RETRACTION, "--out", cfg["demos"]["dataset"], "--episodes", "2",
                 "--root", cfg["demos"]["root"]]) == 0
    capsys.readouterr()
    cfg["demos"]["episodes"] = 3
    config = tmp_path / "bc.yaml"
    config.write_text(yaml.safe_dump(cfg))
    run = tmp_path / "run"
    assert main(["train", str(config), "--run-dir", str(run), "--no-progress"]) == 2
    assert "exists with 2 episodes" in capsys.readouterr().err
    assert not run.exists()


@pytest.mark.slow
@pytest.mark.ray
def test_a_bc_sweep_records_its_demos_once_then_fits_every_seed(tmp_path):
    """`heml-gym sweep` of a BC config records the demonstrations once, before the trials
    (which would otherwise race to write them), and fits every seed from them."""
    pytest.importorskip("ray")
    from heml_gym.agents.cli import main

    config = tmp_path / "bc.yaml"
    config.write_text(yaml.safe_dump(_bc_config(tmp_path)))
    out = tmp_path / "sweep"
    assert main(["sweep", str(config), "--seeds", "0,1", "--out", str(out), "--quiet"]) == 0
    import minari

    assert minari.load_dataset("heml-gym/test-tissue-scripted-v0").total_episodes == 2
    for seed in (0, 1):
        record = json.loads((out / f"bc-test-seed{seed}" / "bc.json").read_text())
        assert record["episodes"] == 2 and (out / f"bc-test-seed{seed}" / "policy.pt").is_file()
