"""What every solver shares: its report (:class:`StepStats`), the divergence error, and
the checks of its arguments."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba as nb
import numpy as np

from ..control import Control
from ..model import Model
from ..state import State

__all__ = ["StepStats", "WorldStepStats", "SimulationDiverged", "Solver", "checked_tool_stiffness"]


def checked_tool_stiffness(value) -> float:
    """A solver's ``tool_stiffness``: a positive number, or a one-line error naming it."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
        raise ValueError(f"tool_stiffness must be a positive number (units of the tissue's own stiffness), got {value!r}")
    return float(value)


class SimulationDiverged(RuntimeError):
    """A step produced a non-finite or exploding state; the previous state was kept.

    Attributes: ``step`` (index of the failed step), ``elements`` (tets with a non-finite
    or inverted state, at most 20), ``reason`` (text).
    """

    def __init__(self, step: int, reason: str, elements=()):
        self.step = int(step)
        self.reason = reason
        self.elements = np.asarray(elements, dtype=np.int64)[:20]
        where = f"; elements {self.elements.tolist()}" if self.elements.size else ""
        super().__init__(f"simulation diverged at step {self.step}: {reason}{where}")


@dataclass
class WorldStepStats:
    """What a step did to one world.

    ``substeps``: sub-steps taken; ``newton_iterations``: Newton iterations in all (0 for
    explicit); ``residual`` (N): the largest final force residual of its Newton solves,
    ``tolerance`` (N) what it had to reach; ``converged``: every solve reached it;
    ``diverged``: the world went non-finite or exploded (its state was kept);
    ``message``: why, when it diverged or did not converge.
    """

    substeps: int = 0
    newton_iterations: int = 0
    residual: float = 0.0
    tolerance: float = math.inf
    converged: bool = True
    diverged: bool = False
    message: str = ""


@dataclass
class StepStats:
    """What a solver's step did, per world (arrays of length N).

    ``reaction (N, n, 3)``: the force (N) the constraints exerted on fixed and held
    vertices, averaged over the step's sub-steps (the impulse over the step divided by
    its length); 0 on free vertices. Summed over a gripper's vertices it is the grasp
    force on the tissue (the tissue pulls the gripper with ``-R``). ``refinement (N,)``:
    the factor by which the solver had to multiply a world's sub-steps (1: none).
    ``fallback (N,)``: the quasi-Newton solver took the step (or a sub-step of it) again by
    Newton's method, its fallback (``refinement`` then counts the Newton steps).
    ``tool_force (N, T, 3)``: the force (N) each rigid tool (:mod:`heml_gym.tools`) exerts
    on the tissue, averaged over the step's sub-steps (each sub-step's contact penalty at
    its solution, backward Euler's force: the impulse over the step divided by its
    length); None for a model without tools.
    """

    substeps: int
    newton_iterations: np.ndarray
    residual: np.ndarray
    tolerance: np.ndarray
    converged: np.ndarray
    diverged: np.ndarray
    reaction: np.ndarray
    messages: list = field(default_factory=list)
    elements: list = field(default_factory=list)
    refinement: np.ndarray | None = None
    fallback: np.ndarray | None = None
    tool_force: np.ndarray | None = None

    @classmethod
    def empty(cls, n_worlds: int, n_vertices: int, substeps: int) -> "StepStats":
        return cls(substeps=int(substeps), newton_iterations=np.zeros(n_worlds, dtype=np.int64),
                   residual=np.zeros(n_worlds), tolerance=np.full(n_worlds, math.inf),
                   converged=np.ones(n_worlds, dtype=bool), diverged=np.zeros(n_worlds, dtype=bool),
                   reaction=np.zeros((n_worlds, n_vertices, 3)), messages=[""] * n_worlds,
                   elements=[NO_ELEMENTS] * n_worlds,
                   refinement=np.ones(n_worlds, dtype=np.int64), fallback=np.zeros(n_worlds, dtype=bool))

    def world(self, s: int) -> WorldStepStats:
        """The report of world ``s``."""
        return WorldStepStats(self.substeps, int(self.newton_iterations[s]), float(self.residual[s]),
                              float(self.tolerance[s]), bool(self.converged[s]), bool(self.diverged[s]),
                              self.messages[s])


#: The ``StepStats.elements`` of a world that did not diverge (shared, read-only).
NO_ELEMENTS = np.zeros(0, dtype=np.int64)
NO_ELEMENTS.flags.writeable = False


def stiffness_damping(field, x: np.ndarray, v: np.ndarray, f_elastic: np.ndarray, beta: float) -> np.ndarray:
    """The Rayleigh stiffness-damping force ``-beta K(x) v`` (N), as a directional
    difference of the elastic forces ``f_elastic`` at ``x`` along ``v``."""
    vmax = float(np.abs(v).max())
    if not beta or vmax == 0.0:
        return np.zeros_like(x)
    eps = 1e-7 * field.mesh.min_edge_length / vmax
    return beta * (field.forces(x + eps * v) - f_elastic) / eps


class Solver:
    """Base of the solvers: ``step(state_in, state_out, control, dt)`` advances every
    (active) world of the model by ``dt`` seconds and returns :class:`StepStats`."""

    #: whether the solver steps vertices held by springs (``Control.hold_stiffness``)
    takes_hold_springs = False
    #: whether it steps jaws on a free wrist (``Control.turns``)
    takes_wrist = False
    #: whether it steps rigid tools (``Model.tools``)
    takes_tools = False

    def __init__(self, model: Model, max_speed: float = 1e3):
        if not isinstance(model, Model):
            raise TypeError(f"model must be a heml_gym.Model, got {type(model).__name__}")
        if len(model.tools) and not self.takes_tools:
            raise ValueError(f"tools: {type(self).__name__} does not step rigid tools yet; the quasi_newton and "
                             "implicit integrators and the static solver do")
        max_speed = float(max_speed)
        if not (math.isfinite(max_speed) and max_speed > 0):
            raise ValueError(f"max_speed must be a positive number of m/s, got {max_speed}")
        self.model = model
        self.max_speed = max_speed

    def forget(self, worlds) -> None:
        """Drop what the solver carries from step to step for ``worlds`` (indices): lagged
        factorisations, quasi-Newton curvature pairs. A world started afresh (an episode
        reset) is then stepped exactly as by a new solver: same seed, same trajectory.
        Solvers that carry nothing keep this no-op."""

    def _check(self, state_in: State, state_out: State, control: Control, dt: float, active) -> tuple:
        m = self.model
        shape = (m.n_worlds, m.n_vertices, 3)
        for name, s in (("state_in", state_in), ("state_out", state_out)):
            if not isinstance(s, State):
                raise TypeError(f"{name} must be a heml_gym.State, got {type(s).__name__}")
            if s.x.shape != shape:
                raise ValueError(f"{name} holds {s.x.shape}, the model needs {shape}")
        if not isinstance(control, Control):
            raise TypeError(f"control must be a heml_gym.Control, got {type(control).__name__}")
        if control.targets.shape != shape:
            raise ValueError(f"control holds {control.targets.shape}, the model needs {shape}")
        if not self.takes_wrist and control.turns.any():
            raise ValueError(f"control.turns: {type(self).__name__} does not step jaws on a free wrist; the "
                             "quasi-Newton solver does (physics integrator 'quasi_newton')")
        if not self.takes_hold_springs and control.spring_held().any():
            raise ValueError(f"control.hold_stiffness: {type(self).__name__} holds vertices exactly only; vertices "
                             "held by springs (a part of the jaws' grip) need a solver that steps them")
        dt = float(dt)
        if not math.isfinite(dt) or dt <= 0:
            raise ValueError(f"dt must be a positive number of seconds, got {dt}")
        if active is None:
            active = np.ones(m.n_worlds, dtype=bool)
        else:
            active = np.asarray(active, dtype=bool)
            if active.shape != (m.n_worlds,):
                raise ValueError(f"active must be a ({m.n_worlds},) mask, got shape {active.shape}")
        if state_out is not state_in:
            state_out.assign(state_in)
        return dt, active

    def tool_penalty_stiffness(self) -> np.ndarray:
        """``(N, n)`` N/m: the rigid tools' contact penalty at each vertex of each world,
        ``tool_stiffness (lambda + mu) V_i^(1/3)`` (``V_i``: the vertex's share of the
        volume): a multiple of the tissue's own stiffness there, whatever the step length,
        so that the force a tool reports is within about ``1 / tool_stiffness`` of the
        force it would take to hold the tissue exactly (a slab squeezed by a paddle, at the
        default 100: within 1 %)."""
        m = self.model
        cached = getattr(self, "_tool_k", None)
        if cached is None or cached[0] != m.material_revision:
            modulus = np.array([mat.lame_lambda + mat.shear_modulus for mat in m.materials])
            k = self.tool_stiffness * modulus[:, None] * np.cbrt(m.mesh.vertex_volumes)[None, :]
            self._tool_k = cached = (m.material_revision, np.ascontiguousarray(k))
        return cached[1]

    def force_scale(self, world: int, control: Control) -> float:
        """Force (N) the solver tolerances of ``world`` are relative to: its weight plus its
        external load, else (weightless and unloaded) ``E h_min^2``."""
        m = self.model
        load = float(np.linalg.norm(m.gravity) * m.mass.sum() + np.abs(control.external_forces[world]).sum())
        if load > 0:
            return load
        return m.materials[world].young_modulus * m.mesh.min_edge_length ** 2

    def force_scales(self, control: Control) -> np.ndarray:
        """:meth:`force_scale` of every world, ``(N,)`` N (the same numbers, in one pass)."""
        m = self.model
        weight = np.linalg.norm(m.gravity) * m.mass.sum()
        if not control.external_forces.any():  # (+ 0.0: the same numbers)
            return np.full(m.n_worlds, float(weight)) if weight > 0 else np.array(
                [self.force_scale(s, control) for s in range(m.n_worlds)])
        load = weight + np.abs(control.external_forces).reshape(m.n_worlds, -1).sum(axis=1)
        if np.all(load > 0):
            return load
        return np.array([load[s] if load[s] > 0 else self.force_scale(s, control) for s in range(m.n_worlds)])

    def suspect_worlds(self, x: np.ndarray, v: np.ndarray, worlds: np.ndarray) -> np.ndarray:
        """Those of ``worlds`` (indices) whose ``x, v`` ``(N, n, 3)`` :meth:`divergence`
        may flag (a non-finite value or a vertex above ``max_speed``); checking only
        them gives the same verdicts as checking every world."""
        worlds = np.asarray(worlds, dtype=np.int64)
        flagged = np.zeros(len(worlds), dtype=np.bool_)
        _flag_suspects(x, v, worlds, self.max_speed, flagged)
        return worlds[flagged]

    def divergence(self, x: np.ndarray, v: np.ndarray) -> tuple[str, np.ndarray]:
        """Why one world's ``x, v`` ``(n, 3)`` counts as diverged, and the tets touching
        its bad vertices ("" and none if it does not)."""
        bad_vertices = ~(np.isfinite(x).all(axis=1) & np.isfinite(v).all(axis=1))
        with np.errstate(all="ignore"):
            speed = np.sqrt((v * v).sum(axis=1))
        too_fast = speed > self.max_speed
        if not (bad_vertices.any() or too_fast.any()):
            return "", NO_ELEMENTS
        bad = bad_vertices | too_fast
        tets = np.flatnonzero(bad[self.model.mesh.tets].any(axis=1))
        what = "non-finite positions or velocities" if bad_vertices.any() else (
            f"speed {np.nanmax(speed):.3g} m/s above max_speed {self.max_speed:g} m/s")
        return what, tets


@nb.njit(cache=True)
def _flag_suspects(x, v, worlds, max_speed, flagged):
    """``flagged[k]``: world ``worlds[k]`` of ``x, v (N, n, 3)`` has a non-finite value or
    a vertex faster than ``max_speed`` (m/s), compared as squares with a relative margin
    of 1e-12 so that no vertex :meth:`Solver.divergence` calls too fast is missed."""
    limit = max_speed * max_speed * (1.0 - 1e-12)
    for k in range(worlds.shape[0]):
        s = worlds[k]
        for i in range(x.shape[1]):
            speed2 = v[s, i, 0] * v[s, i, 0] + v[s, i, 1] * v[s, i, 1] + v[s, i, 2] * v[s, i, 2]
            position = x[s, i, 0] + x[s, i, 1] + x[s, i, 2]
            if not (np.isfinite(speed2) and np.isfinite(position) and speed2 <= limit):
                flagged[k] = True
                break
