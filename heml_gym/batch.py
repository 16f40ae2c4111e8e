"""Many copies of one Neo-Hookean HEML body, advanced together by one parallel Numba call.

Vectorised environments run N scenes that share a mesh but differ in state, stiffness
and grasped vertices. :class:`BatchedSimulation` holds them as ``(N, n, 3)`` arrays and
integrates all of them with explicit symplectic Euler in one call: the kernel
(:func:`heml_gym.kernels_batch.lane_explicit_substeps`) runs the scenes in lockstep,
vectorised across scenes, in blocks of scenes spread over the threads (no race and no
reduction). Units: m, s, kg, Pa, N.

Divergence is per scene: a scene whose state goes non-finite or too fast is flagged in
the returned mask and keeps the state it had before the step; the others go on.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .forces.heml import HemlForce
from .kernels_batch import LANES, lane_explicit_substeps
from .kernels_dynamics import explicit_substeps_constant_psi1
from .materials import NeoHookean
from .mesh import TetMesh
from .simulation import Simulation

__all__ = ["BatchedSimulation"]


class BatchedSimulation:
    """N Neo-Hookean HEML scenes on one mesh, integrated explicitly in one parallel call.

    Parameters
    ----------
    mesh : TetMesh
    n_scenes : int
    young_modulus : float or (N,) floats
        E of each scene in Pa (Poisson's ratio ``poisson`` is shared).
    poisson : float
    density : float
        kg/m^3, shared.
    gravity : (3,) float, m/s^2
    fixed : vertex indices or mask, shared by all scenes
    damping : float
        Mass-proportional Rayleigh damping ``alpha`` in 1/s.
    safety : float
        Sub-steps are at most ``safety`` times the critical step of the stiffest scene.
    floor : float or None
        Height (m) of a rigid, frictionless support plane ``z = floor`` that free vertices
        cannot go below (the organ a tissue lies on); None for none.
    """

    def __init__(self, mesh: TetMesh, n_scenes: int, young_modulus=5e3, poisson=0.45,
                 density=1000.0, gravity=(0.0, 0.0, -9.81), fixed=None, damping=0.0,
                 safety=0.5, max_speed=1e3, floor=None):
        if n_scenes < 1:
            raise ValueError(f"n_scenes must be >= 1, got {n_scenes}")
        self.mesh = mesh
        self.n_scenes = int(n_scenes)
        self.poisson = float(poisson)
        self.density = float(density)
        self.gravity = np.asarray(gravity, dtype=np.float64)
        self.alpha = float(damping)
        self.safety = float(safety)
        self.max_speed = float(max_speed)
        self.floor_z = -math.inf if floor is None else float(floor)
        # a reference single-scene simulation: lumped masses, fixed mask, critical step
        self._reference_E = 1e3
        ref = Simulation(HemlForce(mesh, NeoHookean(E=self._reference_E, nu=poisson)), density,
                         gravity=gravity, fixed=fixed, integrator="explicit")
        self.mass = ref.mass
        self.fixed = ref.fixed
        self._reference_dt = ref.critical_dt()
        field = ref.field
        self._tets = mesh.tets
        self._inv_det = field.inv_det
        self._base_weights = field.spring_weights / field.material.constant_psi1  # 2 V0 a_k
        self._law = np.int64(field.material.law_id)
        n, N = mesh.n_vertices, self.n_scenes
        self.x = np.empty((N, n, 3))
        self.v = np.zeros((N, n, 3))
        self.kinematic = np.zeros((N, n), dtype=bool)
        self.targets = np.zeros((N, n, 3))
        self.reaction = np.zeros((N, n, 3))
        self._f = np.zeros((N, n, 3))
        self._sub_reaction = np.zeros((n, 3))
        self._ext = np.zeros((n, 3))
        self._weights = np.empty((N,) + self._base_weights.shape)
        self._params = np.empty((N, 2))
        self._psi1 = np.empty(N)
        self.young_modulus = np.empty(N)
        self.set_young_modulus(np.broadcast_to(np.asarray(young_modulus, dtype=np.float64), (N,)))
        for s in range(N):
            self.reset_scene(s)

    # ---------------------------------------------------------------- set-up
    def set_young_modulus(self, values, scenes=None) -> None:
        """Set E (Pa) of the given scenes (all by default)."""
        scenes = np.arange(self.n_scenes) if scenes is None else np.atleast_1d(scenes)
        values = np.broadcast_to(np.asarray(values, dtype=np.float64), scenes.shape)
        for s, E in zip(scenes, values):
            mat = NeoHookean(E=float(E), nu=self.poisson)
            self.young_modulus[s] = E
            self._params[s] = mat.params
            self._psi1[s] = mat.constant_psi1
            self._weights[s] = mat.constant_psi1 * self._base_weights

    def critical_dt(self, young_modulus: float | None = None) -> float:
        """Rest-state explicit limit (s) for E = ``young_modulus`` Pa (default: the stiffest scene).

        It scales as ``1 / sqrt(E)`` at fixed Poisson ratio and density.
        """
        E = float(self.young_modulus.max()) if young_modulus is None else float(young_modulus)
        return self._reference_dt * math.sqrt(self._reference_E / E)

    def reset_scene(self, s: int) -> None:
        """Scene ``s`` back to rest, at rest, nothing grasped."""
        self.x[s] = self.mesh.vertices
        self.v[s] = 0.0
        self.kinematic[s] = False
        self.reaction[s] = 0.0

    # --------------------------------------------------------------- grasping
    def attach(self, s: int, vertices) -> None:
        """Make ``vertices`` of scene ``s`` kinematic, held where they are."""
        idx = np.asarray(vertices, dtype=np.int64)
        idx = idx[~self.fixed[idx]]
        self.kinematic[s, idx] = True
        self.targets[s, idx] = self.x[s, idx]

    def drive(self, s: int, vertices, targets) -> None:
        """Kinematic ``vertices`` of scene ``s`` reach ``targets`` (m) at the end of the next step."""
        self.targets[s, np.asarray(vertices, dtype=np.int64)] = targets

    def detach(self, s: int) -> None:
        """Release every kinematic vertex of scene ``s``."""
        self.kinematic[s] = False

    def _lanes(self) -> int:
        """Scenes per block of the batched kernel: the scenes spread evenly over the
        threads, in whole vectors of 4 float64, at most :data:`~heml_gym.kernels_batch.LANES`."""
        per_thread = math.ceil(self.n_scenes / numba.get_num_threads())
        return min(LANES, 4 * math.ceil(per_thread / 4))

    # ---------------------------------------------------------------- stepping
    def step(self, dt: float, active=None, substeps: int | None = None) -> np.ndarray:
        """Advance the active scenes by ``dt`` s; returns the mask of scenes that diverged.

        ``substeps`` defaults to what ``safety`` requires for the stiffest scene. A
        diverged scene keeps the state it had before this step.
        """
        if not (dt > 0 and math.isfinite(dt)):
            raise ValueError(f"dt must be a positive number of seconds, got {dt}")
        active = np.ones(self.n_scenes, dtype=bool) if active is None else np.asarray(active, dtype=bool)
        n_sub = substeps or max(1, math.ceil(dt / (self.safety * self.critical_dt())))
        h = dt / n_sub
        x0, v0 = self.x.copy(), self.v.copy()
        bad = np.full(self.n_scenes, -1, dtype=np.int64)
        with np.errstate(all="ignore"):
            if self.n_scenes == 1:  # one scene: the kernel vectorised across tets
                if active[0]:
                    bad[0] = explicit_substeps_constant_psi1(
                        self.x[0], self.v[0], self._f[0], self.reaction[0], self._sub_reaction,
                        self.mass, self.gravity,
                        self._ext, self.alpha, h, n_sub, self.fixed, self.kinematic[0], x0[0],
                        self.targets[0], self.max_speed, self._tets, self._inv_det, self._weights[0],
                        self._law, self._params[0], self.floor_z)[1]
            else:  # lane copies for the kernel vectorised across scenes
                lanes = self._lanes()
                blocks = math.ceil(self.n_scenes / lanes)
                pad = blocks * lanes - self.n_scenes  # extra lanes repeat scene 0

                def to_lanes(a):
                    a = np.concatenate([a, np.repeat(a[:1], pad, axis=0)]) if pad else a
                    a = a.reshape((blocks, lanes) + a.shape[1:])
                    return np.ascontiguousarray(np.moveaxis(a, 1, -1))

                def from_lanes(a):
                    return np.moveaxis(a, -1, 1).reshape((blocks * lanes,) + a.shape[1:-1])[:self.n_scenes]

                xl, vl = to_lanes(self.x), to_lanes(self.v)
                reaction = np.empty_like(xl)
                bad_lanes = np.empty((blocks, lanes), dtype=np.int64)
                lane_explicit_substeps(
                    xl, vl, np.empty_like(xl), reaction, self.mass, self.gravity, self._ext,
                    self.alpha, h, n_sub, self.fixed, to_lanes(self.kinematic), xl.copy(),
                    to_lanes(self.targets), self.max_speed, self._tets, self._inv_det,
                    self._base_weights, self._law, to_lanes(self._params[:, 0]),
                    to_lanes(self._params[:, 1]), to_lanes(self._psi1), bad_lanes, self.floor_z)
                self.x[:] = from_lanes(xl)
                self.v[:] = from_lanes(vl)
                self.reaction[:] = from_lanes(reaction)
                bad[:] = bad_lanes.reshape(-1)[:self.n_scenes]
                bad[~active] = -1
        self.x[~active] = x0[~active]  # inactive scenes are not advanced
        self.v[~active] = v0[~active]
        diverged = bad >= 0
        self.x[diverged] = x0[diverged]
        self.v[diverged] = v0[diverged]
        self.last_substeps = n_sub
        return diverged
