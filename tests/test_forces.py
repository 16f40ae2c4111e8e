"""HEML against textbook F-based FEM, gradients, invariances and the laws' closed forms."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

import heml_gym as hg
from heml_gym import materials as M

from deformations import perturbed_box, random_deformation

E, NU = 20e3, 0.42
LAWS = M.ALL_MATERIALS
JACOBIANS = [0.3, 0.6, 1.0, 1.7, 3.0]


def rel_diff(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(b)))


def signed_jacobians(mesh, x):
    return hg.mesh.signed_volumes(x, mesh.tets) / mesh.volumes


@pytest.mark.parametrize("law", LAWS, ids=lambda c: c.__name__)
@pytest.mark.parametrize("jacobian", JACOBIANS)
@pytest.mark.parametrize("mesh_kind", ["regular", "irregular"])
def test_heml_equals_textbook_fem(law, jacobian, mesh_kind, small_box, irregular_box):
    mesh = small_box if mesh_kind == "regular" else irregular_box
    mat = law(E=E, nu=NU)
    x = random_deformation(mesh, seed=int(jacobian * 10), jacobian=jacobian)
    j = signed_jacobians(mesh, x)
    assert j.min() > 0.5 * jacobian and j.max() < 2.0 * jacobian  # the state we meant to test
    heml, fem = hg.HemlForce(mesh, mat), hg.FemForce(mesh, mat)
    f_heml, f_fem = heml.forces(x), fem.forces(x)
    assert np.all(np.isfinite(f_fem))
    # to rounding: at most 2.6e-15 measured over these cases, compiled for AVX2 and for SSE2
    assert rel_diff(f_heml, f_fem) <= 1e-13
    w_heml, w_fem = heml.energy(x), fem.energy(x)
    assert abs(w_heml - w_fem) <= 1e-13 * abs(w_fem)


def all_fields(mesh):
    mats = [law(E=E, nu=NU) for law in LAWS]
    fields = [hg.HemlForce(mesh, m) for m in mats] + [hg.FemForce(mesh, m) for m in mats]
    return fields + [hg.MassSpringForce(mesh, M.NeoHookean(E=E, nu=NU))]


def field_id(f):
    return f"{f.name}-{type(f.material).__name__}"


ONE_CELL = hg.box_mesh((0.02, 0.02, 0.02), 1)
FIELDS = all_fields(ONE_CELL)


@pytest.mark.parametrize("field", FIELDS, ids=field_id)
def test_forces_are_minus_energy_gradient(field):
    x0 = random_deformation(ONE_CELL, seed=7, jacobian=0.8, noise=0.05)
    h = 1e-6 * 0.02
    grad = np.zeros_like(x0)
    for i in range(x0.shape[0]):
        for d in range(3):
            xp, xm = x0.copy(), x0.copy()
            xp[i, d] += h
            xm[i, d] -= h
            grad[i, d] = (field.energy(xp) - field.energy(xm)) / (2 * h)
    assert rel_diff(field.forces(x0), -grad) <= 1e-6


@pytest.mark.parametrize("field", all_fields(perturbed_box(seed=1)), ids=field_id)
def test_rest_net_force_torque_and_rigid_invariance(field):
    mesh = field.mesh
    scale = E * np.ptp(mesh.vertices, axis=0).max() ** 2  # a force in newtons
    rest = field.forces(mesh.vertices)
    assert np.abs(rest).max() <= 1e-12 * scale
    assert abs(field.energy(mesh.vertices)) <= 1e-12 * scale * 0.1

    x = random_deformation(mesh, seed=11, jacobian=1.3, noise=0.04)
    f = field.forces(x)
    magnitude = np.abs(f).sum()
    assert np.abs(f.sum(axis=0)).max() <= 1e-12 * magnitude
    arm = np.abs(x).max()
    assert np.abs(np.cross(x, f).sum(axis=0)).max() <= 1e-12 * magnitude * arm

    rot = Rotation.from_rotvec([0.3, -1.2, 2.0]).as_matrix()
    moved = x @ rot.T + np.array([1.5, -0.3, 0.7])
    w = field.energy(x)
    assert abs(field.energy(moved) - w) <= 1e-10 * abs(w)
    # forces rotate with the body
    assert rel_diff(field.forces(moved), f @ rot.T) <= 1e-9


# ----------------------------------------------------------------- closed-form laws
# Each law's energy written directly in the principal stretches (from its definition);
# stresses P_i = dPsi/d lambda_i by complex-step differentiation: an independent truth.
def psi_principal(mat, l1, l2, l3):
    i1 = l1 * l1 + l2 * l2 + l3 * l3
    i2 = l1 * l1 * l2 * l2 + l2 * l2 * l3 * l3 + l1 * l1 * l3 * l3
    j = l1 * l2 * l3
    if isinstance(mat, M.NeoHookean):
        return mat.mu / 2 * (i1 - 3) - mat.mu * np.log(j) + mat.lam / 2 * np.log(j) ** 2
    if isinstance(mat, M.StVenantKirchhoff):
        e = [(l * l - 1) / 2 for l in (l1, l2, l3)]
        return mat.mu * sum(ei * ei for ei in e) + mat.lam / 2 * sum(e) ** 2
    if isinstance(mat, M.MooneyRivlin):
        return (mat.c10 * (j ** (-2 / 3) * i1 - 3) + mat.c01 * (j ** (-4 / 3) * i2 - 3)
                + mat.kappa / 2 * (j - 1) ** 2)
    if isinstance(mat, M.Demiray):
        return (mat.a / (2 * mat.b) * (np.exp(mat.b * (j ** (-2 / 3) * i1 - 3)) - 1)
                + mat.kappa / 2 * (j - 1) ** 2)
    if isinstance(mat, M.StableNeoHookean):
        return (mat.mu / 2 * (i1 - 3) + mat.lam / 2 * (j - mat.alpha) ** 2
                - mat.mu / 2 * np.log(i1 + 1) + mat.rest_offset)
    raise TypeError(mat)


def principal_stress(mat, stretches, i):
    h = 1e-30
    z = [complex(s) for s in stretches]
    z[i] += 1j * h
    return psi_principal(mat, *z).imag / h


def uniaxial_closed_form(mat, stretch):
    """Nominal stress (Pa) and lateral stretch under uniaxial stretch, lateral faces free."""
    def lateral(t):
        return principal_stress(mat, (stretch, t, t), 1)

    t = brentq(lateral, 0.05, 3.0, xtol=1e-15, rtol=1e-15)
    return principal_stress(mat, (stretch, t, t), 0), t


@pytest.mark.parametrize("law", LAWS, ids=lambda c: c.__name__)
@pytest.mark.parametrize("stretch", [0.5, 0.8, 1.25, 2.0])
def test_uniaxial_stretch_matches_closed_form(law, stretch):
    size = np.array([0.04, 0.03, 0.02])
    mesh = hg.box_mesh(size, (2, 2, 2))
    # nu = 0.3: at nu = 0.42 StVK has no uniaxial state at stretch 2 (the sides collapse)
    mat = law(E=E, nu=0.3)
    nominal, t = uniaxial_closed_form(mat, stretch)
    x = mesh.vertices * np.array([stretch, t, t])
    f = hg.HemlForce(mesh, mat).forces(x)
    end = np.isclose(mesh.vertices[:, 0], size[0])
    reaction = -f[end, 0].sum()  # external force holding the end face
    assert abs(reaction / (size[1] * size[2]) - nominal) <= 1e-6 * abs(nominal)
    # lateral faces are traction free: the net lateral force on each is zero
    for axis in (1, 2):
        side = np.isclose(mesh.vertices[:, axis], size[axis])
        assert abs(f[side, axis].sum()) <= 1e-9 * abs(reaction)


@pytest.mark.parametrize("law", LAWS, ids=lambda c: c.__name__)
def test_small_strain_recovers_young_and_poisson(law):
    mat = law(E=E, nu=NU)
    eps = 1e-6
    nominal, t = uniaxial_closed_form(mat, 1 + eps)
    assert nominal / eps == pytest.approx(E, rel=1e-4)
    assert -(t - 1) / eps == pytest.approx(NU, rel=1e-4)
    assert mat.young_modulus == pytest.approx(E, rel=1e-12)
    assert mat.poisson_ratio == pytest.approx(NU, rel=1e-12)


@pytest.mark.parametrize("law", LAWS, ids=lambda c: c.__name__)
def test_inverted_element_is_seen(law):
    mesh = hg.box_mesh((0.01, 0.01, 0.01), 1)
    x = mesh.vertices * np.array([1.0, 1.0, -0.5])  # every tet turned inside out
    for field in (hg.HemlForce(mesh, law(E=E, nu=NU)), hg.FemForce(mesh, law(E=E, nu=NU))):
        f, w = field.forces(x), field.energy(x)
        if law.defined_when_inverted:
            assert np.all(np.isfinite(f)) and np.isfinite(w)
            assert np.abs(f).max() > 0
        else:
            assert np.isnan(f).any() and w == np.inf


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(E=-1.0, nu=0.3), "Young"),
        (dict(E=0.0, nu=0.3), "Young"),
        (dict(E=1e3, nu=0.5), "Poisson"),
        (dict(E=1e3, nu=-1.0), "Poisson"),
        (dict(E=float("nan"), nu=0.3), "Young"),
        (dict(E=1e3), "missing"),
    ],
)
@pytest.mark.parametrize("law", LAWS, ids=lambda c: c.__name__)
def test_bad_young_parameters_raise(law, kwargs, match):
    with pytest.raises(ValueError, match=match):
        law(**kwargs)


@pytest.mark.parametrize(
    "law, kwargs",
    [
        (M.NeoHookean, dict(mu=-1.0, lam=1.0)),
        (M.NeoHookean, dict(mu=1.0, lam=-5.0)),
        (M.StVenantKirchhoff, dict(mu=0.0, lam=1.0)),
        (M.MooneyRivlin, dict(c10=-1.0, c01=1.0, kappa=1.0)),
        (M.MooneyRivlin, dict(c10=1.0, c01=1.0, kappa=-1.0)),
        (M.Demiray, dict(a=1.0, b=-2.0, kappa=1.0)),
        (M.StableNeoHookean, dict(mu=1.0, lam=-1.0)),
        (M.NeoHookean, dict(mu=1.0, lam=1.0, E=3.0, nu=0.2)),
    ],
)
def test_bad_native_parameters_raise(law, kwargs):
    with pytest.raises(ValueError):
        law(**kwargs)


def test_native_and_young_constructors_agree():
    a = M.NeoHookean(E=E, nu=NU)
    b = M.NeoHookean(mu=a.mu, lam=a.lam)
    np.testing.assert_array_equal(a.params, b.params)


def test_force_field_rejects_bad_positions(small_box):
    field = hg.HemlForce(small_box, M.NeoHookean(E=E, nu=NU))
    with pytest.raises(ValueError, match="shape"):
        field.forces(np.zeros((3, 3)))
    with pytest.raises(TypeError):
        hg.HemlForce(small_box, "neo-hookean")


@pytest.mark.parametrize("make", [
    lambda m: hg.HemlForce(m, M.MooneyRivlin(E=E, nu=NU)),
    lambda m: hg.FemForce(m, M.NeoHookean(E=E, nu=NU)),
    lambda m: hg.MassSpringForce(m, M.NeoHookean(E=E, nu=NU)),
    lambda m: hg.MassTensorForce(m, M.StVenantKirchhoff(E=E, nu=NU)),
], ids=["heml", "fem", "spring", "tensor"])
def test_parallel_kernels_match_serial(make, irregular_box):
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one Numba thread: the chunked kernels would run serially, compared with themselves")
    field = make(irregular_box)
    x = random_deformation(irregular_box, seed=5, jacobian=1.2)
    serial_f, serial_w = field.forces(x), field.energy(x)
    field.parallel_min_elements = 0  # force the chunked kernels
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
        threads = numba.get_num_threads()
        assert threads >= 2 and field.kernel_threads() == threads
        par_f, par_w = field.forces(x), field.energy(x)
    finally:
        numba.set_num_threads(old)
    assert rel_diff(par_f, serial_f) <= 1e-13
    assert par_w == pytest.approx(serial_w, rel=1e-13)
