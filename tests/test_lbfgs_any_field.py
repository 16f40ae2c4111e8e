"""L-BFGS backward Euler for any force field (``ImplicitSolver(method="lbfgs")``, what
``integrator="quasi_newton"`` builds for fields other than HEML): it reaches Newton's
solution of the same incremental potential, and the envs step quadratic tets with it."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import scipy.sparse as sp

import heml_gym as hg
import heml_gym.envs  # noqa: F401  (registers the envs)
from heml_gym import QuadraticFemForce, QuadraticTetMesh
from heml_gym import materials as M
from heml_gym.envs.spec import SpecError
from heml_gym.solvers import SolverChoiceError, make_solver
from heml_gym.solvers.newton import minimize_lbfgs

from env_checks import assert_random_steps_stay_finite

LINEAR = hg.box_mesh((0.06, 0.03, 0.008), (4, 2, 1))
QUADRATIC = QuadraticTetMesh.from_linear(LINEAR)
STIFFNESS = [2e3, 3.5e3, 5e3]  # Pa, one per world
DAMPING, DENSITY, GRAVITY = 5.0, 950.0, (0.0, 0.0, -9.81)


def test_lbfgs_minimises_a_quadratic_potential_to_its_linear_solution():
    """On ``1/2 x.A x - b.x`` with some dofs held, the minimiser solves the free rows of
    ``A x = b`` (a sparse direct solve is the independent truth), from a preconditioner
    far from ``A^-1`` (its diagonal) in fewer iterations than dofs."""
    rng = np.random.default_rng(3)
    n = 60
    q = sp.random(n, n, density=0.1, random_state=rng) + sp.eye(n)
    a = (q @ q.T + sp.eye(n)).tocsr()
    b = rng.normal(size=n)
    free = rng.random(n) > 0.2
    x0 = rng.normal(size=n)
    exact = x0.copy()
    exact[free] = sp.linalg.spsolve(a[free][:, free].tocsc(), b[free] - a[free][:, ~free] @ x0[~free])
    inverse_diagonal = 1.0 / a.diagonal()[free]
    result = minimize_lbfgs(x0.reshape(-1, 3), lambda x: 0.5 * x.ravel() @ (a @ x.ravel()) - b @ x.ravel(),
                            lambda x: a @ x.ravel() - b, lambda r: inverse_diagonal * r, free, 1e-10, 500,
                            history=8)
    assert result.converged and result.iterations < free.sum()
    np.testing.assert_allclose(result.x.ravel(), exact, atol=1e-9)
    assert np.array_equal(result.x.ravel()[~free], x0[~free])  # held dofs stay


@pytest.mark.parametrize("field, supports", [("quadratic", ()), ("quadratic", (hg.PlaneSupport(height=-0.004),)),
                                             ("fem", (hg.PlaneSupport(height=-0.004),))])
def test_lbfgs_reaches_the_newton_solution_on_any_field(field, supports):
    """L-BFGS and Newton minimise the same incremental potential: solved tightly, their
    steps agree, for three worlds of different stiffness, some held vertices driven
    exactly and some by springs (the weighted jaws' partial hold), with a support the
    tissue is pressed into."""
    mesh = QUADRATIC if field == "quadratic" else LINEAR
    x_end = mesh.vertices[:, 0]
    fixed = np.isclose(x_end, 0.0)
    held = np.flatnonzero(np.isclose(x_end, 0.06))
    springs = held[mesh.vertices[held, 1] > 0.02]  # one row of the held edge by springs
    exact = np.setdiff1d(held, springs)
    rng = np.random.default_rng(7)
    path = np.cumsum(rng.uniform(-1, 1, (len(STIFFNESS), 5, 3)) * 0.001, axis=1)
    path[..., 2] -= 0.0008 * np.arange(1, 6)  # pressed down, into the support
    results = []
    for method in ("newton", "lbfgs"):
        materials = [M.NeoHookean(E=E, nu=0.45) for E in STIFFNESS]
        model = hg.Model(mesh, materials, field=QuadraticFemForce if field == "quadratic" else "fem",
                         density=DENSITY, gravity=GRAVITY, fixed=fixed, damping=DAMPING, supports=supports)
        solver = hg.ImplicitSolver(model, newton_tol=1e-8, max_newton=2000 if method == "lbfgs" else 50,
                                   contact_stiffness=1000.0, method=method)
        state, control = model.state(), model.control()
        for s in range(model.n_worlds):
            control.attach(s, exact, state.x[s])
            control.attach(s, springs, state.x[s], stiffness=50.0)
        xs, reactions = [], []
        for k in range(path.shape[1]):
            for s in range(model.n_worlds):
                control.drive(s, held, mesh.vertices[held] + path[s, k])
            stats = solver.step(state, state, control, 1 / 30)
            assert stats.converged.all() and not stats.diverged.any()
            xs.append(state.x.copy())
            reactions.append(stats.reaction[:, held].sum(axis=1))
        results.append((np.array(xs), np.array(reactions)))
    (x_newton, r_newton), (x_lbfgs, r_lbfgs) = results
    assert np.abs(x_newton - x_lbfgs).max() < 1e-7
    np.testing.assert_allclose(r_lbfgs, r_newton, rtol=1e-5, atol=1e-7)
    assert np.abs(x_newton[-1] - mesh.vertices).max() > 1e-3  # (it did move)
    if supports:  # (the support held the free vertices up)
        free = ~fixed
        free[held] = False
        assert -0.004 - 1e-4 < x_newton[-1][:, free, 2].min() < -0.004 + 1e-4


def test_quasi_newton_on_a_field_other_than_heml_is_lbfgs_by_the_newton_solver():
    model = hg.Model(field=QuadraticFemForce(QUADRATIC, M.NeoHookean(E=5e3, nu=0.45)), density=DENSITY)
    solver = make_solver(model, "quasi_newton", newton_tol=2e-3, hessian_scale=0.5)
    assert isinstance(solver, hg.ImplicitSolver)
    assert (solver.method, solver.max_newton, solver.newton_tol, solver.hessian_scale) == ("lbfgs", 200, 2e-3, 0.5)
    assert make_solver(model, "quasi_newton", max_iterations=30).max_newton == 30
    with pytest.raises(SolverChoiceError, match="^scheme"):
        make_solver(model, "quasi_newton", scheme="bdf2")
    with pytest.raises(ValueError, match="method must be one of"):
        hg.ImplicitSolver(model, method="bfgs")
    with pytest.raises(ValueError, match="history must be an integer"):
        hg.ImplicitSolver(model, method="lbfgs", history=0)


TISSUE = "heml_gym/TissueRetraction-v1"
QUASI_NEWTON = {"field": "quadratic", "integrator": "quasi_newton", "max_dt": 0.025}


def test_the_flap_on_quadratic_tets_by_lbfgs_follows_newton():
    """The scripted fold of the flap on 6 x 6 x 1 quadratic cells: the same actions
    replayed by L-BFGS and by Newton (both to the env's tolerance) hold the flap with
    the same force and expose the same target."""
    from heml_gym.envs import scripted

    runs = {}
    for integrator in ("implicit", "quasi_newton"):
        env = gym.make(TISSUE, cells=(6, 6, 1), physics={**QUASI_NEWTON, "integrator": integrator})
        if integrator == "implicit":
            policy = scripted.scripted_policy(env.unwrapped.task.scene.spec)
            policy.reset()
        obs, _ = env.reset(seed=2)
        forces, exposures, actions = [], [], runs.get("implicit", {}).get("actions", [])
        for k in range(40):
            action = policy(obs) if integrator == "implicit" else actions[k]
            if integrator == "implicit":
                actions.append(action)
            obs, _, terminated, truncated, info = env.step(action)
            assert info["solver_converged"]
            forces.append(info["grasp_force"])
            exposures.append(info["exposure"])
            if terminated or truncated:
                break
        runs[integrator] = {"actions": actions, "force": np.array(forces), "exposure": np.array(exposures)}
    newton, lbfgs = runs["implicit"], runs["quasi_newton"]
    assert len(newton["force"]) == len(lbfgs["force"]) and newton["force"].max() > 0.1
    # both stop within 3e-3 of the weight of the solution: far closer than the task's 5 % rule
    assert np.abs(lbfgs["force"] - newton["force"]).max() < 0.01 * newton["force"].max()
    assert np.abs(lbfgs["exposure"] - newton["exposure"]).max() < 0.02


def test_random_steps_on_quadratic_tets_by_lbfgs_stay_finite_and_converged():
    assert_random_steps_stay_finite(gym.make(TISSUE, cells=(6, 6, 1), physics=QUASI_NEWTON), 30, seed=1)


def test_bdf2_on_quadratic_tets_is_a_one_line_error():
    with pytest.raises(SpecError, match="scheme"):
        gym.make(TISSUE, physics={**QUASI_NEWTON, "scheme": "bdf2"})
