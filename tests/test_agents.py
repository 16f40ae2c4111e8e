"""Agents: config validation, a tiny train / save / reload / evaluate / resume cycle, CLI errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from stable_baselines3 import PPO

from heml_gym.agents.cli import main
from heml_gym.agents.config import ConfigError, config_from_dict, load_config
from heml_gym.agents.train import load_normalizer, load_policy, normalizer_path

ROOT = Path(__file__).resolve().parents[1]


def tiny_config(tmp_path, **changes) -> Path:
    cfg = yaml.safe_load((ROOT / "configs" / "quick.yaml").read_text())
    cfg["env"]["num_envs"] = 4
    cfg["env"]["kwargs"] = {"settings": {"max_steps": 20}}
    cfg["algorithm"]["total_timesteps"] = 1024
    cfg["algorithm"]["hyperparameters"].update(n_steps=64, batch_size=64, n_epochs=2)
    cfg["evaluation"] = {"every_steps": 512, "episodes": 3}
    cfg["checkpoint"] = {"every_steps": 512}
    for key, value in changes.items():
        section, name = key.split("__")
        cfg[section][name] = value
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.mark.parametrize("name", sorted(p.relative_to(ROOT / "configs").with_suffix("").as_posix()
                                         for p in (ROOT / "configs").rglob("*.yaml") if p.parent.name != "scenes"))
def test_shipped_configs_are_valid(name):
    """The canonical configs and the experiments (configs/experiments/) load and validate."""
    cfg = load_config(ROOT / "configs" / f"{name}.yaml")
    assert cfg.algorithm.total_timesteps > 0
    assert cfg.name == Path(name).name


@pytest.mark.parametrize("rates, stop_at", [
    ([0.0, 0.5, 0.95, 1.0, 1.0], 3),      # two in a row at >= 95 %: stops at the fourth
    ([1.0, 0.9, 1.0, 0.95], 3),           # a dip restarts the count
    ([0.95, 0.94, 1.0, 0.9, 1.0], None),  # never two in a row
])
def test_training_stops_after_two_evaluations_in_a_row_reach_the_bar(tmp_path, rates, stop_at):
    from heml_gym.agents.train import SuccessEvalCallback

    cfg = config_from_dict({"evaluation": {"every_steps": 1000, "episodes": 20, "stop_at_success": 0.95,
                                           "stop_after": 2}})
    callback = SuccessEvalCallback(cfg, tmp_path / "evaluations.json")
    stopped = []
    for k, rate in enumerate(rates):
        callback.history.append({"timesteps": 1000 * (k + 1), "success_rate": rate})
        if callback.learned():
            stopped.append(k)
    assert (stopped[0] if stopped else None) == stop_at


def test_the_main_job_stops_early_and_the_experiments_run_to_their_budget():
    """configs/quick.yaml stops once learned (400 k env steps its cap); the ablations that
    inherit it keep the schedule their stored results were measured with."""
    quick = load_config(ROOT / "configs" / "quick.yaml")
    assert quick.evaluation.stop_at_success == 0.95 and quick.evaluation.stop_after == 2
    assert quick.algorithm.total_timesteps == 400_000
    for name in ("quick_lift5", "quick_release0", "quick_stretch0", "quick_jaws40_weighted"):
        cfg = load_config(ROOT / "configs" / "experiments" / f"{name}.yaml")
        assert cfg.evaluation.stop_at_success is None and cfg.evaluation.every_steps == 40_000


def test_a_config_based_on_another_changes_only_what_it_names(tmp_path):
    base = yaml.safe_load((ROOT / "configs" / "quick.yaml").read_text())
    (tmp_path / "sub").mkdir()
    (tmp_path / "base.yaml").write_text(yaml.safe_dump({**base, "name": "the_base"}))
    (tmp_path / "sub" / "mid.yaml").write_text(yaml.safe_dump(
        {"base": "../base.yaml", "env": {"kwargs": {"weights": {"lift": 5.0}}}, "seed": 7}))
    (tmp_path / "sub" / "leaf.yaml").write_text(yaml.safe_dump(
        {"base": "mid.yaml", "env": {"num_envs": 4, "kwargs": {"settings": {"max_steps": 50}}}}))
    leaf = load_config(tmp_path / "sub" / "leaf.yaml").to_dict()
    expected = {**base, "seed": 7, "name": "leaf"}
    expected["env"] = {**base["env"], "num_envs": 4,
                       "kwargs": {"weights": {"lift": 5.0}, "settings": {"max_steps": 50}}}
    direct = tmp_path / "direct.yaml"
    direct.write_text(yaml.safe_dump(expected))
    assert leaf == load_config(direct).to_dict()


@pytest.mark.parametrize("text, match", [
    ("base: missing.yaml", "config key 'base'.*not found"),
    ("base: 3", "config key 'base'.*must be the path"),
    ("base: loop.yaml", "includes itself"),
])
def test_bad_config_bases_are_clear_errors(tmp_path, text, match):
    (tmp_path / "loop.yaml").write_text("base: other.yaml\n")
    (tmp_path / "other.yaml").write_text("base: loop.yaml\n")
    path = tmp_path / "cfg.yaml"
    path.write_text(text + "\n")
    with pytest.raises(ConfigError, match=match):
        load_config(path)


@pytest.mark.parametrize("data, key", [
    ({"algorithm": {"nme": "PPO"}}, "algorithm.nme"),
    ({"env": {"num_envs": "eight"}}, "env.num_envs"),
    ({"env": {"id": "heml_gym/Nope-v0"}}, "env.id"),
    ({"env": {"id": "heml_gym/OrganRetraction-v0"}}, "is retired"),
    ({"algorithm": {"name": "DQN"}}, "algorithm.name"),
    ({"evaluation": {"episodes": 0}}, "evaluation.episodes"),
    ({"evaluation": {"stop_at_success": 1.5}}, "evaluation.stop_at_success"),
    ({"evaluation": {"stop_at_success": 0}}, "evaluation.stop_at_success"),
    ({"evaluation": {"stop_after": 0}}, "evaluation.stop_after"),
    ({"seeed": 1}, "seeed"),
    ({"env": [1, 2]}, "env"),
])
def test_bad_configs_fail_fast_naming_the_key(data, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        config_from_dict(data)


def test_missing_config_file_and_model_are_clear_errors(tmp_path, capsys):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")
    assert main(["eval", str(tmp_path / "missing.zip")]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(["train", str(tmp_path / "nope.yaml")]) == 2


def test_tiny_training_run_saves_reloads_evaluates_and_resumes(tmp_path, capsys):
    config = tiny_config(tmp_path)
    run = tmp_path / "run"
    assert main(["train", str(config), "--run-dir", str(run), "--no-progress"]) == 0
    model = PPO.load(run / "model.zip", device="cpu")
    assert model.num_timesteps >= 1024
    history = json.loads((run / "evaluations.json").read_text())
    assert history and 0.0 <= history[-1]["success_rate"] <= 1.0
    assert 0.0 < history[0]["wall_s"] < history[-1]["wall_s"]
    checkpoints = sorted((run / "checkpoints").glob("*.zip"))
    assert checkpoints
    # evaluate the saved run through the CLI
    out = tmp_path / "eval.json"
    assert main(["eval", str(run), "--episodes", "2", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["episodes"] == 2 and len(result["success_ci95"]) == 2
    # a rollout on another env than the run's is refused, one line, nothing written
    rrd = tmp_path / "other.rrd"
    assert main(["rollout", "--policy", str(run), "--env", "heml_gym/OrganRetraction-v2", "--rrd", str(rrd)]) == 2
    err = capsys.readouterr().err
    assert "--env heml_gym/OrganRetraction-v2: the policy was trained on" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and not rrd.exists()
    # observation statistics: saved with the model and with every checkpoint, learned from
    # the training observations, and applied by the loaded policy
    stats = load_normalizer(run / "vecnormalize.json")
    assert stats.obs_rms.count >= 1024 and not stats.training
    assert not list(run.rglob("*.pkl"))  # no pickle is written
    assert all(normalizer_path(c).is_file() for c in checkpoints)
    policy, loaded, _ = load_policy(run)
    obs = np.array(stats.obs_rms.mean, dtype=np.float32) + 0.01
    expected = loaded.predict(stats.normalize_obs(obs), deterministic=True)[0]
    np.testing.assert_array_equal(policy(obs), expected)
    assert not np.array_equal(stats.normalize_obs(obs), obs)
    # resume from the final model: the step count continues to the new total, and the
    # statistics continue from the saved ones
    first = model.num_timesteps
    assert main(["train", str(config), "--run-dir", str(run), "--resume", str(run / "model.zip"),
                 "--steps", str(first + 512), "--no-progress"]) == 0
    resumed = PPO.load(run / "model.zip", device="cpu")
    assert first + 512 <= resumed.num_timesteps < first + 512 + 4 * 64 + 1
    assert load_normalizer(run / "vecnormalize.json").obs_rms.count > stats.obs_rms.count + 500
    # a model whose statistics are lost is refused, not run on unnormalised observations
    (run / "vecnormalize.json").unlink()
    with pytest.raises(FileNotFoundError, match="statistics"):
        load_policy(run / "model.zip")


@pytest.mark.slow
def test_a_config_with_env_kwargs_trains_evaluates_and_records_that_physics(tmp_path):
    import yaml as _yaml

    from heml_gym.agents.train import make_env

    physics = {"material": "StVenantKirchhoff", "integrator": "implicit"}
    config = tiny_config(tmp_path, algorithm__total_timesteps=256)
    data = _yaml.safe_load(config.read_text())
    data["env"]["kwargs"]["physics"] = physics
    data["evaluation"] = {"every_steps": 256, "episodes": 1}
    data["algorithm"]["hyperparameters"].update(n_steps=32, batch_size=64)
    config.write_text(_yaml.safe_dump(data))
    run = tmp_path / "run"
    assert main(["train", str(config), "--run-dir", str(run), "--no-progress"]) == 0
    recorded = _yaml.safe_load((run / "config.yaml").read_text())
    assert recorded["env"]["kwargs"] == {"settings": {"max_steps": 20}, "physics": physics}
    _, _, cfg = load_policy(run)
    env = make_env(cfg)
    task = env.unwrapped.task
    assert type(task.solver).__name__ == "ImplicitSolver"
    assert type(task.model.materials[0]).__name__ == "StVenantKirchhoff"
    assert task.settings.max_steps == 20
    rrd = tmp_path / "rollout.rrd"
    assert main(["rollout", "--policy", str(run), "--episodes", "1", "--rrd", str(rrd)]) == 0
    assert rrd.stat().st_size > 1000


def test_bad_env_kwargs_fail_before_a_run_folder_is_made(tmp_path, capsys):
    config = tiny_config(tmp_path)
    text = config.read_text().replace("max_steps: 20", "max_steps: 20\n    physics: {integrator: rk4}")
    config.write_text(text)
    run = tmp_path / "run"
    assert main(["train", str(config), "--run-dir", str(run)]) == 2
    err = capsys.readouterr().err
    assert "env.kwargs.physics.integrator" in err and "Traceback" not in err
    assert not run.exists()


@pytest.mark.parametrize("argv", [
    ["rollout", "--env", "heml_gym/Nope-v0"],
    ["rollout", "--policy", "scripted", "--env", "Nope-v0", "--rrd", "{tmp}/r.rrd"],
    ["eval", "{tmp}/no-run", "--env", "heml_gym/Nope-v0"],
    ["scene", "heml_gym/Nope-v0", "--out", "{tmp}/scene.yaml"],
])
def test_an_unknown_env_is_one_line_exit_2_and_nothing_written(tmp_path, capsys, argv):
    argv = [a.format(tmp=tmp_path) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "unknown environment" in err and "heml_gym/TissueRetraction-v1" in err  # (the known ones listed)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_a_retired_version_names_its_successor(tmp_path, capsys):
    assert main(["scene", "heml_gym/TissueRetraction-v0", "--out", str(tmp_path / "scene.yaml")]) == 2
    err = capsys.readouterr().err
    assert "retired" in err and "use heml_gym/TissueRetraction-v1" in err and len(err.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv, says", [
    (["eval", "{tmp}/nope"], "not found"),
    (["eval", "{tmp}/fake.zip"], "is not a PPO or SAC model"),
    (["eval", "{tmp}/empty_run"], "no model.zip or checkpoint"),
    (["rollout", "--policy", "{tmp}/nope", "--rrd", "{tmp}/r.rrd"], "not found"),
    (["rollout", "--policy", "{tmp}/fake.zip", "--rrd", "{tmp}/r.rrd"], "is not a PPO or SAC model"),
    (["rollout", "--episodes", "0", "--rrd", "{tmp}/r.rrd"], "episodes must be >= 1"),
    (["scene", "--out", "{tmp}/no/such/folder/scene.yaml"], "No such file or directory"),
    (["sweep", "{tmp}/nope.yaml"], "config file not found"),
    (["bench", "no_such_benchmark"], "unknown benchmark"),
    (["eval"], "the following arguments are required"),
    (["rollout", "--episodes", "two"], "invalid int value"),
    (["train", "configs/quick.yaml", "--no-such-flag"], "unrecognized arguments"),
])
def test_every_subcommands_user_errors_are_one_line_exit_2_and_leave_nothing(tmp_path, capsys, argv, says):
    """Missing and unreadable files, an empty run folder, bad values: one line on stderr
    naming the problem, exit 2, no traceback, nothing written."""
    (tmp_path / "fake.zip").write_text("not a zip")
    (tmp_path / "empty_run").mkdir()
    before = sorted(p.name for p in tmp_path.iterdir())
    try:
        code = main([a.format(tmp=tmp_path) for a in argv])
    except SystemExit as exit_:  # (argparse's errors exit from inside the parser)
        code = exit_.code
    assert code == 2
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert err.startswith("heml-gym") and ": error: " in err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_eval_scripted_runs_the_tasks_scripted_expert(tmp_path, capsys):
    """`heml-gym eval scripted --env ID` evaluates the task's scripted expert as a trained
    policy is evaluated: its success rate in the JSON, on seeds nobody tuned it on."""
    out = tmp_path / "scripted.json"
    assert main(["eval", "scripted", "--env", "heml_gym/OrganRetraction-v2", "--episodes", "2", "--seed", "90210",
                 "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["env"] == "heml_gym/OrganRetraction-v2" and result["episodes"] == 2
    assert result["success_rate"] >= 0.5
