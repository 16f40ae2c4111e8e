"""The NumPy sub-step for any force field (heml_gym.solvers.substep.FieldSubstep) against
the quasi-Newton solver's HEML kernels (HemlSubstep): two implementations of one
backward Euler sub-step, which must agree on a HEML field."""

import numpy as np
import pytest

import heml_gym as hg
from heml_gym.contact import PlaneSupport
from heml_gym.kernel_data import world_law
from heml_gym.solvers.substep import FieldSubstep, HemlSubstep


def _pair(seed, h=0.05, fraction=0.5, damping=4.0):
    """The same sub-step of a clamped slab resting on (and partly pressed into) a plane,
    its far edge driven, both ways."""
    rng = np.random.default_rng(seed)
    mesh = hg.box_mesh((0.06, 0.04, 0.008), (6, 4, 1))
    X = mesh.vertices
    model = hg.Model(mesh, hg.materials.NeoHookean(E=5e3, nu=0.45), n_worlds=1, density=950.0,
                     fixed=X[:, 0] < 1e-9, damping=damping, supports=[PlaneSupport((0, 0, 1.0), 0.0)])
    n = mesh.n_vertices
    kinematic = X[:, 0] > 0.06 - 1e-9
    targets = np.where(kinematic[:, None], X + np.array([-0.003, 0.001, 0.005]), 0.0)
    x = X + rng.normal(scale=3e-4, size=X.shape)
    x[model.fixed] = X[model.fixed]
    v = rng.normal(scale=0.02, size=X.shape)
    field = model.fields[0]
    a = FieldSubstep(field, model.mass, model.damping.alpha, model.gravity, model.fixed, model.supports, 1000.0,
                     mesh.tets, h, kinematic, targets, fraction)
    b = HemlSubstep(field, model.heml_body(), world_law(model.heml_laws(), 0), model.supports.kernel_args(),
                    1000.0, h, kinematic, targets, fraction)
    return a, b, x, v, n, rng


@pytest.mark.parametrize("seed", range(4))
def test_field_substep_equals_the_heml_kernels(seed):
    """Start (moved held vertices, inertial target, the start's holding force), potential,
    gradient and Hessian at random configurations (some vertices below the support), and
    the end (projection onto the support, velocities, the trapezoidal reaction)."""
    a, b, x, v, n, rng = _pair(seed)
    xa, xb = x.copy(), x.copy()
    ra, rb = np.zeros((n, 3)), np.zeros((n, 3))
    a.begin(xa, v, ra)
    b.begin(xb, v, rb)
    assert np.array_equal(a.held, b.held) and a.c == pytest.approx(b.c, rel=1e-14)
    assert np.allclose(xa, xb, rtol=0, atol=1e-15) and np.allclose(a.x_hat, b.x_hat, rtol=0, atol=1e-15)
    scale = np.abs(rb).max()
    assert scale > 0 and np.allclose(ra, rb, rtol=0, atol=1e-10 * scale)
    for _ in range(3):
        y = xa + rng.normal(scale=5e-4, size=xa.shape)
        y[a.held] = xa[a.held]
        assert (y[:, 2] < 0).sum() > 3  # some free vertices inside the support
        assert a.potential(y) == pytest.approx(b.potential(y), rel=1e-12)
        ga, gb = a.gradient(y), b.gradient(y)
        assert np.abs(ga - gb).max() <= 1e-10 * np.abs(gb).max()
        for project in (False, True):
            ha, hb = a.hessian(y, project).toarray(), b.hessian(y, project).toarray()
            assert np.abs(ha - hb).max() <= 1e-10 * np.abs(hb).max()
    ya, yb = y.copy(), y.copy()
    va, vb = v.copy(), v.copy()
    reaction_a, reaction_b = np.zeros((n, 3)), np.zeros((n, 3))
    ends_a = a.finish(ya, va, reaction_a, ra)
    ends_b = b.finish(yb, vb, reaction_b, rb)
    for key in ("inside", "projected", "stopped"):
        assert np.array_equal(ends_a[key], ends_b[key]), key
    assert ends_a["projected"].any() and ends_a["stopped"].any()
    assert np.allclose(ya, yb, rtol=0, atol=1e-15) and np.allclose(va, vb, rtol=0, atol=1e-12)
    scale = np.abs(reaction_b).max()
    assert scale > 0 and np.allclose(reaction_a, reaction_b, rtol=0, atol=1e-10 * scale)
    assert np.allclose(ra, rb, rtol=0, atol=1e-10 * scale)


def test_field_substep_gradient_and_hessian_are_the_potentials_derivatives():
    """Central differences of FieldSubstep's potential on quadratic tets (the field the
    HEML kernels cannot run): gradient, and the Hessian's product with a direction."""
    mesh = hg.QuadraticTetMesh.from_linear(hg.box_mesh((0.06, 0.04, 0.008), (3, 2, 1)))
    X = mesh.vertices
    model = hg.Model(mesh, hg.materials.NeoHookean(E=5e3, nu=0.45), n_worlds=1, density=950.0,
                     fixed=X[:, 0] < 1e-9, damping=4.0, supports=[PlaneSupport((0, 0, 1.0), 0.0)],
                     field="quadratic")
    rng = np.random.default_rng(0)
    kinematic = X[:, 0] > 0.06 - 1e-9
    targets = np.where(kinematic[:, None], X + 0.003, 0.0)
    step = FieldSubstep(model.fields[0], model.mass, model.damping.alpha, model.gravity, model.fixed, model.supports,
                        1000.0, mesh.tets, 0.05, kinematic, targets, 1.0)
    x = X + rng.normal(scale=3e-4, size=X.shape)
    step.begin(x, rng.normal(scale=0.02, size=X.shape))
    y = x + rng.normal(scale=3e-4, size=X.shape)
    y[step.held] = x[step.held]
    g = step.gradient(y)
    d = rng.normal(size=y.shape)
    d[step.held] = 0.0
    eps = 1e-7
    fd = (step.potential(y + eps * d) - step.potential(y - eps * d)) / (2 * eps)
    assert float((g * d).sum()) == pytest.approx(fd, rel=1e-6)
    hd = (step.hessian(y) @ d.reshape(-1)).reshape(-1, 3)
    fd_h = (step.gradient(y + eps * d) - step.gradient(y - eps * d)) / (2 * eps)
    free = ~step.held
    assert np.abs(hd[free] - fd_h[free]).max() <= 1e-5 * np.abs(hd[free]).max()
