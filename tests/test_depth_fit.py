"""Fitting to depth images: the model's rendered tissue depth against an independent
renderer, its exact gradient against central differences, recovery of a known tissue from
depth alone, and bad depth options."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from heml_gym.agents.cli import main
from heml_gym.calibration import fit
from heml_gym.envs import ORGAN_RETRACTION, TISSUE_RETRACTION
from heml_gym.envs.depth_loss import DepthTerm, render_tissue_depth
from heml_gym.envs.observations import calibration_problem, record
from heml_gym.envs.scripted import scripted_policy


def _folded(env_id, steps=15, size=(40, 56)):
    kw = {"mesh_size": 0.012} if env_id == ORGAN_RETRACTION else {}
    env = gym.make(env_id, physics={"young_modulus": [5e3, 5e3]}, **kw)
    obs = record(env, scripted_policy(env.unwrapped.scene), seed=2, steps=steps, points=0, depth_size=size)
    return env, obs


@pytest.mark.parametrize("env_id", [TISSUE_RETRACTION, ORGAN_RETRACTION])
def test_the_rendered_tissue_depth_equals_the_env_cameras(env_id):
    """Half-way through the scripted fold, a non-square 40 x 56 image: where the env's own
    camera renderer (another rasteriser, of the whole scene) labels a pixel tissue, the
    depth fit's renderer finds the tissue at the same depth (to 1 micrometre) on all but a
    few silhouette pixels; in front of the tissue (the jaws) it finds it deeper."""
    env, obs = _folded(env_id)
    view = env.unwrapped.camera_view(0, (40, 56))
    task = env.unwrapped.task
    depth, triangle = render_tissue_depth(task.x[0], task.scene.surface_faces, obs.intrinsics, obs.camera_pose,
                                          (40, 56))
    tissue = view["segmentation"] == 1
    assert tissue.sum() > 100
    same = tissue & (np.abs(depth - view["depth"]) < 1e-6)
    assert same.sum() >= 0.97 * tissue.sum()
    np.testing.assert_allclose(view["depth"], obs.depth[-1])  # the observation is that camera's (noise-free)
    jaws = (view["segmentation"] == 3) & (triangle >= 0)
    assert np.all(depth[jaws] > view["depth"][jaws])


@pytest.mark.parametrize("env_id", [TISSUE_RETRACTION, ORGAN_RETRACTION])
def test_the_depth_terms_gradient_equals_central_differences(env_id):
    """d loss / d x of the depth term, along random directions of every vertex at every
    time, against central differences over a step within which the loss is smooth (from
    1e-7 m, refined until a tenth of it gives the same difference: the loss has a kink
    where a pixel's ray crosses a crease or the silhouette)."""
    env, obs = _folded(env_id, steps=6)
    term = DepthTerm(obs.depth + 2e-3, obs.intrinsics, obs.camera_pose, env.unwrapped.task.scene.surface_faces)
    replay, *_ = calibration_problem(gym.make(env_id, **({"mesh_size": 0.012} if env_id == ORGAN_RETRACTION else {})),
                                     obs, ("young_modulus",))
    x = replay.run([5600.0]).x
    loss, residuals, x_bar = term(x)
    assert loss > 0 and residuals.size == obs.depth.size
    rng = np.random.default_rng(0)

    def central(direction, h):
        return (term(x + h * direction)[0] - term(x - h * direction)[0]) / (2 * h)

    for _ in range(3):
        direction = rng.normal(size=x.shape)
        h = 1e-7
        coarse = central(direction, h)
        for _ in range(3):  # a step over which the loss is smooth: a tenth of it changes nothing
            fd = central(direction, h / 10)
            smooth = abs(coarse - fd) <= 1e-6 * abs(fd)
            if smooth:
                break
            h, coarse = h / 10.0, fd
        assert smooth, f"the loss is not smooth even within {h} m"
        assert (x_bar * direction).sum() == pytest.approx(fd, rel=1e-5)


def test_depth_alone_recovers_the_tissue_it_was_made_with():
    """A flap of E 5,500 Pa seen by a 48 x 48 depth camera (0.5 mm noise) for 1.2 s, no
    points and no force: the fit from E 7,000 Pa ends within 3 % of the truth."""
    env = gym.make(TISSUE_RETRACTION, physics={"young_modulus": [5500.0, 5500.0]})
    obs = record(env, scripted_policy(env.unwrapped.scene), seed=2, steps=12, points=0, depth_size=(48, 48),
                 depth_noise=5e-4, noise_seed=3)
    obs.force = None
    replay, observed, names, bounds, _ = calibration_problem(gym.make(TISSUE_RETRACTION), obs, ("young_modulus",))
    assert observed.points is None and observed.force is None and len(observed.extra) == 1
    result = fit(replay, observed, names, [[7000.0]], bounds)
    assert result.converged
    assert result.theta[0] == pytest.approx(5500.0, rel=0.03)
    assert 0 < result.std[0] < 0.03 * 5500.0
    assert 0 < result.residual_rms["depth_m"] < 0.01


@pytest.mark.parametrize("args, message", [(["--depth", "84"], "--depth"), (["--depth", "4x4"], "--depth"),
                                           (["--depth", "84x84", "--depth-noise", "-1"], "--depth-noise")])
def test_bad_depth_options_are_refused(tmp_path, capsys, args, message):
    out = tmp_path / "o.npz"
    assert main(["observe", TISSUE_RETRACTION, "--out", str(out), "--steps", "2", *args]) == 2
    assert message in capsys.readouterr().err and not out.exists()


def test_inconsistent_depth_files_are_refused_naming_the_field(tmp_path, capsys):
    """Depth in millimetres, non-square pixels, a pose that is not a rotation, a camera
    turned away from the tissue, a negative depth: each a one-line error naming the field,
    before any fit, and no output folder."""
    base = tmp_path / "base.npz"
    assert main(["observe", TISSUE_RETRACTION, "--out", str(base), "--steps", "2", "--points", "0",
                 "--depth", "32x32"]) == 0
    capsys.readouterr()
    data = dict(np.load(base))
    data.pop("force")
    fy, scaled, turned, negative = data["intrinsics"].copy(), data["camera_pose"].copy(), data["camera_pose"].copy(), \
        data["depth"].copy()
    fy[1, 1] *= 2
    scaled[:3, :3] *= 2
    turned[:3, 0] *= -1
    turned[:3, 2] *= -1
    negative[0, 0, 0] = -1.0
    for name, change, field in (("mm", {"depth": data["depth"] * 1000}, "depth"), ("fy", {"intrinsics": fy}, "intrinsics"),
                                ("scaled", {"camera_pose": scaled}, "camera_pose"),
                                ("turned", {"camera_pose": turned}, "depth"), ("negative", {"depth": negative}, "depth")):
        path = tmp_path / f"{name}.npz"
        np.savez(path, **{**data, **change})
        out = tmp_path / f"fit_{name}"
        assert main(["calibrate", "-", str(path), "--out", str(out), "--fit", "young_modulus", "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert f"field '{field}'" in err and len(err.strip().splitlines()) == 1, (name, err)
        assert not out.exists()


def test_observe_without_force_writes_a_depth_only_file(tmp_path, capsys):
    out = tmp_path / "d.npz"
    assert main(["observe", TISSUE_RETRACTION, "--out", str(out), "--steps", "2", "--points", "0", "--depth", "16x24",
                 "--no-force"]) == 0
    files = set(np.load(out).files)
    assert {"depth", "intrinsics", "camera_pose"} <= files and not {"force", "points"} & files
    assert np.load(out)["depth"].shape == (3, 16, 24)
    nothing = tmp_path / "e.npz"
    assert main(["observe", TISSUE_RETRACTION, "--out", str(nothing), "--points", "0", "--no-force"]) == 2
    assert "--no-force" in capsys.readouterr().err and not nothing.exists()
