"""Loading a run never executes code from it: a planted pickle, in every place a run is
read (model zip, observation statistics, checkpoints, a bare model), never runs; the
statistics round-trip through JSON exactly; the rebuilt model acts as SB3's own load."""

from __future__ import annotations

import base64
import json
import pathlib
import pickle
import shutil
import zipfile

import numpy as np
import pytest
from stable_baselines3 import PPO

from heml_gym.agents.cli import main
from heml_gym.agents.run_files import load_normalizer, save_normalizer

from test_agents import tiny_config


class Planted:
    """Unpickling this creates ``marker``: proof that a loader ran code from a file."""

    def __init__(self, marker: pathlib.Path):
        self.marker = marker

    def __reduce__(self):
        return pathlib.Path.touch, (self.marker,)


def plant_in_zip(path: pathlib.Path, marker: pathlib.Path) -> int:
    """Replace every pickled entry of an SB3 zip's ``data`` by the planted pickle."""
    with zipfile.ZipFile(path) as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(entries["data"].decode())
    planted = base64.b64encode(pickle.dumps(Planted(marker))).decode()
    n = 0
    for key, value in data.items():
        if isinstance(value, dict) and ":serialized:" in value:
            value[":serialized:"] = planted
            n += 1
    entries["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(path, "w") as archive:
        for name, content in entries.items():
            archive.writestr(name, content)
    return n


def test_a_planted_pickle_never_runs_wherever_a_run_is_read(tmp_path, capsys):
    config = tiny_config(tmp_path, algorithm__total_timesteps=512)
    run = tmp_path / "run"
    assert main(["train", str(config), "--run-dir", str(run), "--no-progress"]) == 0
    obs = np.linspace(-1.0, 1.0, 24).astype(np.float32)
    honest = PPO.load(run / "model.zip", device="cpu")  # (the test's own file: trusted)
    stats = load_normalizer(run / "vecnormalize.json")
    expected = honest.predict(stats.normalize_obs(obs), deterministic=True)[0]
    marker = tmp_path / "ran"
    zips = [run / "model.zip", *sorted((run / "checkpoints").glob("*.zip"))]
    assert all(plant_in_zip(z, marker) >= 3 for z in zips)
    for z in zips:  # and a planted pickle where the former statistics lived
        pickled = z.with_name("vecnormalize.pkl") if z.name == "model.zip" else z.with_name(
            z.name.replace("model_", "model_vecnormalize_").replace(".zip", ".pkl"))
        pickled.write_bytes(pickle.dumps(Planted(marker)))

    # every reader of a run: the same actions as SB3's own load of the honest file, and nothing ran
    from heml_gym.agents.train import load_policy

    policy, _, _ = load_policy(run)
    np.testing.assert_array_equal(policy(obs), expected)
    assert main(["eval", str(run), "--episodes", "1", "--out", str(tmp_path / "eval.json")]) == 0
    assert main(["rollout", "--policy", str(run / "model.zip"), "--episodes", "1", "--rrd",
                 str(tmp_path / "r.rrd")]) == 0
    checkpoint = sorted((run / "checkpoints").glob("*.zip"))[-1]
    assert main(["train", str(config), "--run-dir", str(run), "--resume", str(checkpoint), "--steps", "768",
                 "--no-progress"]) == 0
    assert not marker.exists()
    capsys.readouterr()

    # only the former pickled statistics, or a model without its run config: refused in one line
    (run / "vecnormalize.json").unlink()
    shutil.copy(run / "model.zip", tmp_path / "bare.zip")
    for argv in (["eval", str(run), "--episodes", "1"], ["eval", str(tmp_path / "bare.zip"), "--episodes", "1"],
                 ["rollout", "--policy", str(run), "--episodes", "1", "--rrd", str(tmp_path / "r2.rrd")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "--trust-pickle" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not marker.exists()
    # the planted pickle does run when the user says they trust the folder (the control)
    main(["eval", str(run), "--episodes", "1", "--trust-pickle"])
    assert marker.exists()


def test_observation_statistics_round_trip_through_json_exactly(tmp_path):
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize
    import gymnasium as gym

    rng = np.random.default_rng(0)
    venv = VecNormalize(DummyVecEnv([lambda: gym.make("Pendulum-v1")]), norm_reward=False, clip_obs=7.0)
    venv.obs_rms.update(rng.normal(3.0, 2.0, (500, 3)))
    path = save_normalizer(venv, tmp_path / "stats.json")
    loaded = load_normalizer(path)
    obs = rng.normal(3.0, 5.0, (10, 3)).astype(np.float32)
    np.testing.assert_array_equal(loaded.normalize_obs(obs), venv.normalize_obs(obs))
    assert loaded.obs_rms.count == venv.obs_rms.count and loaded.clip_obs == 7.0 and not loaded.training
    data = json.loads(path.read_text())
    data["stats"][""]["var"][0] = -1.0
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="stats.json"):
        load_normalizer(path)
