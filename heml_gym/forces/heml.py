"""HEML: the P1 hyperelastic force field written on the mesh edges.

``C = F^T F`` of a P1 tet is linear in its six squared edge lengths ``s_k``:
``C = sum_k s_k A_k`` with constant ``A_k = Dm^-T E_k Dm^-1``, where ``E_k`` places
``s_k`` in the Gram matrix ``G = Ds^T Ds`` (``G_aa = s_0a``,
``G_ab = (s_0a + s_0b - s_ab) / 2``). Hence ``I1 = a . s`` and ``I2 = s^T Q s / 2`` with
``a_k = tr A_k`` and ``Q_kl = a_k a_l - tr(A_k A_l)`` precomputed per tet, and ``J`` is
the signed volume ratio. The force is a set of edge forces plus one volume term; see
:mod:`heml_gym.forces.kernels_heml`.
"""

from __future__ import annotations

import copy

import numpy as np

from ..mesh import EDGE_PAIRS
from . import kernels_heml
from .base import ForceField
from .hessian import HessianCache, heml_hessian

# Upper-triangle (k <= l) index pairs of a 6x6 symmetric matrix, row by row: 21 entries.
Q_UPPER = np.array([(k, l) for k in range(6) for l in range(k, 6)], dtype=np.int64)


def gram_coefficients() -> np.ndarray:
    """``(6, 3, 3)`` matrices ``E_k`` with ``G = Ds^T Ds = sum_k s_k E_k``."""
    e = np.zeros((6, 3, 3))
    for k, (a, b) in enumerate(EDGE_PAIRS):
        if a == 0:  # s_0b sits on the diagonal G_bb and in half of each G_bc
            i = b - 1
            e[k, i, i] = 1.0
            for j in range(3):
                if j != i:
                    e[k, i, j] += 0.5
                    e[k, j, i] += 0.5
        else:  # s_ab enters G_ab with -1/2
            e[k, a - 1, b - 1] = e[k, b - 1, a - 1] = -0.5
    return e


def edge_tensors(dm_inv: np.ndarray) -> np.ndarray:
    """``A_k`` per tet, ``(m, 6, 3, 3)``, from the rest edge inverses ``Dm^-1`` ``(m, 3, 3)``
    (:attr:`heml_gym.TetMesh.rest_edge_inverses`)."""
    return np.einsum("tia,kab,tbj->tkij", dm_inv.transpose(0, 2, 1), gram_coefficients(), dm_inv)


def heml_coefficients(mesh, with_q: bool):
    """Per-tet HEML constants of ``mesh``: ``coef (m, 9) = (V0, 1/(6 V0), a_0..a_5, 1)`` and
    ``q (m, 21)``, the upper triangle of ``Q`` (``(1, 21)`` zeros unless ``with_q``). The
    last column is the tet's relative stiffness ``s`` (1 here; see
    :meth:`HemlRestData.with_stiffness`), by which its energy weight ``coef[:, 0]`` is also
    multiplied."""
    a_mats = edge_tensors(mesh.rest_edge_inverses)
    a = np.einsum("tkii->tk", a_mats)
    volume = mesh.volumes
    coef = np.empty((mesh.n_tets, 9))
    coef[:, 0] = volume
    coef[:, 1] = 1.0 / (6.0 * volume)
    coef[:, 2:8] = a
    coef[:, 8] = 1.0
    if with_q:
        tr_aa = np.einsum("tkij,tlji->tkl", a_mats, a_mats)
        q_full = a[:, :, None] * a[:, None, :] - tr_aa
        q = np.ascontiguousarray(q_full[:, Q_UPPER[:, 0], Q_UPPER[:, 1]])
    else:
        q = np.zeros((1, 21))
    return coef, q


def assembled_edge_weights(mesh, tet_edge_weights: np.ndarray):
    """Sum per-tet edge weights ``(m, 6)`` onto the mesh's unique edges.

    Returns ``(edges (e, 2), weights (e,))`` with the edges as in :attr:`TetMesh.edges`.
    """
    n = mesh.n_vertices
    edges = np.ascontiguousarray(mesh.edges)
    pairs = np.sort(mesh.tets[:, EDGE_PAIRS].reshape(-1, 2), axis=1)
    idx = np.searchsorted(edges[:, 0] * n + edges[:, 1], pairs[:, 0] * n + pairs[:, 1])
    weights = np.bincount(idx, weights=tet_edge_weights.reshape(-1), minlength=len(edges))
    return edges, weights


def _edge_weights(coef: np.ndarray) -> np.ndarray:
    """``(6, m)`` ``2 s V0 a_k`` (m^3) from the per-tet constants ``coef`` (m, 9), edge-major."""
    return np.ascontiguousarray((2.0 * coef[:, 0:1] * coef[:, 2:8]).T)


class HemlRestData:
    """What HEML precomputes from the rest shape, for any material: shared by every
    :class:`HemlForce` of one mesh (see :meth:`HemlForce.with_material`).

    Attributes
    ----------
    coef, coef_t : ``(m, 9)`` ``(s V0, 1/(6 V0), a_0..a_5, s)`` per tet, and its constant-major
        copy; ``s`` is the tet's relative stiffness (1 unless :meth:`with_stiffness`)
    tets : ``(m, 4)`` vertex indices for the kernels (32-bit when the mesh allows:
        less memory traffic; on 1 M tets, 2 threads: 97 against 77 M tets/s)
    inv_det : ``(m,)`` ``1 / det(Dm) = 1 / (6 V0)`` (1/m^3)
    edge_weights : ``(6, m)`` ``2 s V0 a_k`` (m^3), edge-major: the spring weights of a law
        with constant ``Psi_1`` are ``Psi_1`` times these
    relative_stiffness : ``(m,)`` or None
        Each tet's stiffness relative to the material's (dimensionless; None: 1 everywhere)
    q, q_t : ``(m, 21)`` upper triangle of ``Q`` and its constant-major copy, computed on
        first use (only laws with an ``I2`` term read them)
    """

    def __init__(self, mesh):
        self.mesh = mesh
        self.coef, _ = heml_coefficients(mesh, with_q=False)
        self.coef_t = np.ascontiguousarray(self.coef.T)
        small = mesh.n_vertices < np.iinfo(np.int32).max
        self.tets = np.ascontiguousarray(mesh.tets, dtype=np.int32 if small else np.int64)
        self.inv_det = np.ascontiguousarray(self.coef[:, 1])
        self.edge_weights = _edge_weights(self.coef)
        self.relative_stiffness = None
        self._q = None
        self._q_t = None
        self._hessian_cache = None

    def with_stiffness(self, relative) -> "HemlRestData":
        """The rest data of the same mesh with each tet's strain energy multiplied by
        ``relative`` ``(m,)`` (dimensionless, > 0): a Young's modulus that varies over the
        body, ``E_t = relative[t] E`` at a fixed Poisson ratio (every law's energy is
        linear in its moduli). Shares the tets, ``Q`` and the Hessian pattern."""
        relative = np.asarray(relative, dtype=np.float64)
        if relative.shape != (self.mesh.n_tets,) or not np.all(np.isfinite(relative)) or np.any(relative <= 0):
            raise ValueError(f"relative stiffness: must be ({self.mesh.n_tets},) finite numbers > 0, "
                             f"got shape {relative.shape}")
        self.hessian_cache  # noqa: B018 - built once, shared by the copies
        scaled = copy.copy(self)
        scaled.coef = self.coef.copy()
        scaled.coef[:, 0] = self.mesh.volumes * relative
        scaled.coef[:, 8] = relative
        scaled.coef_t = np.ascontiguousarray(scaled.coef.T)
        scaled.edge_weights = _edge_weights(scaled.coef)
        scaled.relative_stiffness = relative.copy()
        return scaled

    @property
    def hessian_cache(self) -> HessianCache:
        """The Hessian's sparsity pattern and element block positions (built on first
        use; shared by the fields of this rest data, i.e. of one mesh)."""
        if self._hessian_cache is None:
            self._hessian_cache = HessianCache(self.mesh.n_vertices, self.mesh.tets, self.mesh.edges)
        return self._hessian_cache

    @property
    def q(self) -> np.ndarray:
        if self._q is None:
            _, self._q = heml_coefficients(self.mesh, with_q=True)
            self._q_t = np.ascontiguousarray(self._q.T)
        return self._q

    @property
    def q_t(self) -> np.ndarray:
        self.q  # noqa: B018 - computes it
        return self._q_t


_NO_Q = np.zeros((1, 21))
_NO_Q_T = np.ascontiguousarray(_NO_Q.T)


class HemlForce(ForceField):
    """Hyper-Elastic Mass-Links force field for any law of :mod:`heml_gym.materials`.

    Exactly P1 finite elements (it agrees with :class:`heml_gym.FemForce` to rounding),
    evaluated as state-dependent edge springs plus one volume term per tet. For a law
    with constant ``dPsi/dI1`` (Neo-Hookean) the spring weights are constants (``split``):
    they are precomputed, and a blocked kernel that vectorises evaluates springs and
    volume term together.

    Public kernel data (read by the solvers and the Hessian): ``law_id``, ``params``
    (the law's constants), ``use_q``, ``split``, ``spring_weights`` (``(6, m)`` N/m, when
    ``split``) and ``rest`` (:class:`HemlRestData`: ``coef``, ``coef_t``, ``q``, ``q_t``,
    ``tets``, ``inv_det``, ``edge_weights``).
    """

    name = "HEML"
    has_hessian = True

    def __init__(self, mesh, material, rest: HemlRestData | None = None):
        super().__init__(mesh, material)
        if rest is None:
            rest = HemlRestData(mesh)
        elif rest.mesh is not mesh:
            raise ValueError("rest data belongs to another mesh")
        self.rest = rest
        self.use_q = bool(material.needs_i2)
        self.law_id = np.int64(material.law_id)
        self.params = np.ascontiguousarray(material.params, dtype=np.float64)
        # Constant Psi_1 (Neo-Hookean): the I1 part is a fixed spring network, its weights
        # 2 V0 Psi_1 a_k precomputed; a blocked kernel that vectorises does the rest (its
        # volume term takes no relative stiffness: a body whose E varies takes the general one).
        self.split = material.constant_psi1 is not None and not self.use_q and rest.relative_stiffness is None
        if self.split:
            self.psi1 = float(material.constant_psi1)
            self.spring_weights = np.ascontiguousarray(self.psi1 * rest.edge_weights)

    def with_material(self, material) -> "HemlForce":
        """The HEML field of ``material`` on this mesh, sharing the rest data and the
        Hessian pattern (only the law's constants and, for Neo-Hookean, the ``6 m``
        spring weights are new)."""
        return HemlForce(self.mesh, material, rest=self.rest)

    # compatibility names of the per-tet data (the rest data holds them)
    coef = property(lambda self: self.rest.coef)
    coef_t = property(lambda self: self.rest.coef_t)
    inv_det = property(lambda self: self.rest.inv_det)
    q = property(lambda self: self.rest.q if self.use_q else _NO_Q)
    q_t = property(lambda self: self.rest.q_t if self.use_q else _NO_Q_T)

    def kernel_args(self):
        """Arguments of the general force and energy kernels of
        :mod:`heml_gym.forces.kernels_heml` (after ``x``): ``tets, coef_t, q_t, use_q,
        law_id, params``."""
        return self.rest.tets, self.coef_t, self.q_t, self.use_q, self.law_id, self.params

    def split_kernel_args(self):
        """Arguments of the constant-``Psi_1`` kernels (after ``x``; only when ``split``):
        ``tets, inv_det, spring_weights, law_id, params``."""
        return self.rest.tets, self.rest.inv_det, self.spring_weights, self.law_id, self.params

    def _energy_serial(self, x):
        return kernels_heml.heml_energy_chunk(x, *self.kernel_args(), 0, self.n_elements)

    def _energy_parallel(self, x, n_chunks):
        return kernels_heml.heml_energy_parallel(x, *self.kernel_args(), n_chunks)

    def _add_forces_serial(self, x, f):
        if self.split:
            kernels_heml.constant_psi1_forces_chunk(x, *self.split_kernel_args(), f, 0, self.mesh.n_tets)
        else:
            kernels_heml.heml_forces_chunk(x, *self.kernel_args(), f, 0, self.n_elements)

    def _add_forces_parallel(self, x, buf):
        if self.split:
            kernels_heml.constant_psi1_forces_parallel(x, *self.split_kernel_args(), buf)
        else:
            kernels_heml.heml_forces_parallel(x, *self.kernel_args(), buf)

    def hessian(self, x, project=True):
        """Stiffness matrix ``d2W/dx2`` (N/m) at ``x``: a ``3n x 3n`` scipy CSR matrix.

        ``forces(x + dx) ~= forces(x) - K dx``. With ``project=True`` each tet's
        contribution is made positive semi-definite (negative eigenvalues of
        ``d2Psi/dF2`` clamped to zero, in closed form); ``project=False`` gives the
        exact Hessian. See :mod:`heml_gym.forces.hessian`.
        """
        return heml_hessian(self, x, project)

    @property
    def hessian_cache(self) -> HessianCache:
        """The Hessian's pattern and block positions (its rest data's: one per mesh)."""
        return self.rest.hessian_cache


class SameEnergyAsHeml:
    """Mixin for fields that compute HEML's P1 energy another way (F-FEM, mass-tensor).

    Their Hessian is HEML's analytic one, so the implicit integrator can run with their
    forces.
    """

    has_hessian = True
    _hessian_field = None

    def _heml(self) -> HemlForce:
        if self._hessian_field is None:
            self._hessian_field = HemlForce(self.mesh, self.material)
        return self._hessian_field

    def hessian(self, x, project=True):
        """Stiffness matrix ``d2W/dx2`` (N/m), a ``3n x 3n`` scipy CSR matrix (HEML's)."""
        return self._heml().hessian(x, project)

    @property
    def hessian_cache(self) -> HessianCache:
        """HEML's Hessian pattern and block positions for this mesh."""
        return self._heml().hessian_cache
