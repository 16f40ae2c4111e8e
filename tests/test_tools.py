"""Rigid tools that touch the tissue (heml_gym/tools.py): their signed distances against
geometry, contact against the support plane it must reproduce, the force they report
against equilibrium (a slab's weight) and against the analytic uniaxial stress of a
squeezed slab, the same equilibrium in every solver, momentum (a tool's impulse) and
energy (the work it does pressing slowly is what the tissue stores), and a one-line error
from a solver that does not step them."""

from __future__ import annotations

import numpy as np
import pytest

import heml_gym as hg
from heml_gym import materials as M
from heml_gym.control import rotation
from heml_gym.tools import Tools

SLAB = hg.box_mesh((0.06, 0.03, 0.008), (6, 3, 2), origin=(0.0, 0.0, 0.0))
DENSITY, GRAVITY, DAMPING = 950.0, (0.0, 0.0, -9.81), 2.0


def _random_rotation(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return rotation(q[1:] / np.linalg.norm(q[1:]), 2 * np.arccos(q[0]))


def _pose(centre, rot):
    return np.concatenate([centre, rot.ravel()])[None, :]


def test_a_capsules_distance_is_the_distance_to_its_segment_less_its_radius():
    rng = np.random.default_rng(0)
    for _ in range(20):
        r, half = rng.uniform(0.002, 0.01), rng.uniform(0.005, 0.05)
        centre, rot = rng.uniform(-0.05, 0.05, 3), _random_rotation(rng)
        tools = Tools([hg.Capsule(r, half)])
        points = centre + rng.normal(size=(200, 3)) * 0.03
        d, normal = tools.signed_distance(points, _pose(centre, rot))
        # the segment, sampled densely: an independent nearest-point search
        segment = centre + np.linspace(-half, half, 20001)[:, None] * rot[:, 2]
        nearest = np.array([np.linalg.norm(segment - p, axis=1).min() for p in points])
        np.testing.assert_allclose(d, nearest - r, atol=half / 20000 + 1e-12)
        np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, rtol=1e-12)


def test_a_boxs_distance_is_zero_on_its_faces_and_grows_along_their_normals_and_its_normal_is_its_gradient():
    rng = np.random.default_rng(1)
    for _ in range(20):
        h = rng.uniform(0.002, 0.03, 3)
        centre, rot = rng.uniform(-0.05, 0.05, 3), _random_rotation(rng)
        tools, pose = Tools([hg.Box(h)]), _pose(centre, rot)
        for axis in range(3):
            for sign in (-1.0, 1.0):
                local = rng.uniform(-0.8, 0.8, (30, 3)) * h
                local[:, axis] = sign * h[axis]
                out = sign * rot[:, axis]
                face = centre + local @ rot.T
                for s in (0.0, 0.001, -0.2 * h.min()):  # on, outside, inside (nearer this face than any other)
                    d, normal = tools.signed_distance(face + s * out, pose)
                    np.testing.assert_allclose(d, s, atol=1e-13)
                    if s != 0.0:
                        np.testing.assert_allclose(normal, np.broadcast_to(out, normal.shape), atol=1e-12)
        # outside, off the faces (edges and corners too): the normal is the distance's gradient
        points = centre + rng.normal(size=(50, 3)) * 0.04
        d, normal = tools.signed_distance(points, pose)
        eps = 1e-7
        grad = np.column_stack([(tools.signed_distance(points + eps * e, pose)[0]
                                 - tools.signed_distance(points - eps * e, pose)[0]) / (2 * eps) for e in np.eye(3)])
        outside = d > 1e-5
        np.testing.assert_allclose(grad[outside], normal[outside], atol=1e-6)


def _slab_model(tools=(), supports=(), gravity=GRAVITY, E=5e3, fixed=None):
    return hg.Model(SLAB, M.NeoHookean(E=E, nu=0.45), density=DENSITY, gravity=gravity, damping=DAMPING,
                    supports=supports, tools=tools, fixed=fixed)


def _solver(model, integrator, **kwargs):
    if integrator == "explicit":
        return hg.ExplicitSolver(model, **kwargs)
    kwargs = {"newton_tol": 1e-9, **kwargs}
    return (hg.ImplicitSolver if integrator == "implicit" else hg.QuasiNewtonSolver)(model, **kwargs)


def _settle(model, integrator, steps=40, dt=0.05, pose=None, **kwargs):
    solver = _solver(model, integrator, **kwargs)
    state, control = model.state(), model.control()
    if pose is not None:
        control.pose_tool(0, 0, *pose)
    for _ in range(steps):
        stats = solver.step(state, state, control, dt)
        assert not stats.diverged.any() and stats.converged.all(), stats.messages
    return state, stats


#: a paddle 100 x 60 x 4 mm (it reaches past the slab)
PADDLE = hg.Box((0.05, 0.03, 0.002))
#: a block 100 x 60 x 60 mm whose top face is the plane z = 0: a slab dropped on it from rest
#: moves 25 mm in Newton's first iterate (backward Euler's free fall over 0.05 s), and would
#: pass through a thinner tool (see heml_gym.tools on tunnelling)
BLOCK = hg.Box((0.05, 0.03, 0.03))
BLOCK_UNDER = ((0.03, 0.015, -0.03), None)


@pytest.mark.parametrize("integrator", ["quasi_newton", "implicit"])
def test_a_slab_resting_on_a_tool_rests_as_on_the_plane_and_the_tool_carries_its_weight(integrator):
    """A tool's flat face is the plane (here a stiff one): the same equilibrium, to within
    the penalty's penetration (a tool leaves it; the plane projects it away)."""
    on_paddle, stats = _settle(_slab_model(tools=[BLOCK]), integrator, pose=BLOCK_UNDER)
    on_plane, _ = _settle(_slab_model(supports=[hg.PlaneSupport(height=0.0)]), integrator, contact_stiffness=1e6)
    penetration = -on_paddle.x[0, :, 2].min()
    assert 0 <= penetration < 1e-5
    assert np.abs(on_paddle.x - on_plane.x).max() <= 2 * penetration + 1e-7  # m, the same equilibrium
    assert np.abs(on_paddle.x[0, :, 2] - SLAB.vertices[:, 2]).max() > 1e-5  # it sagged under its weight
    weight = DENSITY * 0.06 * 0.03 * 0.008 * 9.81
    force = stats.tool_force[0, 0]
    assert force[2] == pytest.approx(weight, rel=0.01)
    assert np.abs(force[:2]).max() < 0.01 * weight


@pytest.mark.parametrize("integrator", ["quasi_newton", "implicit"])
def test_a_slab_squeezed_by_a_paddle_pushes_back_with_its_uniaxial_stress(integrator):
    """Weightless, on the frictionless floor, pressed 0.2 % of its height by a flat
    paddle turned upside down: uniaxial stress, F = E A delta / H (linear tets represent a
    uniform strain exactly; at 0.2 % the Neo-Hookean law is linear to 0.3 %)."""
    E, H, delta = 5e3, 0.008, 0.008 * 0.002
    flipped = rotation(np.array([1.0, 0.0, 0.0]), np.pi)  # the paddle's -z face now faces up: any face works
    pose = ((0.03, 0.015, H - delta + 0.002), flipped)
    model = _slab_model(tools=[PADDLE], supports=[hg.PlaneSupport(height=0.0)], gravity=(0.0, 0.0, 0.0), E=E)
    # the floor as stiff as the tool: the slab cannot sink into it instead
    state, stats = _settle(model, integrator, steps=60, pose=pose, contact_stiffness=1e6)
    force = stats.tool_force[0, 0]
    assert -force[2] == pytest.approx(E * 0.06 * 0.03 * delta / H, rel=0.01)
    np.testing.assert_allclose(state.x[0, :, 2].max(), H - delta, atol=0.01 * delta)  # the top on the paddle


def test_both_solvers_find_the_same_equilibrium_under_a_capsule():
    """A bar (capsule) lowered across the slab on the floor, 1 mm into it over 10 steps,
    then held: quasi-Newton and Newton agree (the slab's end x = 0 fixed: on a frictionless
    floor under a frictionless bar it would otherwise slide off)."""
    bar = hg.Capsule(0.004, 0.03)
    along_y = rotation(np.array([1.0, 0.0, 0.0]), np.pi / 2)  # its axis along y
    results = []
    for integrator in ("quasi_newton", "implicit"):
        model = _slab_model(tools=[bar], supports=[hg.PlaneSupport(height=0.0)],
                            fixed=np.flatnonzero(SLAB.vertices[:, 0] == 0.0))
        # the floor as stiff as the tool (a soft floor, projected after each step, and the bar
        # take turns at the vertices squeezed between them: the solvers then differ)
        solver = _solver(model, integrator, newton_tol=1e-6, contact_stiffness=1e6)
        state, control = model.state(), model.control()
        for k in range(40):
            depth = 0.001 * min(k + 1, 10) / 10
            control.pose_tool(0, 0, (0.03, 0.015, 0.008 + 0.004 - depth), along_y)
            stats = solver.step(state, state, control, 0.05)
            assert not stats.diverged.any() and stats.converged.all(), stats.messages
        results.append((state, stats))
    (qn, qn_stats), (nt, nt_stats) = results
    assert np.abs(qn.x - nt.x).max() < 1e-5  # m: 1 % of the press
    assert qn_stats.tool_force[0, 0, 2] < -0.1  # N: it presses down
    np.testing.assert_allclose(qn_stats.tool_force, nt_stats.tool_force, rtol=0.01, atol=1e-3)


def test_a_model_without_tools_reports_no_tool_force_and_an_unposed_tool_touches_nothing():
    _, stats = _settle(_slab_model(supports=[hg.PlaneSupport(height=0.0)]), "quasi_newton", steps=2)
    assert stats.tool_force is None
    _, stats = _settle(_slab_model(tools=[PADDLE], supports=[hg.PlaneSupport(height=0.0)]), "quasi_newton", steps=2)
    np.testing.assert_array_equal(stats.tool_force, 0.0)


def test_a_solver_that_does_not_step_tools_refuses_them_in_one_line():
    class NoTools(hg.solvers.base.Solver):
        pass

    with pytest.raises(ValueError, match=r"^tools: NoTools does not step rigid tools yet") as caught:
        NoTools(_slab_model(tools=[PADDLE]))
    assert "\n" not in str(caught.value)


def test_the_explicit_solver_rests_a_slab_on_a_tool_as_on_the_plane_and_reports_its_weight():
    """Explicit sub-steps put a vertex inside a tool back on its surface, as they do a
    support: the slab rests on the block's top face exactly, and the block carries its weight."""
    state, stats = _settle(_slab_model(tools=[BLOCK]), "explicit", pose=BLOCK_UNDER)
    weight = DENSITY * 0.06 * 0.03 * 0.008 * 9.81
    assert state.x[0, :, 2].min() > -1e-12  # on the face, not in it
    assert stats.tool_force[0, 0, 2] == pytest.approx(weight, rel=0.01)
    assert np.abs(stats.tool_force[0, 0, :2]).max() < 0.01 * weight


def test_every_solver_finds_the_same_equilibrium_on_a_tool():
    """A cantilever (the slab fixed at x = 0, no floor) sagging under gravity onto a paddle
    under its free end that holds it 2 mm above where it rests: the static solver's
    equilibrium is where backward Euler (Newton's and L-BFGS's) comes to rest, and the
    paddle carries the same share of the weight."""
    bar = hg.Box((0.01, 0.02, 0.01))  # under the last two columns of vertices (x 50 and 60 mm)
    pose = ((0.055, 0.015, -0.008), None)  # its top 2 mm above the slab's underside at rest (and 18 mm above its bottom)
    fixed = np.flatnonzero(SLAB.vertices[:, 0] == 0.0)
    model = _slab_model(tools=[bar], fixed=fixed)
    state, control = model.state(), model.control()
    control.pose_tool(0, 0, *pose)
    stats = hg.StaticSolver(model, load_steps=4, tol=1e-9).solve(state, control)
    assert stats.converged.all(), stats.messages
    weight = DENSITY * 0.06 * 0.03 * 0.008 * 9.81
    assert 0.05 * weight < stats.tool_force[0, 0, 2] < weight  # it carries part of the weight
    for integrator in ("quasi_newton", "implicit"):
        rest, rest_stats = _settle(_slab_model(tools=[bar], fixed=fixed), integrator, steps=120, pose=pose)
        assert np.abs(rest.x - state.x).max() < 1e-5, integrator  # m
        np.testing.assert_allclose(rest_stats.tool_force, stats.tool_force, rtol=0.01, atol=1e-4 * weight)
    # explicit sub-steps to rest (damped at 2 /s: 10 s), the paddle's face exact where the penalty lets 2 um in
    rest, rest_stats = _settle(_slab_model(tools=[bar], fixed=fixed), "explicit", steps=200, pose=pose)
    assert np.abs(rest.x - state.x).max() < 2e-5  # m
    np.testing.assert_allclose(rest_stats.tool_force, stats.tool_force, rtol=0.01, atol=1e-4 * weight)


@pytest.mark.parametrize("call, message", [
    (lambda: hg.Capsule(-1.0, 0.01), r"radius must be a positive number"),
    (lambda: hg.Box((0.01, 0.01)), r"half_extents must be three positive lengths"),
    (lambda: _slab_model(tools=[PADDLE]).control().pose_tool(0, 1, (0, 0, 0)), r"tool must be in \[0, 1\)"),
    (lambda: _slab_model(tools=[PADDLE]).control().pose_tool(0, 0, (0, 0, 0), np.diag([1.0, 1.0, -1.0])),
     r"rotation must be a \(3, 3\) rotation matrix"),
])
def test_bad_tools_and_poses_are_one_line_naming_the_argument(call, message):
    with pytest.raises(ValueError, match=message):
        call()


@pytest.mark.parametrize("integrator", ["quasi_newton", "implicit"])
def test_the_tools_impulse_is_the_change_of_the_tissues_momentum(integrator):
    """A free slab (nothing fixed, no floor, no damping) lifted by a paddle that speeds up:
    each step, sum m dv / dt = M g + the paddle's reported force (backward Euler's momentum
    balance: the elastic forces sum to zero)."""
    model = hg.Model(SLAB, M.NeoHookean(E=5e3, nu=0.45), density=DENSITY, gravity=GRAVITY, damping=0.0,
                     tools=[BLOCK])
    solver = _solver(model, integrator, newton_tol=1e-8)
    state, control = model.state(), model.control()
    weight = model.mass.sum() * np.asarray(GRAVITY)
    dt, z = 0.05, -0.03
    for k in range(30):
        z += 0.0005 * max(0, k - 10) * dt / 0.05  # still, then faster and faster up
        control.pose_tool(0, 0, (0.03, 0.015, z))
        v0 = state.v[0].copy()
        stats = solver.step(state, state, control, dt)
        assert stats.converged.all(), stats.messages
        rate = (model.mass[:, None] * (state.v[0] - v0)).sum(axis=0) / dt
        np.testing.assert_allclose(rate, weight + stats.tool_force[0, 0], atol=1e-6 * np.linalg.norm(weight))
    assert state.x[0, :, 2].min() > 0.004  # it was lifted


@pytest.mark.parametrize("speed", [0.01, 0.03])
def test_a_paddle_driven_into_a_slab_below_its_speed_limit_lets_no_vertex_through(speed):
    """A 4 mm paddle driven down at ``speed`` (m/s) onto a slab on a stiff floor, in 0.05 s
    steps: no vertex passes its middle plane, as long as it moves less than its half
    thickness in a step (here 40 mm/s; heml_gym.tools states the limit)."""
    model = _slab_model(tools=[PADDLE], supports=[hg.PlaneSupport(height=0.0)])
    solver = _solver(model, "quasi_newton", newton_tol=1e-4, contact_stiffness=1e6)
    state, control = model.state(), model.control()
    top = 0.010
    for _ in range(40):
        top = max(top - speed * 0.05, 0.004)  # down to half the slab's height, then held
        control.pose_tool(0, 0, (0.03, 0.015, top + 0.002))
        stats = solver.step(state, state, control, 0.05)
        assert not stats.diverged.any()
        under = (np.abs(state.x[0, :, 0] - 0.03) < 0.05) & (np.abs(state.x[0, :, 1] - 0.015) < 0.03)
        assert np.all(state.x[0, under, 2] <= top + 0.002 + 1e-9)  # none above the paddle's middle
    assert -stats.tool_force[0, 0, 2] > 0.1  # N: it squeezes the slab


@pytest.mark.parametrize("integrator", ["quasi_newton", "implicit"])
def test_tools_thrown_about_never_give_a_nan(integrator):
    """Seeded streams of a paddle and a probe posed anywhere (through the tissue, into the
    floor, at any turn) each step: every step's state and tool forces are finite, or the
    world is reported diverged with its state kept."""
    tools = [PADDLE, hg.Capsule(0.004, 0.02)]
    for seed in range(3):
        rng = np.random.default_rng(seed)
        model = _slab_model(tools=tools, supports=[hg.PlaneSupport(height=0.0)],
                            fixed=np.flatnonzero(SLAB.vertices[:, 0] == 0.0))
        solver = _solver(model, integrator, newton_tol=1e-3)
        state, control = model.state(), model.control()
        for _ in range(12):
            for t in range(2):
                axis = rng.normal(size=3)
                control.pose_tool(0, t, rng.uniform((-0.02, -0.02, -0.01), (0.08, 0.05, 0.03)),
                                  rotation(axis / np.linalg.norm(axis), rng.uniform(0, np.pi)))
            before = state.x.copy()
            stats = solver.step(state, state, control, 0.05)
            assert np.isfinite(state.x).all() and np.isfinite(state.v).all()
            if stats.diverged[0]:
                np.testing.assert_array_equal(state.x, before)
                assert stats.messages[0]
                np.testing.assert_array_equal(stats.tool_force, 0.0)
            else:
                assert np.isfinite(stats.tool_force).all()


@pytest.mark.parametrize("tool, turn", [(hg.Capsule(0.004, 0.03), rotation(np.array([1.0, 0.0, 0.0]), np.pi / 2)),
                                        (hg.Box((0.012, 0.02, 0.002)), rotation(np.array([0.0, 1.0, 0.0]), 0.3))])
def test_the_work_a_tool_does_pressing_slowly_is_the_energy_the_tissue_stores(tool, turn):
    """Energy: a bar (capsule) and a tilted paddle pressed 1.5 mm into a weightless slab
    clamped at its base, through static equilibria: the work the tool does on the tissue
    (its reported push times its displacement, summed by the trapezoid rule) equals the
    rise of the potential the tissue stores (elastic energy plus the contact penalty's),
    as it must in a conservative system; pulling back gives it all back."""
    mesh = hg.box_mesh((0.06, 0.03, 0.008), (12, 6, 4), origin=(0.0, 0.0, 0.0))
    model = hg.Model(mesh, M.NeoHookean(E=5e3, nu=0.45), density=DENSITY, gravity=(0.0, 0.0, 0.0), damping=0.0,
                     tools=[tool], fixed=np.flatnonzero(mesh.vertices[:, 2] == 0.0))
    solver = hg.StaticSolver(model, tol=1e-10)
    state, control = model.state(), model.control()
    # the tool's lowest point on the slab's top (at x = 30.5 mm: off the vertex columns)
    lowest = -np.abs(turn @ np.asarray(getattr(tool, "half_extents", (0.0, 0.0, 0.0)))).sum() \
        if isinstance(tool, hg.Box) else -tool.radius
    centre = np.array([0.0305, 0.015, 0.008 - lowest])
    free = np.ones(model.n_vertices, dtype=bool)
    free[model.fixed] = False

    def stored(x):
        pose = control.tool_pose[0]
        return model.fields[0].energy(x) + model.tools.penalty(x, pose, solver.tool_penalty_stiffness()[0], free).energy

    depths = np.concatenate([np.linspace(0.0, 0.0015, 21), np.linspace(0.0015, 0.0, 21)[1:]])
    work, force_before, energy = 0.0, np.zeros(3), []
    for k, depth in enumerate(depths):
        control.pose_tool(0, 0, centre - (0.0, 0.0, depth), turn)
        stats = solver.solve(state, control)
        assert stats.converged.all(), stats.messages
        force = stats.tool_force[0, 0]
        if k:
            work += 0.5 * (force + force_before) @ np.array([0.0, 0.0, depths[k - 1] - depth])
        force_before = force
        energy.append(stored(state.x[0]))
        if k == 20:  # at the bottom
            assert energy[-1] > 1e-5  # J: it did press
            assert work == pytest.approx(energy[-1] - energy[0], rel=1e-3)
    assert work == pytest.approx(0.0, abs=1e-3 * max(energy))  # J: back where it started, all of it given back
    assert energy[-1] == pytest.approx(energy[0], abs=1e-9 * max(energy))
