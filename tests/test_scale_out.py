"""Scale-out on Ray: sweep planning, statistics, and sweeps and an RLlib run on a real 2-node
cluster made and shut down by the test itself (``ray.cluster_utils.Cluster``; never a broad process kill)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from heml_gym.agents.config import ConfigError
from heml_gym.agents.stats import iqm, iqm_interval
from heml_gym.agents.sweep import parse_assignments, parse_grid, plan_sweep

ROOT = Path(__file__).resolve().parents[1]


def tiny_config(tmp_path) -> Path:
    cfg = yaml.safe_load((ROOT / "configs" / "quick.yaml").read_text())
    cfg["env"]["num_envs"] = 2
    cfg["env"]["kwargs"] = {"settings": {"max_steps": 10}}
    cfg["algorithm"]["total_timesteps"] = 128
    cfg["algorithm"]["hyperparameters"].update({"n_steps": 32, "batch_size": 32, "n_epochs": 1})
    cfg["evaluation"] = {"every_steps": 64, "episodes": 2}
    cfg["checkpoint"] = {"every_steps": 128}
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_iqm_is_the_trimmed_mean_and_its_interval_brackets_it():
    assert iqm([0.0, 1.0, 1.0, 1.0]) == 1.0  # the outlier is trimmed
    assert iqm([0.1, 0.2, 0.3, 0.4]) == pytest.approx(0.25)
    assert iqm([0.5]) == 0.5
    scores = np.array([0.2, 0.9, 0.95, 1.0, 1.0])
    lo, hi = iqm_interval(scores)
    assert lo <= iqm(scores) <= hi and 0.2 <= lo and hi <= 1.0
    assert iqm_interval([0.7, 0.7, 0.7]) == pytest.approx((0.7, 0.7))


def test_plan_validates_every_trial_before_anything_runs(tmp_path):
    config = tiny_config(tmp_path)
    trials = plan_sweep(config, [0, 1], parse_assignments(["algorithm.total_timesteps=256"]),
                        parse_grid(["algorithm.hyperparameters.learning_rate=0.001,0.0003"]), tmp_path / "out")
    assert len(trials) == 4 and len({t.run_dir for t in trials}) == 4
    assert {t.config.algorithm.total_timesteps for t in trials} == {256}
    assert {t.config.algorithm.hyperparameters["learning_rate"] for t in trials} == {0.001, 0.0003}
    assert {t.config.seed for t in trials} == {0, 1}
    with pytest.raises(ConfigError, match="n_stepz"):
        plan_sweep(config, [0], parse_assignments(["algorithm.hyperparameters.n_stepz=3"]))
    with pytest.raises(ConfigError, match="env.kwargs.physics.integrator"):
        plan_sweep(config, [0], parse_assignments(["env.kwargs.physics={integrator: rk4}"]))
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        parse_assignments(["algorithm.total_timesteps"])
    with pytest.raises(ConfigError, match="repeated"):
        plan_sweep(config, [1, 1])


@pytest.mark.slow
@pytest.mark.ray
def test_a_two_seed_sweep_lands_on_both_nodes_of_a_two_node_cluster(tmp_path):
    ray = pytest.importorskip("ray")
    from ray.cluster_utils import Cluster

    from heml_gym.agents.sweep import run_sweep

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    try:
        config = tiny_config(tmp_path)
        out = tmp_path / "sweep"
        trials = plan_sweep(config, [0, 1], {}, {}, out)
        summary = run_sweep(trials, out, address=cluster.address, verbose=False)
        assert summary["finished"] == 2 and summary["failed"] == 0
        rows = summary["trials"]
        assert len({r["node_id"] for r in rows}) == 2  # one trial per node
        nodes = {n["NodeID"] for n in ray.nodes() if n["Alive"]} if ray.is_initialized() else None
        for r in rows:
            assert r["env_steps"] >= 128 and 0.0 <= r["success_rate"] <= 1.0
            assert (Path(r["run_dir"]) / "model.zip").is_file()
            if nodes:
                assert r["node_id"] in nodes
        saved = json.loads((out / "summary.json").read_text())
        assert saved["grid_points"][0]["seeds"] == [0, 1] and "iqm" in saved["grid_points"][0]
        assert (out / "summary.png").is_file()
        # re-running resumes: both trials are finished, nothing runs again
        before = {r["run_dir"]: Path(r["run_dir"], "result.json").stat().st_mtime for r in rows}
        again = run_sweep(plan_sweep(config, [0, 1], {}, {}, out), out, address=cluster.address, verbose=False)
        assert again["finished"] == 2
        assert all(Path(p, "result.json").stat().st_mtime == t for p, t in before.items())
    finally:
        if ray.is_initialized():
            ray.shutdown()
        cluster.shutdown()


@pytest.mark.slow
@pytest.mark.ray
def test_a_failing_trial_is_reported_and_the_others_go_on(tmp_path, monkeypatch):
    pytest.importorskip("ray")
    from heml_gym.agents.sweep import run_sweep

    config = tiny_config(tmp_path)
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "sweep"
    trials = plan_sweep(config, [0, 1], {}, {}, "sweep")  # a relative folder, as the CLI's default
    # trial 1 cannot write its run folder: a file stands where its folder would be
    trials[1].run_dir.parent.mkdir(parents=True, exist_ok=True)
    trials[1].run_dir.write_text("in the way")
    summary = run_sweep(trials, out, verbose=False)
    status = {r["seed"]: r["status"] for r in summary["trials"]}
    assert status == {0: "finished", 1: "failed"}
    failed = next(r for r in summary["trials"] if r["seed"] == 1)
    assert "not a directory" in failed["error"]
    # the finished trial's run folder is under the sweep folder, not in Ray's trial working folder
    assert (out / trials[0].name / "evaluations.json").is_file()
    assert (out / "summary.json").is_file()


@pytest.mark.ray
def test_a_tiny_rllib_run_trains_checkpoints_evaluates_and_resumes_on_a_two_node_cluster(tmp_path):
    ray = pytest.importorskip("ray")
    from ray.cluster_utils import Cluster

    from heml_gym.agents.cli import main
    from heml_gym.agents.train import load_policy

    config = tmp_path / "rllib.yaml"
    config.write_text(yaml.safe_dump({
        "env": {"id": "heml_gym/TissueRetraction-v1", "num_envs": 2, "obs_mode": "state",
                "kwargs": {"settings": {"max_steps": 10}}},
        "algorithm": {"name": "RLlibPPO", "total_timesteps": 256,
                      "hyperparameters": {"num_env_runners": 2, "train_batch_size_per_learner": 128,
                                          "minibatch_size": 64, "num_epochs": 1}},
        "evaluation": {"every_steps": 256, "episodes": 1}, "checkpoint": {"every_steps": 128}, "seed": 0}))
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 2})
    cluster.add_node(num_cpus=2)
    cluster.wait_for_nodes()
    run = tmp_path / "run"
    try:
        assert main(["train", str(config), "--run-dir", str(run), "--no-progress", "--address", cluster.address]) == 0
        assert (run / "rllib_checkpoint" / "obs_stats.json").is_file()
        # the first checkpoint at the first iteration past 128 env steps (RLlib's iteration may
        # overshoot its batch by a rollout fragment on a busy machine: 192 steps seen)
        first = min(int(p.name.split("_")[1]) for p in (run / "checkpoints").iterdir())
        assert 128 <= first < 256
        history = json.loads((run / "evaluations.json").read_text())
        assert history[-1]["timesteps"] >= 256 and 0 <= history[-1]["success_rate"] <= 1
        with pytest.raises(ValueError, match="--trust-pickle"):  # RLlib unpickles its checkpoints
            load_policy(run)
        policy, _, cfg = load_policy(run, trust_pickle=True)
        action = policy(np.zeros(24, dtype=np.float32))
        assert action.shape == (4,) and np.all(np.abs(action) <= 1)
        assert cfg.algorithm.name == "RLlibPPO"
        out = tmp_path / "eval.json"
        assert main(["eval", str(run), "--episodes", "1", "--out", str(out), "--trust-pickle"]) == 0
        assert json.loads(out.read_text())["episodes"] == 1
        # resume from the final checkpoint: the step count continues
        assert main(["train", str(config), "--run-dir", str(run), "--no-progress", "--address", cluster.address,
                     "--resume", str(run / "rllib_checkpoint"), "--steps", "512", "--trust-pickle"]) == 0
        assert json.loads((run / "evaluations.json").read_text())[-1]["timesteps"] >= 512
    finally:
        if ray.is_initialized():
            ray.shutdown()
        cluster.shutdown()
