"""The model: what does not change while N worlds are simulated.

A :class:`Model` holds one tet mesh and, for each of its ``N`` worlds, a material (so
E, nu and even the law can differ per world), plus what all worlds share: the force
field's rest-shape precomputation (HEML coefficients, ``Dm^-1``, the Hessian pattern:
computed once, whatever N), lumped masses, fixed vertices, gravity, damping and rigid
supports. It is built once; a :class:`~heml_gym.state.State` holds what a step changes
and a :class:`~heml_gym.control.Control` what the user drives; the solvers of
:mod:`heml_gym.solvers` step all N worlds. N = 1 is the single case, not a separate
path. Units: m, s, kg, Pa, N.

A *world* is one independent copy in this batch (index ``0 .. N-1``: arrays of
:class:`State` and :class:`Control` lead with it); a *scene* (:mod:`heml_gym.envs`) is
what is simulated: the tissue, its supports and the task. An env with 16 copies of a
scene steps one model of 16 worlds.

    model = Model(mesh, NeoHookean(E=5e3, nu=0.45), n_worlds=4, fixed=clamped)
    model.set_material(2, StVenantKirchhoff(E=8e3, nu=0.45))
    state, control = model.state(), model.control()
    solver = ImplicitSolver(model)
    solver.step(state, state, control, dt=1 / 30)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse.linalg as spla

from .contact import Support, Supports
from .control import Control
from .forces import FemForce, ForceField, HemlForce, MassSpringForce, MassTensorForce, QuadraticFemForce
from .kernel_data import HemlBody, HemlLaws, SupportArrays
from .materials import Material
from .mesh import TetMesh
from .state import State
from .tools import Tools

__all__ = ["Model", "Damping", "FORCE_FIELDS"]

#: Force fields by name (``Model(field=...)``, the envs' ``physics={"field": ...}``).
#: ``"quadratic"`` needs a :class:`~heml_gym.QuadraticTetMesh` (10-node tets).
FORCE_FIELDS = {"heml": HemlForce, "fem": FemForce, "mass_tensor": MassTensorForce,
                "mass_spring": MassSpringForce, "quadratic": QuadraticFemForce}


@dataclass(frozen=True)
class Damping:
    """Rayleigh damping ``C = alpha M + beta K``.

    ``alpha`` (1/s) damps every motion, rigid motion included (like drag in a fluid);
    ``beta`` (s) damps deformation rates only, more at high frequencies.
    """

    alpha: float = 0.0
    beta: float = 0.0

    def __post_init__(self):
        for name in ("alpha", "beta"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"Damping.{name} must be a finite number >= 0, got {v!r}")


class Model:
    """N worlds of one tet mesh: per-world materials, shared mesh, masses and constraints.

    Parameters
    ----------
    mesh : TetMesh
        The body at rest (m). Optional when ``field`` is a force field instance.
    material : Material or sequence of N Materials
        The law and constants of every world (one material for all, or one each).
    n_worlds : int
        N (default: the number of materials given, else 1).
    field : str, ForceField class or ForceField instance
        ``"heml"`` (default), ``"fem"``, ``"mass_tensor"``, ``"mass_spring"`` (see
        :data:`FORCE_FIELDS`), a class, or a ready field (whose mesh and material are then
        used; its precomputation is shared with the other worlds).
    density : float
        kg/m^3; lumped mass ``rho V / 4`` per vertex per incident tet.
    fixed : vertex indices or (n,) bool mask
        Vertices that never move (every world).
    gravity : (3,) float, m/s^2
    damping : Damping, float (``alpha``) or None
    supports : sequence of :class:`~heml_gym.contact.PlaneSupport` /
        :class:`~heml_gym.contact.MeshSupport`
        Rigid bodies the tissue rests on.
    tools : sequence of :class:`~heml_gym.tools.Capsule` / :class:`~heml_gym.tools.Box`
        Rigid tools that touch the tissue, posed per world each step
        (:meth:`heml_gym.Control.pose_tool`; the ``quasi_newton`` and ``implicit``
        integrators step them).
    """

    def __init__(self, mesh: TetMesh | None = None, material: Material | Sequence[Material] | None = None,
                 n_worlds: int | None = None, field="heml", density: float = 1000.0, fixed=None,
                 gravity=(0.0, 0.0, -9.81), damping: Damping | float | None = None, supports=(), tools=()):
        if isinstance(field, ForceField):
            if mesh is not None and mesh is not field.mesh:
                raise ValueError("mesh and field.mesh differ: give one of them")
            mesh = field.mesh
            if material is None:
                material = field.material
            base = field
        else:
            if isinstance(field, str):
                if field not in FORCE_FIELDS:
                    raise ValueError(f"field must be one of {sorted(FORCE_FIELDS)}, got {field!r}")
                cls = FORCE_FIELDS[field]
            elif isinstance(field, type) and issubclass(field, ForceField):
                cls = field
            else:
                raise TypeError(f"field must be a name, a ForceField class or instance, got {field!r}")
            if not isinstance(mesh, TetMesh):
                raise TypeError(f"mesh must be a heml_gym.TetMesh, got {type(mesh).__name__}")
            base = None
        materials = [material] if isinstance(material, Material) else list(material or [])
        if not materials:
            raise ValueError("material is required: a heml_gym.materials.Material (or one per world)")
        if n_worlds is None:
            n_worlds = len(materials)
        if not isinstance(n_worlds, (int, np.integer)) or isinstance(n_worlds, bool) or n_worlds < 1:
            raise ValueError(f"n_worlds must be an integer >= 1, got {n_worlds!r}")
        n_worlds = int(n_worlds)
        if len(materials) == 1:
            materials = materials * n_worlds
        if len(materials) != n_worlds:
            raise ValueError(f"give one material or n_worlds = {n_worlds} of them, got {len(materials)}")
        density = float(density)
        if not math.isfinite(density) or density <= 0:
            raise ValueError(f"density must be a positive number of kg/m^3, got {density}")
        gravity = np.asarray(gravity, dtype=np.float64)
        if gravity.shape != (3,) or not np.all(np.isfinite(gravity)):
            raise ValueError(f"gravity must be three finite numbers (m/s^2), got {gravity}")
        if damping is None:
            damping = Damping()
        elif not isinstance(damping, Damping):
            damping = Damping(alpha=float(damping))

        self.mesh = mesh
        self.n_worlds = n_worlds
        self.n_vertices = mesh.n_vertices
        self.density = density
        self.gravity = gravity
        self.damping = damping
        self.supports = Supports(s for s in supports) if not isinstance(supports, Supports) else supports
        for s in self.supports.items:
            if not isinstance(s, Support):
                raise TypeError(f"supports must be PlaneSupport / MeshSupport objects, got {type(s).__name__}")
        self.tools = tools if isinstance(tools, Tools) else Tools(tools)
        self.mass = density * mesh.vertex_volumes  # kg per vertex
        self.fixed = vertex_mask(mesh.n_vertices, fixed, "fixed")
        self.fixed.setflags(write=False)
        if base is None:
            base = cls(mesh, materials[0])
        self._base = base
        self._mapped = None  # HEML rest data with a relative stiffness per tet (set_stiffness_map)
        self._body: HemlBody | None = None  # see heml_body / heml_laws
        self._laws: HemlLaws | None = None
        self.material_revision = 0  # counts set_material calls (for what a solver derives from materials)
        self.fields: list[ForceField] = [None] * n_worlds
        self.materials: list[Material] = [None] * n_worlds
        for s, mat in enumerate(materials):
            self.set_material(s, mat)
        self._critical = {}  # (field class, moduli ratios) -> (E, rest critical step)

    # ---------------------------------------------------------------- materials
    @property
    def field(self) -> ForceField:
        """The force field of world 0 (every world's has the same kind and mesh)."""
        return self.fields[0]

    def set_material(self, worlds, material: Material) -> None:
        """Give ``worlds`` (an index or indices) the ``material``: a new force field that
        shares every material-independent precomputation with the others."""
        if not isinstance(material, Material):
            raise TypeError(f"material must be a heml_gym.materials.Material, got {type(material).__name__}")
        field = self._field_for(material)
        for s in np.atleast_1d(worlds):
            s = int(s)
            if not 0 <= s < self.n_worlds:
                raise IndexError(f"world {s} outside [0, {self.n_worlds})")
            self.fields[s] = field
            self.materials[s] = material
        self.material_revision += 1
        self._update_laws(np.atleast_1d(worlds))

    def _field_for(self, material: Material) -> ForceField:
        """The force field of ``material`` on this mesh (with the stiffness map, if set)."""
        if self._mapped is not None:
            return HemlForce(self.mesh, material, rest=self._mapped)
        return self._base if material is self._base.material else self._base.with_material(material)

    def set_stiffness_map(self, relative) -> None:
        """Make Young's modulus vary over the body: tet ``t`` of every world gets
        ``relative[t]`` times its world's modulus, at the world's Poisson ratio (its strain
        energy is multiplied by ``relative[t]``; ``relative``: ``(m,)``, dimensionless,
        finite and > 0). None makes the body uniform again. HEML fields only. Every solver
        reads it (the explicit one's critical step is divided by the square root of the
        stiffest tet's factor: a safe bound); a Neo-Hookean body with a map takes the
        general kernels (the constant ``Psi_1`` ones assume a uniform body), about as fast
        as Mooney-Rivlin's."""
        if not isinstance(self._base, HemlForce):
            raise ValueError(f"stiffness map: HEML force fields only (field 'heml'), the model's is "
                             f"{type(self._base).__name__}")
        self._mapped = None if relative is None else self._base.rest.with_stiffness(relative)
        for s in range(self.n_worlds):
            self.fields[s] = self._field_for(self.materials[s])
        self._body = None
        self._laws = None
        self.material_revision += 1

    @property
    def stiffness_map(self) -> np.ndarray | None:
        """Each tet's Young's modulus relative to its world's, ``(m,)``, or None (uniform);
        see :meth:`set_stiffness_map`."""
        return None if self._mapped is None else self._mapped.relative_stiffness

    # -------------------------------------------------------------- kernel arrays
    def heml_body(self) -> HemlBody:
        """The arrays of a HEML model that the solver kernels read and every world shares
        (:class:`~heml_gym.kernel_data.HemlBody`: rest data, masses, fixed set, gravity,
        damping, the tets around each vertex). Only for HEML force fields."""
        if self._body is None:
            rest = self._heml_fields()[0].rest
            tets = self.mesh.tets
            order = np.argsort(tets.ravel(), kind="stable")
            vt_tets = np.ascontiguousarray(order // 4, dtype=np.int64)
            vt_ptr = np.concatenate([[0], np.cumsum(np.bincount(tets.ravel(), minlength=self.n_vertices))])
            self._body = HemlBody(tets=rest.tets, coef_t=rest.coef_t, inv_det=rest.inv_det,
                                  edge_weights=np.ascontiguousarray(rest.edge_weights), mass=self.mass,
                                  fixed=self.fixed, gravity=self.gravity, alpha=float(self.damping.alpha),
                                  vt_ptr=vt_ptr.astype(np.int64), vt_tets=vt_tets)
        return self._body

    def heml_laws(self) -> HemlLaws:
        """Every world's law as the solver kernels read it
        (:class:`~heml_gym.kernel_data.HemlLaws`), kept current by :meth:`set_material`.
        Only for HEML force fields."""
        if self._laws is None:
            fields = self._heml_fields()
            split = all(f.split for f in fields)
            use_q = any(f.use_q for f in fields)
            N = self.n_worlds
            self._laws = HemlLaws(
                law=np.zeros(N, dtype=np.int64), params=np.zeros((N, max(len(f.params) for f in fields))),
                weights=np.zeros((N,) + (fields[0].spring_weights.shape if split else (6, 1))), psi1=np.zeros(N),
                split=split, use_q=use_q, q_t=fields[0].rest.q_t if use_q else fields[0].q_t)
            self._set_law_rows(range(N))
        return self._laws

    def _heml_fields(self) -> list[HemlForce]:
        if not all(isinstance(f, HemlForce) for f in self.fields):
            kinds = sorted({type(f).__name__ for f in self.fields})
            raise TypeError(f"these kernels need HEML force fields, the model has {', '.join(kinds)}")
        return self.fields

    def _update_laws(self, worlds: np.ndarray) -> None:
        """Keep :meth:`heml_laws` current after ``worlds`` changed material: their rows in
        place, or a rebuild (on the next call) when the batch's flags or widths change."""
        laws = self._laws
        if laws is None:
            return
        fields = self.fields
        if (all(f.split for f in fields) != laws.split or any(f.use_q for f in fields) != laws.use_q
                or max(len(f.params) for f in fields) != laws.params.shape[1]):
            self._laws = None
            return
        self._set_law_rows(worlds)

    def _set_law_rows(self, worlds) -> None:
        """Write ``worlds``' rows of :meth:`heml_laws` from their fields (law id, zero-padded
        constants, ``psi1`` and spring weights when the batch is split)."""
        laws = self._laws
        for s in worlds:
            f = self.fields[int(s)]
            laws.law[s] = f.law_id
            laws.params[s] = 0.0
            laws.params[s, :len(f.params)] = f.params
            laws.psi1[s] = f.psi1 if f.split else 0.0
            if laws.split:
                laws.weights[s] = f.spring_weights

    @property
    def young_modulus(self) -> np.ndarray:
        """Small-strain Young's modulus of each world (Pa), ``(N,)``."""
        return np.array([m.young_modulus for m in self.materials])

    # ------------------------------------------------------------------- states
    def state(self) -> State:
        """A state of all worlds at rest (positions the mesh's, velocities zero)."""
        x = np.repeat(self.mesh.vertices[None], self.n_worlds, axis=0)
        return State(x, np.zeros_like(x))

    def control(self) -> Control:
        """A control with nothing held and no external force."""
        return Control(self.n_worlds, self.n_vertices, n_tools=len(self.tools))

    def contact_args(self, control: Control, tool_k=None) -> SupportArrays:
        """The supports and the tools posed as ``control`` says, their penalty stiffness
        ``tool_k (N, n)`` (N/m at each vertex), for the kernels."""
        return self.supports.kernel_args(self.tools, control.tool_pose, tool_k)

    @property
    def has_contact(self) -> bool:
        """Whether the tissue can touch anything rigid (a support or a tool)."""
        return bool(len(self.supports) or len(self.tools))

    # --------------------------------------------------------------- stability
    def critical_dt(self, world: int | None = None, material: Material | None = None) -> float:
        """Explicit stability limit (s) at rest: ``2 / omega_max``, with ``omega_max^2`` the
        largest eigenvalue of ``M^-1 K`` (undamped, lumped mass), of world ``world``, of
        ``material`` on this mesh, or (default) the smallest over all worlds.

        The rest stiffness is that of linear elasticity with the law's small-strain moduli,
        so at a given Poisson ratio the limit scales as ``1 / sqrt(E)``: one Lanczos run
        (on force differences) per field kind and Poisson ratio, cached, serves every E.
        Stiffening under large strain lowers the limit, which is what the explicit
        solver's ``safety`` is for.
        """
        if material is not None:
            return self._critical_dt_of(material)
        if world is not None:
            return self._critical_dt_of(self.materials[int(world)])
        return min(self._critical_dt_of(m) for m in set(self.materials))

    def _critical_dt_of(self, material: Material) -> float:
        E = material.young_modulus
        key = (type(self._base).__name__, round(material.shear_modulus / E, 12),
               round(material.bulk_modulus / E, 12))
        if key not in self._critical:
            field = self._base if material is self._base.material else self._base.with_material(material)
            self._critical[key] = (E, 2.0 / math.sqrt(rest_max_eigenvalue(field, self.mass)))
        E_ref, dt_ref = self._critical[key]
        stiffest = 1.0 if self._mapped is None else float(self._mapped.relative_stiffness.max())
        return dt_ref * math.sqrt(E_ref / (E * stiffest))  # (a map's stiffest tet: a safe bound)

    def estimated_critical_dt(self, world: int = 0) -> float:
        """``h_min / c`` (s): the smallest tet altitude over the small-strain P-wave speed.
        Quick, but off by a mesh-dependent factor (measured 0.88 to 1.75 on our meshes)."""
        return self.mesh.min_height / self.materials[world].wave_speed(self.density)

    def __repr__(self) -> str:
        laws = sorted({type(m).__name__ for m in self.materials})
        return (f"Model({self.mesh!r}, {self.n_worlds} worlds, {type(self._base).__name__}, "
                f"{'/'.join(laws)}, {int(self.fixed.sum())} fixed, {len(self.supports)} supports)")


def vertex_mask(n: int, vertices, what: str) -> np.ndarray:
    """``(n,)`` bool mask from vertex indices or a mask; errors name ``what``."""
    mask = np.zeros(n, dtype=bool)
    if vertices is None:
        return mask
    arr = np.asarray(vertices)
    if arr.dtype == bool:
        if arr.shape != (n,):
            raise ValueError(f"{what} mask must have shape ({n},), got {arr.shape}")
        return arr.copy()
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{what} vertices must be integer indices or a bool mask, got {arr.dtype}")
    arr = arr.astype(np.int64).ravel()
    if arr.size and (arr.min() < 0 or arr.max() >= n):
        raise ValueError(f"{what} vertex indices must lie in [0, {n})")
    mask[arr] = True
    return mask


def rest_max_eigenvalue(field: ForceField, mass: np.ndarray) -> float:
    """Largest eigenvalue (1/s^2) of ``M^-1/2 K M^-1/2`` at the rest shape, by Lanczos
    iteration on central differences of the forces. Should ARPACK fail, the Gershgorin
    bound of the rest Hessian (an upper bound: a smaller, safe step) is used instead."""
    try:
        return _lanczos_max_eigenvalue(field, mass)
    except (spla.ArpackError, spla.ArpackNoConvergence):
        return gershgorin_max_eigenvalue(field, mass)


def gershgorin_max_eigenvalue(field: ForceField, mass: np.ndarray) -> float:
    """An upper bound (1/s^2) of the largest eigenvalue of ``M^-1/2 K M^-1/2`` at rest:
    the largest Gershgorin row sum of the scaled rest Hessian."""
    k = field.hessian(field.mesh.vertices, project=False).tocsr()
    inv_sqrt_m = 1.0 / np.sqrt(np.repeat(mass, 3))
    scaled = abs(k).multiply(inv_sqrt_m[:, None]).multiply(inv_sqrt_m[None, :]).tocsr()
    return float(np.asarray(scaled.sum(axis=1)).max())


def _lanczos_max_eigenvalue(field: ForceField, mass: np.ndarray) -> float:
    mesh = field.mesh
    x0 = np.array(mesh.vertices)
    n = mesh.n_vertices
    inv_sqrt_m = 1.0 / np.sqrt(np.repeat(mass, 3))
    h = 1e-6 * mesh.min_edge_length

    def matvec(y):
        d = (inv_sqrt_m * np.ravel(y)).reshape(n, 3)
        kd = (field.forces(x0 - h * d) - field.forces(x0 + h * d)) / (2.0 * h)
        return inv_sqrt_m * kd.ravel()

    op = spla.LinearOperator((3 * n, 3 * n), matvec=matvec, dtype=np.float64)
    v0 = np.random.default_rng(0).standard_normal(3 * n)
    lam = spla.eigsh(op, k=1, which="LA", tol=1e-4, v0=v0, maxiter=10 * 3 * n, return_eigenvectors=False)[0]
    return float(lam)
