"""Jaws on a free wrist (heml_gym.calibration.wrist): a held patch turns about the jaws'
axis to where the tissue's torque on it vanishes; the replay's adjoint gradients hold
through the turn."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize as so

import heml_gym as hg
from heml_gym.calibration import ControlLog, Replay, ReplayError, embed_points
from heml_gym.calibration.wrist import rotation
from heml_gym.contact import PlaneSupport

from test_calibration import _random_loss_gradient_check

AXIS = np.array([0.0, 1.0, 0.0])  # the jaws' axis: along the slab's free edge


def _material(theta):
    return hg.materials.NeoHookean(E=theta[0], nu=theta[1])


def _slab(mesh, field="heml"):
    """A slab 60 x 60 x 8 mm clamped at x = 0 on a support plane; its last 10 mm (x >= 50
    mm) is the patch the jaws hold."""
    X = mesh.vertices
    model = hg.Model(mesh, _material((5e3, 0.45)), n_worlds=1, density=950.0, fixed=X[:, 0] < 1e-9, damping=5.0,
                     supports=[PlaneSupport((0, 0, 1.0), 0.0)], field=field)
    return model, X[:, 0] > 0.05 - 1e-9


def _wrist_log(mesh, patch, steps, move, substeps=2, turning=True, lead=0):
    """The patch lifted by ``move`` (m) per 0.1 s control step; ``turning``: on a free wrist
    about the y axis through the patch's middle, else held rigidly. With ``lead`` steps,
    the edge line alone is lifted first (held without the wrist) and the patch is grasped
    after them where the tissue then is (so that the grasp's start depends on the tissue)."""
    X = mesh.vertices
    move = np.asarray(move, dtype=np.float64)
    edge = X[:, 0] > 0.06 - 1e-9
    kinematic = np.zeros((steps, mesh.n_vertices), bool)
    kinematic[:lead, edge] = True
    kinematic[lead:, patch] = True
    targets = np.zeros((steps, mesh.n_vertices, 3))
    for t in range(steps):
        targets[t, kinematic[t]] = X[kinematic[t]] + move * (t + 1)
    points = np.array([0.055, 0.03, 0.004]) + move * np.arange(steps + 1)[:, None]
    wrist = kinematic.copy()
    wrist[:lead] = False
    wrist = dict(wrist=wrist, wrist_axis=AXIS, wrist_points=points) if turning else {}
    return ControlLog(kinematic, targets, 0.1, substeps, X, np.zeros_like(X), **wrist)


def _torque(model, y, patch, point):
    """The elastic torque (N m) on the patch about the axis through ``point``."""
    f = model.fields[0].forces(y)
    return float(np.cross(y[patch] - point, f[patch]).sum(axis=0) @ AXIS)


@pytest.mark.parametrize("field", ["heml", "quadratic"])
def test_a_free_wrist_turns_the_patch_to_where_the_torque_on_it_vanishes(field):
    """One backward Euler step that lifts the patch by 12 mm: the free wrist's end state is
    the rigidly held patch's at the angle where the tissue's torque on it about the axis is
    zero, found independently by root-finding over rigid holds at fixed angles."""
    mesh = hg.box_mesh((0.06, 0.06, 0.008), (6, 6, 1))
    if field == "quadratic":
        mesh = hg.QuadraticTetMesh.from_linear(hg.box_mesh((0.06, 0.06, 0.008), (3, 3, 1)))
    model, patch = _slab(mesh, field)
    move = np.array([-0.004, 0.0, 0.012])
    free = Replay(model, _wrist_log(mesh, patch, 1, move, substeps=1), _material).run((5e3, 0.45))
    point = np.array([0.055, 0.03, 0.004]) + move
    X = mesh.vertices

    def held_at(angle):
        log = _wrist_log(mesh, patch, 1, move, substeps=1, turning=False)
        log.targets[0, patch] = point + (X[patch] + move - point) @ rotation(AXIS, angle).T
        return Replay(model, log, _material).run((5e3, 0.45)).x[-1]

    angle = so.brentq(lambda a: _torque(model, held_at(a), patch, point), -1.5, 0.5, xtol=1e-12)
    assert abs(angle) > 0.1  # the tissue turns the patch
    assert free.tape[-1]["angle"] == pytest.approx(angle, abs=1e-7)
    assert np.abs(free.x[-1] - held_at(angle)).max() < 1e-8
    # and that angle matters: held 0.1 rad further, the patch feels a torque (the slab's
    # weight, 0.27 N, times its length is 0.016 N m)
    assert abs(_torque(model, held_at(angle + 0.1), patch, point)) > 1e-4


def test_adjoint_gradients_with_a_free_wrist():
    """The edge lifted for 2 control steps, then the patch around it grasped on a free wrist
    where the tissue is and lifted and pulled back for 5 more (two sub-steps each; it turns
    by over 1 rad), on the support plane, with damping: d/dE, d/dnu, d/density and
    d/damping of a random loss on every position and the jaws' force against central
    differences."""
    mesh = hg.box_mesh((0.06, 0.06, 0.008), (6, 6, 1))
    model, patch = _slab(mesh)
    log = _wrist_log(mesh, patch, 7, (-0.004, 0.0, 0.006), lead=2)
    replay = Replay(model, log, _material, dynamics_of=lambda theta: (theta[2], theta[3]))
    result = replay.run((5e3, 0.45, 1100.0, 3.0))
    assert abs(result.tape[-1]["angle"]) > 1.0
    _random_loss_gradient_check(replay, (5e3, 0.45, 1100.0, 3.0), (0.5, 1e-5, 0.1, 1e-3), np.random.default_rng(3))


def test_adjoint_gradients_with_a_free_wrist_on_quadratic_tets():
    """The same on 10-node tets (the NumPy sub-step), over 4 control steps (the first on the edge)."""
    mesh = hg.QuadraticTetMesh.from_linear(hg.box_mesh((0.06, 0.06, 0.008), (3, 3, 1)))
    model, patch = _slab(mesh, "quadratic")
    replay = Replay(model, _wrist_log(mesh, patch, 4, (-0.004, 0.0, 0.006), lead=1), _material)
    _random_loss_gradient_check(replay, (5e3, 0.45), (0.5, 1e-5), np.random.default_rng(4))


@pytest.mark.parametrize("law", ["NeoHookean", "MooneyRivlin"])
def test_the_quasi_newton_solver_steps_a_free_wrist_as_the_replay_does(law):
    """The envs' solver (L-BFGS, the wrist's angle eliminated inside each evaluation of the
    potential) against the calibration's replay (Newton on the free vertices and the angle
    together, an independent implementation): the patch lifted and pulled back over 3
    control steps of two sub-steps each, turning by over 0.8 rad. Two worlds in one call:
    the first on the free wrist, the second holding the same patch rigidly (its replay
    holds it rigidly too), so the wrist stays in its world. Neo-Hookean (the kernels' fused
    constant-Psi_1 path) and Mooney-Rivlin (the general one, with I2)."""
    def material(theta):
        return getattr(hg.materials, law)(E=theta[0], nu=theta[1])

    mesh = hg.box_mesh((0.06, 0.06, 0.008), (6, 6, 1))
    model, patch = _slab(mesh)
    model = hg.Model(mesh, material((5e3, 0.45)), n_worlds=2, density=950.0, fixed=model.fixed, damping=5.0,
                     supports=[PlaneSupport((0, 0, 1.0), 0.0)])
    steps, move, point = 3, np.array([-0.004, 0.0, 0.006]), np.array([0.055, 0.03, 0.004])
    X = mesh.vertices
    solver = hg.QuasiNewtonSolver(model, newton_tol=1e-9, max_iter=1000)
    state = hg.State(np.stack([X, X]))
    control = hg.Control(2, mesh.n_vertices)
    for world in (0, 1):
        control.attach(world, patch, X)
    control.turn(0, patch, point, AXIS)
    for t in range(steps):
        control.drive_wrist(0, point + move * (t + 1))
        control.drive(1, patch, X[patch] + move * (t + 1))
        stats = solver.step(state, state, control, 0.1, substeps=2)
        assert stats.converged.all(), stats.messages
    turned = Replay(model, _wrist_log(mesh, patch, steps, move), material).run((5e3, 0.45))
    rigid = Replay(model, _wrist_log(mesh, patch, steps, move, turning=False), material).run((5e3, 0.45))
    assert control.wrist_angle[0] < -0.8
    assert control.wrist_angle[0] == pytest.approx(turned.tape[-1]["angle"], abs=1e-7)
    assert np.abs(state.x[0] - turned.x[-1]).max() < 1e-8
    assert np.abs(state.x[1] - rigid.x[-1]).max() < 1e-8
    assert np.abs(turned.x[-1] - rigid.x[-1]).max() > 5e-3  # (the turn matters)
    # the patch is where the control says the wrist is, and rigid
    assert np.abs(state.x[0][patch] - control.wrist_places(0)).max() < 1e-12


def test_releasing_part_of_a_wrist_keeps_the_rest_held_where_it_is():
    """``Control.detach`` of some of the wrist's vertices ends the wrist; the others stay
    held exactly where the turn left them (a step without new targets does not move them),
    and ``wrist_places`` is where the solver put the patch."""
    mesh = hg.box_mesh((0.06, 0.06, 0.008), (6, 6, 1))
    model, patch = _slab(mesh)
    X = mesh.vertices
    solver = hg.QuasiNewtonSolver(model)
    state = hg.State(X[None].copy())
    control = hg.Control(1, mesh.n_vertices)
    control.attach(0, patch, X)
    point = np.array([0.055, 0.03, 0.004])
    control.turn(0, patch, point, AXIS)
    control.drive_wrist(0, point + np.array([-0.004, 0.0, 0.01]))
    assert solver.step(state, state, control, 0.1, substeps=2).converged.all()
    assert abs(control.wrist_angle[0]) > 0.1
    assert np.abs(control.wrist_places(0) - state.x[0][patch]).max() < 1e-12
    rows = np.flatnonzero(patch)
    released, kept = rows[: len(rows) // 2], rows[len(rows) // 2:]
    here = state.x[0][kept].copy()
    control.detach(0, released)
    assert not control.turns.any() and control.kinematic[0, kept].all() and not control.kinematic[0, released].any()
    assert solver.step(state, state, control, 0.1, substeps=2).converged.all()
    assert np.abs(state.x[0][kept] - here).max() < 1e-12


@pytest.mark.parametrize("solver", ["ExplicitSolver", "ImplicitSolver", "StaticSolver"])
def test_solvers_that_do_not_step_a_wrist_say_so(solver):
    mesh = hg.box_mesh((0.06, 0.06, 0.008), (2, 2, 1))
    _, patch = _slab(mesh)
    model = hg.Model(mesh, _material((5e3, 0.45)), fixed=mesh.vertices[:, 0] < 1e-9)  # (statics: no supports)
    control = hg.Control(1, mesh.n_vertices)
    control.attach(0, patch, mesh.vertices)
    control.turn(0, patch, (0.055, 0.03, 0.004), AXIS)
    state = hg.State(mesh.vertices[None].copy())
    with pytest.raises(ValueError, match="does not step jaws on a free wrist") as error:
        stepper = getattr(hg, solver)(model)
        if solver == "StaticSolver":
            stepper.solve(state, control)
        else:
            stepper.step(state, state, control, 0.01)
    assert "\n" not in str(error.value)


@pytest.mark.parametrize("change, says", [
    (dict(vertices="unheld"), "must be held exactly"),
    (dict(axis=(0.0, 0.0, 0.0)), "axis must be a finite nonzero"),
    (dict(pivot=(0.0, np.nan, 0.0)), "pivot must be 3 finite coordinates"),
    (dict(vertices="on the axis"), "every vertex lies on the axis"),
])
def test_a_bad_wrist_control_is_a_one_line_error(change, says):
    mesh = hg.box_mesh((0.06, 0.06, 0.008), (2, 2, 1))
    _, patch = _slab(mesh)
    control = hg.Control(1, mesh.n_vertices)
    control.attach(0, patch, mesh.vertices)
    args = dict(vertices=patch, pivot=(0.055, 0.03, 0.004), axis=AXIS)
    args.update(change)
    if isinstance(args["vertices"], str) and args["vertices"] == "unheld":
        args["vertices"] = ~patch
    elif isinstance(args["vertices"], str):  # on the axis
        args["vertices"], args["pivot"] = np.flatnonzero(patch)[:1], mesh.vertices[patch][0]
    with pytest.raises(ValueError, match=says) as error:
        control.turn(0, args["vertices"], args["pivot"], args["axis"])
    assert "\n" not in str(error.value)


@pytest.mark.parametrize("change, says", [
    (dict(wrist_axis=None), "wrist: give wrist_axis"),
    (dict(wrist_axis=(0.0, 0.0, 0.0)), "wrist_axis: must be a finite nonzero"),
    (dict(wrist_points=np.zeros((2, 3))), "wrist_points: must be finite with shape (3, 3)"),
    (dict(wrist=np.ones((2, 8), bool)), "wrist: must have shape"),
    (dict(unheld=True), "wrist: every vertex that turns with the jaws must be held"),
    (dict(wrist=None), "wrist_axis, wrist_points: give them with wrist"),
])
def test_a_bad_wrist_is_a_one_line_error_naming_the_field(change, says):
    mesh = hg.box_mesh((0.06, 0.06, 0.008), (2, 2, 1))
    _, patch = _slab(mesh)
    log = _wrist_log(mesh, patch, 2, (0.0, 0.0, 0.001))
    fields = dict(kinematic=log.kinematic, targets=log.targets, dt=0.1, substeps=1, x0=log.x0, v0=log.v0,
                  wrist=log.wrist, wrist_axis=AXIS, wrist_points=log.wrist_points)
    if change.pop("unheld", False):
        fields["wrist"] = np.ones_like(log.wrist)
    fields.update(change)
    with pytest.raises(ReplayError) as error:
        ControlLog(**fields)
    assert says in str(error.value) and "\n" not in str(error.value)


def test_a_fixed_vertex_cannot_turn_with_the_jaws():
    mesh = hg.box_mesh((0.06, 0.06, 0.008), (2, 2, 1))
    model, patch = _slab(mesh)
    log = _wrist_log(mesh, patch, 2, (0.0, 0.0, 0.001))
    log.kinematic[:] = True
    log.wrist[:] = True
    with pytest.raises(ReplayError, match="a vertex the model fixes cannot turn"):
        Replay(model, log, _material)


def test_the_flaps_jaws_on_a_free_wrist_hold_the_patch_next_to_their_line():
    """control_log(wrist_reach=...) on the flap's scripted retraction: the jaws hold every
    vertex within 10 mm (at rest) of the line the scene's jaws take, about the edge's
    direction; replayed, the patch stays rigid, ends turned, and feels no torque about
    the jaws' axis through its middle."""
    import gymnasium as gym

    from heml_gym.envs import TISSUE_RETRACTION
    from heml_gym.envs.observations import control_log, record
    from heml_gym.envs.scripted import scripted_policy

    env = gym.make(TISSUE_RETRACTION, physics={"young_modulus": [5e3, 5e3]})
    obs = record(env, scripted_policy(env.unwrapped.scene), seed=2, steps=12, points=4)
    env = gym.make(TISSUE_RETRACTION)
    line = control_log(env, obs)
    log = control_log(env, obs, wrist_reach=0.01)
    X = env.unwrapped.task.scene.mesh.vertices
    t = int(np.flatnonzero(line.gripped.any(axis=1))[0])  # the jaws close
    taken = line.gripped[t]
    near = np.array([np.linalg.norm(X[taken] - p, axis=1).min() <= 0.01 for p in X])
    assert np.array_equal(log.wrist[t], near) and not log.wrist[:t].any()
    assert np.all(log.gripped[t:] >= log.wrist[t:])
    edge = X[taken][-1] - X[taken][0]
    assert abs(log.wrist_axis @ edge) == pytest.approx(np.linalg.norm(edge), rel=1e-9)
    model = env.unwrapped.task.model
    replay = Replay(model, log, lambda theta: env.unwrapped.task.scene.physics.material_for(theta[0]))
    result = replay.run((5e3,))
    patch = log.wrist[-1]
    rest = result.x[t][patch]
    end = result.x[-1][patch]
    assert np.abs(np.linalg.norm(end[:, None] - end[None], axis=-1)
                  - np.linalg.norm(rest[:, None] - rest[None], axis=-1)).max() < 1e-9  # rigid
    assert abs(result.tape[-1]["angle"]) > 0.3
    f = model.fields[0].forces(result.x[-1])
    torque = np.cross(result.x[-1][patch] - log.wrist_points[-1], f[patch]).sum(axis=0) @ log.wrist_axis
    weight = float(np.linalg.norm(model.gravity) * model.mass.sum())
    assert abs(torque) < 1e-6 * weight * 0.1  # (the flap's weight times its length)


def test_a_wrist_reach_must_be_a_positive_distance():
    import gymnasium as gym

    from heml_gym.envs import TISSUE_RETRACTION
    from heml_gym.envs.observations import control_log, record
    from heml_gym.envs.scripted import scripted_policy

    env = gym.make(TISSUE_RETRACTION)
    obs = record(env, scripted_policy(env.unwrapped.scene), seed=2, steps=2, points=4)
    for bad in (0.0, -0.01, float("nan"), "1cm"):
        with pytest.raises(ValueError, match="wrist_reach: must be a positive distance in metres"):
            control_log(env, obs, wrist_reach=bad)


def test_observe_and_calibrate_with_a_free_wrist_from_the_command_line(tmp_path, capsys):
    """`heml-gym observe --wrist-reach` (the flap held on a free wrist, stepped by the
    replay: the envs do not step that grasp) then `heml-gym calibrate --wrist-reach` on the
    same model: E recovered to 1 %; calibrated with the scene's own grasp instead, the same
    file gives an E more than 5 % off."""
    import json

    from heml_gym.agents.cli import main
    from heml_gym.envs import TISSUE_RETRACTION

    obs = tmp_path / "wrist.npz"
    assert main(["observe", TISSUE_RETRACTION, "--out", str(obs), "--young-modulus", "4500", "--steps", "12",
                 "--points", "6", "--seed", "5", "--wrist-reach", "0.01"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["wrist_reach_m"] == 0.01 and summary["truth"]["young_modulus"] == 4500.0
    fits = {}
    for name, extra in (("wrist", ["--wrist-reach", "0.01"]), ("line", [])):
        out = tmp_path / name
        assert main(["calibrate", "-", str(obs), "--out", str(out), "--fit", "young_modulus", "--no-progress",
                     *extra]) in (0, 1)
        fits[name] = json.loads((out / "fit.json").read_text())
    capsys.readouterr()
    assert fits["wrist"]["settings"]["wrist_reach_m"] == 0.01 and fits["wrist"]["converged"]
    assert fits["wrist"]["parameters"]["young_modulus"]["value"] == pytest.approx(4500.0, rel=0.01)
    assert abs(fits["line"]["parameters"]["young_modulus"]["value"] / 4500.0 - 1.0) > 0.05


@pytest.mark.parametrize("env_id, kwargs", [
    ("heml_gym/TissueRetraction-v1", {"scene": {"tissue": {"cells": [8, 8, 2]}, "gripper": {"wrist_reach": 0.01}}}),
    ("heml_gym/OrganRetraction-v2", {"mesh_size": 0.014, "scene": {"gripper": {"wrist_reach": 0.005}}}),
])
def test_an_env_with_its_jaws_on_a_free_wrist_is_what_the_replay_of_its_control_gives(env_id, kwargs):
    """``scene.gripper.wrist_reach``: the env's own solver turns the patch; the calibration's
    replay of the control it logged (:func:`control_log`: the patch, axis and pivot path)
    gives the same trajectory (tracked points within 10 nm, the jaws' force within 1 uN,
    over a scripted retraction in which the wrist turns by over 0.5 rad), the env's
    L-BFGS tightened to 1e-8 of the weight."""
    import gymnasium as gym

    from heml_gym.envs.observations import calibration_problem, record
    from heml_gym.envs.scripted import scripted_policy

    kwargs = {**kwargs, "physics": {"young_modulus": [5000.0, 5000.0], "newton_tol": 1e-8, "max_newton": 3000}}
    env = gym.make(env_id, **kwargs)
    obs = record(env, scripted_policy(env.unwrapped.scene), seed=2, steps=12, points=8)
    angle = env.unwrapped.task.control.wrist_angle[0]
    assert abs(angle) > 0.5
    replay, *_ = calibration_problem(gym.make(env_id, **kwargs), obs, ("young_modulus",))
    assert replay.log.wrist is not None and replay.log.wrist.any()
    result = replay.run((5000.0, float(env.unwrapped.task.scene.physics.poisson)))
    assert result.tape[-1]["angle"] == pytest.approx(angle, abs=1e-6)
    B = embed_points(env.unwrapped.task.scene.mesh, obs.rest_points)
    points = np.stack([B @ x for x in result.x])
    assert np.abs(points - obs.points).max() < 1e-8
    assert np.abs(result.force - obs.force[1:]).max() < 1e-6


@pytest.mark.slow
def test_observe_and_calibrate_a_scene_whose_jaws_are_on_a_free_wrist(tmp_path, capsys):
    """A scene with ``gripper.wrist_reach`` from the command line: `heml-gym observe` records
    points, force and depth images of its own free-wrist grasp (the env steps it), and
    `heml-gym calibrate` with the same scene (its replay turns the patch as the env did)
    recovers E to 2 % from all three; a replay without the wrist (the scene's line grasp)
    misreads the same file by more than 5 %."""
    import json

    from heml_gym.agents.cli import main
    from heml_gym.envs import TISSUE_RETRACTION

    wrist = json.dumps({"scene": {"gripper": {"wrist_reach": 0.01}}})
    obs = tmp_path / "wrist.npz"
    assert main(["observe", TISSUE_RETRACTION, "--out", str(obs), "--young-modulus", "4500", "--steps", "12",
                 "--points", "6", "--seed", "5", "--depth", "32x32", "--env-kwargs", wrist]) == 0
    capsys.readouterr()
    fits = {}
    for name, extra in (("wrist", ["--env-kwargs", wrist]), ("line", [])):
        out = tmp_path / name
        assert main(["calibrate", "-", str(obs), "--out", str(out), "--fit", "young_modulus", "--no-progress",
                     *extra]) in (0, 1)
        fits[name] = json.loads((out / "fit.json").read_text())
    capsys.readouterr()
    assert fits["wrist"]["converged"]
    assert fits["wrist"]["parameters"]["young_modulus"]["value"] == pytest.approx(4500.0, rel=0.02)
    assert abs(fits["line"]["parameters"]["young_modulus"]["value"] / 4500.0 - 1.0) > 0.05


@pytest.mark.parametrize("gripper, physics, says", [
    ({"wrist_reach": -0.01}, {}, "wrist_reach: must be a positive length"),
    ({"wrist_reach": 0.01, "jaw_ends": "weighted", "jaw_length": 0.03}, {}, "give jaw_ends 'vertex'"),
    ({"wrist_reach": 0.01}, {"integrator": "explicit"}, "stepped by the quasi_newton integrator, not explicit"),
])
def test_a_bad_wrist_setting_is_a_one_line_error(gripper, physics, says):
    import gymnasium as gym

    from heml_gym.envs import TISSUE_RETRACTION
    from heml_gym.envs.spec import SpecError

    with pytest.raises(SpecError, match=says) as error:
        gym.make(TISSUE_RETRACTION, scene={"gripper": gripper}, physics=physics)
    assert "\n" not in str(error.value)
