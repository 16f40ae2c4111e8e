"""The physics of a batch of worlds: one tissue's model and solver, N worlds stepped at once.

:class:`World` holds what the physics of a task needs and nothing of the task: the
:class:`~heml_gym.Model` (mesh, law per world, masses, fixed vertices, supports), its
solver, the :class:`~heml_gym.State` and :class:`~heml_gym.Control`, the tissue stuck to
what it rests on (adhesion: vertices held where they rest) and the hold springs of jaws
that hold part of a vertex. Instruments (grasp, release, drive) and tasks (what is
measured and rewarded) sit on top of it. Units: m, s, N, Pa.
"""

from __future__ import annotations

import math

import numpy as np

from .mesh import box_regions
from .model import Model
from .solvers import make_solver

#: Weighted jaws hold a vertex with share ``w`` of its row inside them by a spring of
#: ``HOLD_SPRING_SCALE w / (1 - w)`` times the vertex's diagonal rest stiffness: in series
#: with a tissue of that stiffness, a spring of ``w / (1 - w)`` times it holds with ``w`` of
#: it, but the diagonal overstates the stiffness a hold meets (the neighbours give way
#: too); a quarter of it brought the flap's hold force on the default mesh closest to the
#: finest mesh's over jaws of 24-56 mm (one seed, four scales tried;
#: docs/benchmarks/jaw_length_weighted.md measures five seeds).
HOLD_SPRING_SCALE = 0.25


class World:
    """N worlds of one tissue (a batch, as everywhere in heml_gym), stepped together by one solver.

    ``model``: the :class:`~heml_gym.Model` (``n_worlds`` worlds); ``solver``: its solver;
    ``substeps``: solver sub-steps per :meth:`step`. Attributes: ``state``, ``control``,
    ``reaction`` (the last step's constraint reactions, N, ``(N, n, 3)``) and ``stuck``
    (``(N, n)`` bool: vertices held where they rest by adhesion).
    """

    def __init__(self, model: Model, solver, substeps: int = 1):
        self.model, self.solver, self.substeps = model, solver, int(substeps)
        self.n = model.n_worlds
        self.mesh = model.mesh
        self.state = model.state()
        self.control = model.control()
        self.reaction = np.zeros((self.n, self.mesh.n_vertices, 3))
        self.stuck = np.zeros((self.n, self.mesh.n_vertices), dtype=bool)

    @classmethod
    def from_physics(cls, mesh, physics, n_worlds: int, control_dt: float, fixed=None, supports=(),
                     tools=()) -> "World":
        """The world of a physics description (``physics``: an object with the fields of
        ``heml_gym.envs.PhysicsSpec``: ``material_for(E)``, ``young_modulus`` (low, high),
        ``field``, ``density``, ``gravity``, ``damping``, ``stiffness_regions``,
        ``integrator``, ``scheme``, ``safety``, ``newton_tol``, ``max_newton``,
        ``hessian_scale``, ``max_dt``, ``tool_stiffness``), stepped ``control_dt`` seconds at a time. Every world
        starts with the stiffest tissue the range allows; explicit sub-steps are fixed by it,
        so that a world's trajectory does not depend on its neighbours. ``tools``: rigid tools
        (:mod:`heml_gym.tools`) the world's control poses."""
        ph = physics
        E_high = ph.young_modulus[1]
        model = Model(mesh, ph.material_for(E_high), n_worlds=int(n_worlds), field=ph.field, density=ph.density,
                      fixed=fixed, gravity=ph.gravity, damping=ph.damping, supports=supports, tools=tools)
        if ph.stiffness_regions:  # E varies over the tissue: each region's share of the drawn E
            relative = np.asarray(ph.stiffness_regions["relative"], dtype=np.float64)
            model.set_stiffness_map(relative[box_regions(mesh, ph.stiffness_regions["grid"])])
        solver = make_solver(model, ph.integrator, scheme=ph.scheme, safety=ph.safety, newton_tol=ph.newton_tol,
                             max_iterations=ph.max_newton,
                             hessian_scale=ph.hessian_scale if ph.integrator == "quasi_newton" else 1.0,
                             tool_stiffness=getattr(ph, "tool_stiffness", 100.0))
        if ph.integrator == "explicit":
            substeps = solver.substeps(control_dt, model.critical_dt(material=ph.material_for(E_high)))
        else:
            substeps = max(1, math.ceil(control_dt / ph.max_dt - 1e-9))
        return cls(model, solver, substeps)

    @property
    def x(self) -> np.ndarray:
        """Vertex positions of every world, ``(N, n, 3)`` m."""
        return self.state.x

    def reset(self, i: int) -> None:
        """World ``i`` at rest: undeformed, still, nothing held or stuck."""
        self.state.x[i] = self.mesh.vertices
        self.state.v[i] = 0.0
        self.control.clear(i)
        self.reaction[i] = 0.0
        self.stuck[i] = False

    def stick(self, i: int, vertices: np.ndarray) -> None:
        """Hold ``vertices`` of world ``i`` where they rest (adhesion)."""
        self.stuck[i, vertices] = True
        self.control.attach(i, vertices, self.mesh.vertices)

    def unstick(self, i: int) -> None:
        """Release every stuck vertex of world ``i``."""
        self.control.detach(i, np.flatnonzero(self.stuck[i]))
        self.stuck[i] = False

    def release(self, i: int, vertices: np.ndarray) -> None:
        """Release ``vertices`` of world ``i`` from what they are stuck to (those not stuck
        are left as they are: held by an instrument, or free)."""
        v = np.asarray(vertices, dtype=np.int64)
        v = v[self.stuck[i, v]]
        self.control.detach(i, v)
        self.stuck[i, v] = False

    def hold_stiffness(self, i: int, vertices: np.ndarray, share: np.ndarray) -> np.ndarray:
        """The hold stiffness (N/m) of ``vertices`` of world ``i`` held with ``share`` (0..1):
        0 (held exactly) for a whole share, else ``share / (1 - share)`` times
        :data:`HOLD_SPRING_SCALE` times the tissue's own stiffness at the vertex (the mean
        diagonal of the world's rest stiffness matrix there, N/m)."""
        k = np.zeros(len(vertices))
        part = share < 1.0 - 1e-9
        if part.any():
            X = self.mesh.vertices
            diagonal = self.model.fields[i].hessian(X, project=False).diagonal().reshape(-1, 3).mean(axis=1)
            w = share[part]
            k[part] = HOLD_SPRING_SCALE * diagonal[vertices[part]] * w / (1.0 - w)
        return k

    def step(self, dt: float, active: np.ndarray | None = None):
        """Advance every (``active``) world by ``dt`` seconds in :attr:`substeps` solver steps;
        returns the solver's :class:`~heml_gym.StepStats` (converged, diverged, reaction per world)."""
        stats = self.solver.step(self.state, self.state, self.control, dt, substeps=self.substeps, active=active)
        self.reaction = stats.reaction
        return stats
