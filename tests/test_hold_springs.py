"""Vertices held by springs (``Control.hold_stiffness``): a vertex the jaws hold in part.

Checked against independent computations: a stiffness of 0 is today's exact hold bit for
bit; the reaction the solver reports on a spring-held vertex is the spring's force
computed from the states and anchors it left (the trapezoid of the step's start and end);
at equilibrium each spring-held vertex's spring balances the tissue's forces on it; a
stiff spring tends to the exact hold; solvers that cannot step springs refuse them."""

from __future__ import annotations

import numpy as np
import pytest

import heml_gym as hg
from heml_gym.contact import PlaneSupport

MESH = hg.box_mesh((0.06, 0.06, 0.008), (6, 6, 1))
X = MESH.vertices
CLAMPED = X[:, 0] < 1e-9
GRIP = np.flatnonzero(X[:, 0] > 0.06 - 1e-9)
#: the gripped edge's two end vertices are held in part (by springs)
ENDS = (X[GRIP, 1] < 1e-9) | (X[GRIP, 1] > 0.06 - 1e-9)


def _model(n_worlds=1):
    return hg.Model(MESH, hg.materials.NeoHookean(E=5e3, nu=0.45), n_worlds=n_worlds, density=950.0,
                    fixed=CLAMPED, damping=5.0, supports=[PlaneSupport((0, 0, 1.0), 0.0)])


def _pull(model, solver, stiffness, steps=6, on_step=None):
    """Pull the gripped edge up and back ``steps`` control steps (0.1 s each), its end
    vertices held with ``stiffness`` (N/m; None: attach without the argument)."""
    state, control = model.state(), model.control()
    k = None if stiffness is None else np.where(ENDS, stiffness, 0.0)
    control.attach(0, GRIP, X, stiffness=k)
    stats = None
    for t in range(steps):
        control.targets[0, GRIP] = X[GRIP] + np.array([-0.002, 0.0, 0.004]) * (t + 1)
        before = state.x[0].copy(), control.anchors[0].copy()
        stats = solver.step(state, state, control, 0.1)
        assert stats.converged.all(), stats.messages
        if on_step is not None:
            on_step(before, state.x[0].copy(), control.anchors[0].copy(), stats)
    return state, control, stats


def test_stiffness_zero_is_the_exact_hold_bit_for_bit():
    model = _model()
    exact, _, stats_exact = _pull(model, hg.QuasiNewtonSolver(model), None)
    model = _model()
    zero, control, stats_zero = _pull(model, hg.QuasiNewtonSolver(model), 0.0)
    assert np.array_equal(exact.x, zero.x) and np.array_equal(exact.v, zero.v)
    assert np.array_equal(stats_exact.reaction, stats_zero.reaction)
    assert not control.spring_held().any() and control.exactly_held()[0, GRIP].all()


def test_a_spring_held_vertex_reports_its_springs_force():
    """One sub-step per step: the step-mean reaction on a spring-held vertex is the mean of
    ``k (anchor - x)`` at the step's start and end (the anchors and positions the solver
    left, read from outside); the anchors follow the targets; the spring-held vertices
    lag behind them, by less than the exact hold's pull would stretch a soft spring."""
    k = 50.0
    model = _model()
    ends = GRIP[ENDS]
    checked = []

    def check(before, x, anchors, stats):
        start = k * (before[1][ends] - before[0][ends])
        end = k * (anchors[ends] - x[ends])
        np.testing.assert_allclose(stats.reaction[0, ends], 0.5 * (start + end), rtol=0, atol=1e-12)
        checked.append(float(np.abs(end).max()))

    state, control, _ = _pull(model, hg.QuasiNewtonSolver(model), k, on_step=check)
    np.testing.assert_allclose(control.anchors[0, ends], control.targets[0, ends], rtol=0, atol=1e-15)
    assert max(checked) > 1e-3  # (the springs do pull: a force of a millinewton and more)
    assert np.linalg.norm(control.anchors[0, ends] - state.x[0, ends], axis=1).min() > 1e-5


def test_at_rest_each_spring_balances_the_tissue_on_its_vertex():
    """Held still long enough to come to rest, a spring-held vertex feels no inertia: the
    spring's pull ``k (anchor - x)`` plus the elastic force of the tissue and its weight on
    that vertex is zero, to the solver's tolerance (the elastic force from the model's
    own force field, outside the solver)."""
    k = 80.0
    model = _model()
    solver = hg.QuasiNewtonSolver(model)
    state, control, _ = _pull(model, solver, k)
    for _ in range(60):  # hold still: the damping brings the tissue to rest
        stats = solver.step(state, state, control, 0.1)
    ends = GRIP[ENDS]
    elastic = model.fields[0].forces(state.x[0])
    weight = model.mass[:, None] * model.gravity
    spring = k * (control.anchors[0] - state.x[0])
    balance = (spring + elastic + weight)[ends]
    assert np.abs(balance).max() < 3 * stats.tolerance[0]
    assert np.abs(spring[ends]).max() > 10 * stats.tolerance[0]  # (not a trivial balance)


def test_a_stiff_spring_tends_to_the_exact_hold():
    model = _model()
    exact, _, stats_exact = _pull(model, hg.QuasiNewtonSolver(model), None)
    force = -stats_exact.reaction[0, GRIP].sum(axis=0)
    gaps = []
    for k in (1e2, 1e4, 1e6):
        model = _model()
        state, _, stats = _pull(model, hg.QuasiNewtonSolver(model), k)
        gaps.append(np.abs(state.x - exact.x).max())
        if k == 1e6:
            np.testing.assert_allclose(-stats.reaction[0, GRIP].sum(axis=0), force, rtol=1e-3, atol=1e-5)
    assert gaps[0] > gaps[1] > gaps[2] and gaps[2] < 5e-5  # m


def test_newton_and_quasi_newton_take_the_same_spring_held_step():
    """The implicit solver (Newton on the same backward Euler potential) and the
    quasi-Newton one step the spring-held pull to the same positions, within their
    tolerances; the implicit solver reports the springs' pull at the step's end."""
    model = _model()
    qn, _, stats_qn = _pull(model, hg.QuasiNewtonSolver(model, newton_tol=1e-8, max_iter=1000,
                                                         contact_stiffness=1000.0), 50.0)
    model = _model()
    newton, control, stats_newton = _pull(model, hg.ImplicitSolver(model, newton_tol=1e-8, contact_stiffness=1000.0),
                                          50.0)
    assert np.abs(qn.x - newton.x).max() < 1e-7  # m
    ends = GRIP[ENDS]
    np.testing.assert_allclose(stats_newton.reaction[0, ends], 50.0 * (control.targets[0, ends] - newton.x[0, ends]),
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(control.anchors[0, ends], control.targets[0, ends], atol=1e-15)


def test_a_static_spring_held_slab_balances_at_every_vertex():
    """Statics (no supports, no inertia): each spring-held vertex's spring balances the
    tissue's forces and its weight there; the reaction reported is that spring's pull."""
    k = 80.0
    model = hg.Model(MESH, hg.materials.NeoHookean(E=5e3, nu=0.45), n_worlds=1, density=950.0, fixed=CLAMPED)
    solver = hg.StaticSolver(model, load_steps=2)
    state, control = model.state(), model.control()
    control.attach(0, GRIP, X, stiffness=np.where(ENDS, k, 0.0))
    control.drive(0, GRIP, X[GRIP] + np.array([-0.004, 0.0, 0.01]))
    stats = solver.solve(state, control)
    assert stats.converged.all()
    ends = GRIP[ENDS]
    x = state.x[0]
    spring = k * (control.targets[0, ends] - x[ends])
    balance = spring + model.fields[0].forces(x)[ends] + model.mass[ends, None] * model.gravity
    assert np.abs(balance).max() < 3 * stats.tolerance[0] and np.abs(spring).max() > 1e-3
    np.testing.assert_allclose(stats.reaction[0, ends], spring, rtol=0, atol=1e-12)


def test_explicit_implicit_and_static_springs_rest_at_one_equilibrium():
    """Held still after a pull, with damping, the explicit solver (its sub-steps shortened
    for the springs: a stiff spring on a light vertex would blow up at the tissue's own
    critical step) and the implicit one come to rest where the static solver puts the
    slab in equilibrium, spring-held ends included (no supports: statics has none)."""
    k = 2000.0
    targets = X[GRIP] + np.array([-0.004, 0.0, 0.01])

    def at_rest(make, seconds):
        model = hg.Model(MESH, hg.materials.NeoHookean(E=5e3, nu=0.45), n_worlds=1, density=950.0, fixed=CLAMPED,
                         damping=20.0)
        solver = make(model)
        state, control = model.state(), model.control()
        control.attach(0, GRIP, X, stiffness=np.where(ENDS, k, 0.0))
        control.drive(0, GRIP, targets)
        if isinstance(solver, hg.StaticSolver):
            stats = solver.solve(state, control)
        else:
            for _ in range(int(round(seconds / 0.05))):
                stats = solver.step(state, state, control, 0.05)
                assert not stats.diverged.any(), stats.messages
        return state.x[0], stats, solver, control

    static, *_ = at_rest(lambda m: hg.StaticSolver(m, load_steps=2), 0)
    implicit, *_ = at_rest(lambda m: hg.ImplicitSolver(m, newton_tol=1e-8), 3.0)
    explicit, stats, solver, control = at_rest(hg.ExplicitSolver, 3.0)
    assert np.abs(implicit - static).max() < 1e-6 and np.abs(explicit - static).max() < 1e-6  # m
    # the springs needed shorter sub-steps than the tissue alone
    assert solver.spring_critical_dt(control, control.spring_held()) < 0.5 * solver.model.critical_dt()
    assert stats.substeps > solver.substeps(0.05)


@pytest.mark.parametrize("stiffness", [-1.0, float("nan"), float("inf")])
def test_a_bad_stiffness_is_refused(stiffness):
    control = _model().control()
    with pytest.raises(ValueError, match="stiffness must be finite and >= 0"):
        control.attach(0, GRIP, X, stiffness=stiffness)
