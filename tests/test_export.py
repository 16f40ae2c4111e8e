"""ONNX export: the graph computes what the SB3 policy does (an independent runtime,
onnxruntime, against SB3's own predict), with its limits applied, and it runs in rollout / eval."""

from __future__ import annotations

import json

import numpy as np
import pytest

from heml_gym.agents.cli import main
from heml_gym.agents.export import OnnxPolicy
from heml_gym.agents.train import load_policy
from test_agents import tiny_config


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("export")
    config = tiny_config(tmp, algorithm__total_timesteps=512)
    assert main(["train", str(config), "--run-dir", str(tmp / "run"), "--no-progress"]) == 0
    return tmp / "run"


def observations(n=400, seed=0):
    """Observations over and beyond the state's range (normalisation and clipping matter)."""
    from heml_gym.envs import STATE_SPEC

    rng = np.random.default_rng(seed)
    low = np.array([lo for _, lo, _, _ in STATE_SPEC])
    high = np.array([hi for _, _, hi, _ in STATE_SPEC])
    span = np.where(np.isfinite(high - low), high - low, 1.0)
    return (low + span * rng.uniform(-0.2, 1.2, (n, len(STATE_SPEC)))).astype(np.float32)


def test_the_onnx_graph_acts_as_the_policy(run, tmp_path):
    out = tmp_path / "policy.onnx"
    assert main(["export", str(run), "--out", str(out)]) == 0
    onnx_policy = OnnxPolicy(out)
    sb3_policy, _, cfg = load_policy(run)
    obs = observations()
    expected = np.array([sb3_policy(o) for o in obs])
    np.testing.assert_allclose(onnx_policy(obs), expected, atol=1e-5)
    assert onnx_policy.metadata["env_id"] == cfg.env.id and "gripper" in onnx_policy.metadata["observation"]


def test_a_sac_policy_exports_with_its_squash(tmp_path):
    import yaml

    from test_agents import ROOT

    cfg = yaml.safe_load((ROOT / "configs" / "tissue_sac.yaml").read_text())
    cfg["env"].update(num_envs=4, kwargs={"settings": {"max_steps": 20}})
    cfg["algorithm"]["total_timesteps"] = 160
    cfg["algorithm"]["hyperparameters"].update(learning_starts=40, batch_size=32, buffer_size=1000, gradient_steps=1)
    cfg["evaluation"] = {"every_steps": 160, "episodes": 1}
    cfg["checkpoint"] = {"every_steps": 160}
    config = tmp_path / "sac.yaml"
    config.write_text(yaml.safe_dump(cfg))
    assert main(["train", str(config), "--run-dir", str(tmp_path / "sac"), "--no-progress"]) == 0
    assert main(["export", str(tmp_path / "sac"), "--out", str(tmp_path / "sac.onnx")]) == 0
    sb3_policy, _, _ = load_policy(tmp_path / "sac")
    obs = observations(seed=2)
    np.testing.assert_allclose(OnnxPolicy(tmp_path / "sac.onnx")(obs), np.array([sb3_policy(o) for o in obs]),
                               atol=1e-5)


def test_limits_are_applied_in_the_graph(run, tmp_path):
    out = tmp_path / "limited.onnx"
    assert main(["export", str(run), "--out", str(out), "--speed-limit", "0.0003",
                 "--workspace", "0.0,0.0,0.0,0.1,0.1,0.05"]) == 0
    limited = OnnxPolicy(out)
    sb3_policy, _, cfg = load_policy(run)
    obs = observations(seed=1)
    raw = np.array([sb3_policy(o) for o in obs])
    got = limited(obs)
    fraction = 0.0003 / 0.05  # the env's max_speed is 0.05 m/s
    expected = raw.copy()
    expected[:, :3] = np.clip(raw[:, :3], -fraction, fraction)
    gripper = obs[:, :3]
    leaving = ((gripper >= np.array([0.1, 0.1, 0.05])) & (expected[:, :3] > 0)) | \
              ((gripper <= 0.0) & (expected[:, :3] < 0))
    expected[:, :3][leaving] = 0.0
    assert leaving.any() and (np.abs(raw[:, :3]) > fraction).any()  # both limits were exercised
    np.testing.assert_allclose(got, expected, atol=1e-5)
    np.testing.assert_allclose(json.loads(limited.metadata["workspace_m"]), [[0.0, 0.0, 0.0], [0.1, 0.1, 0.05]], rtol=1e-6)


def test_an_exported_policy_rolls_out_and_evaluates(run, tmp_path, capsys):
    out = tmp_path / "policy.onnx"
    assert main(["export", str(run), "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["eval", str(out), "--episodes", "2"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["episodes"] == 2 and "mean_damage" in result
    assert main(["rollout", "--policy", str(out), "--episodes", "1", "--rrd", str(tmp_path / "r.rrd")]) == 0
    assert (tmp_path / "r.rrd").stat().st_size > 0


@pytest.mark.parametrize("argv, says", [
    (["export", "{run}", "--out", "{tmp}/p.txt"], "--out"),
    (["export", "{run}", "--out", "{tmp}/p.onnx", "--workspace", "1,2,3"], "--workspace"),
    (["export", "{run}", "--out", "{tmp}/p.onnx", "--speed-limit", "-1"], "--speed-limit"),
    (["export", "{tmp}/nothing", "--out", "{tmp}/p.onnx"], "not found"),
    (["eval", "{tmp}/fake.onnx"], "not a loadable ONNX policy"),
])
def test_export_user_errors_are_one_line_and_leave_nothing(run, tmp_path, capsys, argv, says):
    (tmp_path / "fake.onnx").write_text("not onnx")
    before = sorted(p.name for p in tmp_path.iterdir())
    assert main([a.format(run=run, tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == before
