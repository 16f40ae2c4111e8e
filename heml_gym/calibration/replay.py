"""Replay a recorded control on one world of a model, and differentiate the replay by the adjoint method.

A :class:`ControlLog` is what drove a scene: for each control step, which vertices were
held (the jaws' grip, an attachment) and where they were driven. :class:`Replay` steps
the scene through it by backward Euler, each sub-step minimised by Newton's method with
the field's exact Hessian to a tight tolerance (the same incremental potential, supports
and sub-step bookkeeping as :class:`~heml_gym.solvers.QuasiNewtonSolver`: on a HEML
model its kernels, through :class:`~heml_gym.solvers.substep.HemlSubstep`; on any other
field with a Hessian, such as quadratic tets, the same sub-step in NumPy,
:class:`~heml_gym.solvers.substep.FieldSubstep`), and records what the reverse pass needs.

Gradients. A converged sub-step satisfies ``grad Phi(y; x_hat, p, theta) = 0`` on the
free vertices, so by the implicit function theorem ``dy = H^-1 (c M dx_hat - H_fp dp +
df/dtheta dtheta)`` with ``H`` the potential's Hessian at ``y`` (the elastic Hessian
plus ``c M`` plus the support penalty's). :meth:`Replay.gradient` runs that backwards:
one sparse solve with ``H`` per sub-step (Hessians evaluated on the stored states), through
the support projection (a vertex pushed into a plane goes onto it and loses its inward
velocity: a fixed projection for the step's contact set), the velocities, the held
vertices' prescribed path and the reaction on them (the step-mean force the jaws feel).
``df/dtheta``, the elastic forces' derivative in a material constant at a fixed
configuration, is a central difference in the constant (exact up to rounding for laws
linear in their constants, as Neo-Hookean, St Venant-Kirchhoff and Mooney-Rivlin are in
``mu`` and ``lambda`` and so in ``E``, and every law in a region's modulus when E varies
over the body, ``stiffness_of``; within 1e-9 relative for ``nu``). Constants of the
dynamics (``dynamics_of``: the density, which scales every lumped mass, their weight and
the support penalty, and the mass damping ``alpha``) enter the sub-step's gradient and the
reactions on the held vertices, not the elastic forces: their derivatives are central
differences of those, at the sub-step's stored state.

Jaws on a free wrist (``ControlLog.wrist``): the held patch's angle about the jaws' axis
is one more unknown of each sub-step (:class:`~heml_gym.calibration.wrist.WristSubstep`:
Newton on the free vertices and the angle together, with the bordered Hessian), and the
reverse pass solves with that bordered Hessian, so the patch's turn, its unturned path
and the place where the jaws took it are all differentiated.

Only backward Euler (BDF2's two-step history is not differentiated). Units: m, s, N, Pa.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
import scipy.sparse.linalg as spla

from ..forces import HemlForce
from ..kernel_data import world_law
from ..linear_solvers import DiagonalAdd, DiagonalBlockAdd, EnvelopeCholesky, FreeSubmatrix, LaggedFactorPCG
from ..materials import Material
from ..model import Model
from ..solvers import kernels_quasi_newton as kq
from ..solvers.newton import linear_response, minimize
from ..solvers.substep import FieldSubstep, HemlSubstep
from .wrist import WristSubstep, rotation

__all__ = ["ControlLog", "Replay", "ReplayResult", "ReplayError"]


class ReplayError(ValueError):
    """A replay that cannot be made or differentiated (bad log, unconverged step)."""


@dataclass
class ControlLog:
    """What drove one scene, control step by control step.

    Attributes
    ----------
    kinematic : (T, n) bool
        The vertices held during each control step (gripper and attachments; the model's
        fixed vertices are held anyway).
    targets : (T, n, 3) float, m
        Where the held vertices are at the end of each control step (they move there in
        a straight line over the step's sub-steps).
    dt : float, s
        The control step.
    substeps : int
        Backward Euler sub-steps per control step.
    x0, v0 : (n, 3) float, m and m/s
        The state the replay starts from.
    gripped : (T, n) bool, optional
        Which held vertices the gripper holds (its force is minus their reaction's sum);
        default: the kinematic ones.
    wrist : (T, n) bool, optional
        Held vertices that turn with the jaws about their axis, freely: a patch held
        rigidly by jaws on a free wrist (:mod:`~heml_gym.calibration.wrist`). Their
        ``targets`` are their places without the turn; the turn's angle is where the
        torque on them about the axis vanishes, found with each sub-step. A control step
        whose wrist set differs from the previous one's grasps anew: the patch is held
        where it is, unturned. Default: none.
    wrist_axis : (3,) float
        The jaws' axis (a direction; normalised).
    wrist_points : (T + 1, 3) float, m
        A point on the axis at each control step's start and (last row) the log's end; it
        moves in a straight line over a step's sub-steps.
    """

    kinematic: np.ndarray
    targets: np.ndarray
    dt: float
    substeps: int
    x0: np.ndarray
    v0: np.ndarray
    gripped: np.ndarray | None = None
    wrist: np.ndarray | None = None
    wrist_axis: np.ndarray | None = None
    wrist_points: np.ndarray | None = None

    def __post_init__(self):
        self.kinematic = np.asarray(self.kinematic, dtype=bool)
        self.targets = np.asarray(self.targets, dtype=np.float64)
        self.x0 = np.asarray(self.x0, dtype=np.float64)
        self.v0 = np.asarray(self.v0, dtype=np.float64)
        if self.kinematic.ndim != 2:
            raise ReplayError(f"kinematic: must be (T, n) bool, got shape {self.kinematic.shape}")
        T, n = self.kinematic.shape
        for name, value, shape in (("targets", self.targets, (T, n, 3)), ("x0", self.x0, (n, 3)),
                                   ("v0", self.v0, (n, 3))):
            if value.shape != shape:
                raise ReplayError(f"{name}: must have shape {shape}, got {value.shape}")
            if not np.all(np.isfinite(value)):
                raise ReplayError(f"{name}: must be finite")
        self.gripped = self.kinematic.copy() if self.gripped is None else np.asarray(self.gripped, dtype=bool)
        if self.gripped.shape != (T, n):
            raise ReplayError(f"gripped: must have shape {(T, n)}, got {self.gripped.shape}")
        self._check_wrist(T, n)
        if not (isinstance(self.dt, (int, float)) and math.isfinite(self.dt) and self.dt > 0):
            raise ReplayError(f"dt: must be a positive number of seconds, got {self.dt!r}")
        if isinstance(self.substeps, bool) or not isinstance(self.substeps, (int, np.integer)) or self.substeps < 1:
            raise ReplayError(f"substeps: must be an integer >= 1, got {self.substeps!r}")

    def _check_wrist(self, T: int, n: int) -> None:
        if self.wrist is None:
            if self.wrist_axis is not None or self.wrist_points is not None:
                raise ReplayError("wrist_axis, wrist_points: give them with wrist (the vertices that turn)")
            return
        self.wrist = np.asarray(self.wrist, dtype=bool)
        if self.wrist.shape != (T, n):
            raise ReplayError(f"wrist: must have shape {(T, n)}, got {self.wrist.shape}")
        if np.any(self.wrist & ~self.kinematic):
            raise ReplayError("wrist: every vertex that turns with the jaws must be held (kinematic) in that step")
        if self.wrist_axis is None or self.wrist_points is None:
            raise ReplayError("wrist: give wrist_axis (3,) and wrist_points (T + 1, 3) with it")
        axis = np.asarray(self.wrist_axis, dtype=np.float64)
        norm = float(np.linalg.norm(axis)) if axis.shape == (3,) and np.all(np.isfinite(axis)) else 0.0
        if norm < 1e-12:
            raise ReplayError(f"wrist_axis: must be a finite nonzero (3,) vector, got {self.wrist_axis!r}")
        self.wrist_axis = axis / norm
        self.wrist_points = np.asarray(self.wrist_points, dtype=np.float64)
        if self.wrist_points.shape != (T + 1, 3) or not np.all(np.isfinite(self.wrist_points)):
            raise ReplayError(f"wrist_points: must be finite with shape {(T + 1, 3)}, got {self.wrist_points.shape}")

    @property
    def steps(self) -> int:
        return self.kinematic.shape[0]

    def wrist_at(self, t: int) -> np.ndarray:
        """``(n,)`` bool: the vertices that turn with the jaws in control step ``t``."""
        return np.zeros(self.kinematic.shape[1], dtype=bool) if self.wrist is None else self.wrist[t]

    def grasps_anew(self, t: int) -> bool:
        """Whether control step ``t`` starts a wrist grasp (its set differs from step ``t - 1``'s)."""
        here = self.wrist_at(t)
        return bool(here.any()) and (t == 0 or not np.array_equal(here, self.wrist_at(t - 1)))


@dataclass
class ReplayResult:
    """A replay's trajectory: ``x`` (T + 1, n, 3) m, the positions at the control steps
    (``x[0]``: the start); ``force`` (T, 3) N, the step-mean force the tissue pulls the
    gripper with; ``iterations`` (Newton, in all); ``residual`` the largest sub-step
    residual against its ``tolerance`` (N)."""

    x: np.ndarray
    force: np.ndarray
    iterations: int
    residual: float
    tolerance: float
    tape: list = field(default_factory=list, repr=False)


class Replay:
    """Replay a :class:`ControlLog` on world ``world`` of ``model`` for material constants
    ``theta``, and give the gradient of a loss on the trajectory in ``theta``.

    Parameters
    ----------
    model : Model
        A model on any force field with a Hessian (any law); its world ``world``'s material is replaced by
        ``material_of(theta)`` for each replay.
    log : ControlLog
    material_of : callable
        ``theta`` (a sequence of floats, e.g. ``(E, nu)``) -> :class:`~heml_gym.materials.Material`.
    steps : sequence of float, optional
        The central-difference step of each constant for ``df/dtheta`` (default: 1e-6 of
        its value, or 1e-6 when it is 0).
    tol : float
        Each sub-step's force residual (N) on the free vertices is brought below ``tol``
        times the tissue's weight (the solver's own tolerance is 3e-3 of it: the
        gradients need the converged step they differentiate).
    contact_stiffness : float
        The supports' penalty, as :class:`~heml_gym.solvers.QuasiNewtonSolver`'s.
    dynamics_of : callable, optional
        ``theta`` -> ``(density, alpha)``: the tissue's density (kg/m^3; the lumped masses
        are ``density`` times each vertex's share of the volume) and the mass-proportional
        damping (1/s) to replay with; default: the model's own, whatever ``theta``.
    max_iter : int
        Newton iterations per sub-step at most (a sub-step that stops above its tolerance
        is a :class:`ReplayError`).
    stiffness_of : callable, optional
        ``theta`` -> ``(m,)`` each tet's Young's modulus relative to ``material_of(theta)``'s
        (:meth:`~heml_gym.Model.set_stiffness_map`): a modulus that varies over the body,
        e.g. one per region of a coarse grid (HEML models only). Default: the model's own
        map, whatever ``theta``.
    """

    def __init__(self, model: Model, log: ControlLog, material_of: Callable[[Sequence[float]], Material],
                 world: int = 0, steps: Sequence[float] | None = None, tol: float = 1e-8,
                 contact_stiffness: float = 1000.0, max_iter: int = 60,
                 dynamics_of: Callable[[Sequence[float]], tuple[float, float]] | None = None,
                 stiffness_of: Callable[[Sequence[float]], np.ndarray] | None = None):
        if not isinstance(log, ControlLog):
            raise TypeError(f"log must be a ControlLog, got {type(log).__name__}")
        if log.kinematic.shape[1] != model.n_vertices:
            raise ReplayError(f"log: {log.kinematic.shape[1]} vertices, the model has {model.n_vertices}")
        if model.supports.kernel_args().grids.shape[0]:
            raise ReplayError("replays differentiate plane supports only (a mesh support's curvature is not)")
        if not model.field.has_hessian:
            raise ReplayError(f"replays differentiate force fields with a Hessian, the model's field "
                              f"{type(model.field).__name__} has none")
        if log.wrist is not None and np.any(log.wrist & model.fixed[None, :]):
            raise ReplayError("log.wrist: a vertex the model fixes cannot turn with the jaws")
        if stiffness_of is not None and not isinstance(model.field, HemlForce):
            raise ReplayError(f"stiffness_of: a modulus that varies over the body needs a HEML model, the model's "
                              f"field is {type(model.field).__name__}")
        self.model, self.log, self.material_of, self.world = model, log, material_of, int(world)
        self.dynamics_of, self.stiffness_of = dynamics_of, stiffness_of
        #: HEML's sub-steps run on the quasi-Newton solver's kernels, any other field's in NumPy
        self._heml = isinstance(model.field, HemlForce)
        self._mass, self._alpha = model.mass, float(model.damping.alpha)  # the replay's (see dynamics_of)
        self._body = model.heml_body() if self._heml else None  # the kernels' body, with the replay's mass, alpha
        #: each sub-step's converged positions of the latest run: the next run's Newton may
        #: start there (a fit's successive constants are close, so are their trajectories)
        self._previous: list[tuple[np.ndarray, float]] = []  # (positions, wrist angle)
        self.steps = None if steps is None else np.asarray(steps, dtype=np.float64)
        self.tol = float(tol) * max(float(np.linalg.norm(model.gravity) * model.mass.sum()), 1e-12)
        self.contact_stiffness = float(contact_stiffness)
        self.max_iter = int(max_iter)
        self._submatrix = FreeSubmatrix()
        self._add_diagonal = DiagonalAdd()
        self._add_blocks = DiagonalBlockAdd()
        # Newton's linear solves: CG preconditioned by a lagged Cholesky factor (refactorised
        # when CG needs more than 30 iterations or the held set changes)
        self._linear = LaggedFactorPCG(rtol=1e-10, max_iter=30, factorization="cholesky")
        self._cholesky = None

    # ------------------------------------------------------------------ helpers
    def forget(self) -> None:
        """Start the next :meth:`run`'s Newton solves afresh, not from the latest run's
        trajectory (a cold replay: what timing one forward simulation should measure)."""
        self._previous = []

    def _set(self, theta) -> None:
        theta = tuple(float(t) for t in theta)
        if self.stiffness_of is not None:
            self.model.set_stiffness_map(self.stiffness_of(theta))
        self.model.set_material(self.world, self.material_of(theta))
        self._mass, self._alpha = self.model.mass, float(self.model.damping.alpha)
        if self.dynamics_of is not None:
            density, alpha = (float(v) for v in self.dynamics_of(theta))
            if not (math.isfinite(density) and density > 0 and math.isfinite(alpha) and alpha >= 0):
                raise ReplayError(f"dynamics_of: density must be > 0 kg/m^3 and alpha >= 0 1/s, got "
                                  f"{density}, {alpha}")
            self._mass, self._alpha = density * self.model.mesh.vertex_volumes, alpha
        if self._heml:
            self._body = self.model.heml_body()._replace(mass=self._mass, alpha=self._alpha)

    def _dynamic_constants(self, theta) -> list[int]:
        """The indices of ``theta`` that change the density or the damping."""
        if self.dynamics_of is None:
            return []
        base = tuple(self.dynamics_of(tuple(theta)))
        out = []
        for j in range(len(theta)):
            shifted = list(theta)
            shifted[j] = shifted[j] * (1.0 + 1e-3) + 1e-3
            if tuple(self.dynamics_of(tuple(shifted))) != base:
                out.append(j)
        return out

    def _substep(self, t: int, h: float, fraction: float):
        """A sub-step of control step ``t`` (every held vertex held exactly: a replay holds
        no springs), for the constants last set: a :class:`~heml_gym.solvers.substep.HemlSubstep`
        on a HEML model, else a :class:`~heml_gym.solvers.substep.FieldSubstep`."""
        m, log = self.model, self.log
        field = m.fields[self.world]
        if self._heml:
            return HemlSubstep(field, self._body, self._law(), m.supports.kernel_args(), self.contact_stiffness, h,
                               log.kinematic[t], log.targets[t], fraction, self._add_diagonal, self._add_blocks)
        return FieldSubstep(field, self._mass, self._alpha, m.gravity, m.fixed, m.supports, self.contact_stiffness,
                            m.mesh.tets, h, log.kinematic[t], log.targets[t], fraction, self._add_diagonal,
                            self._add_blocks)

    def _law(self):
        return world_law(self.model.heml_laws(), self.world)

    def _forces(self, x: np.ndarray) -> np.ndarray:
        """The elastic forces (N) at ``x`` for the constants last set."""
        if not self._heml:
            return self.model.fields[self.world].forces(x)
        f = np.zeros_like(x)
        kq.elastic_forces(x, f, self.model.heml_body(), self._law())
        return f

    def _difference_steps(self, theta: np.ndarray) -> np.ndarray:
        """Each constant's central-difference step (``steps``, else 1e-6 of its value)."""
        return self.steps if self.steps is not None else np.where(theta != 0, 1e-6 * np.abs(theta), 1e-6)

    def _force_derivatives(self, theta, configurations: list[np.ndarray], skip=()) -> list[np.ndarray]:
        """``df/dtheta_j`` (N per unit of the constant) at each configuration: ``(k, n, 3)``;
        the constants ``skip`` (indices) are left 0."""
        theta = np.asarray(theta, dtype=np.float64)
        steps = self._difference_steps(theta)
        out = [np.zeros((len(theta),) + configurations[0].shape) for _ in configurations]
        try:
            for j in range(len(theta)):
                if j in skip:
                    continue
                for sign in (1.0, -1.0):
                    shifted = theta.copy()
                    shifted[j] += sign * steps[j]
                    self._set(shifted)
                    for d, x in zip(out, configurations):
                        d[j] += sign * self._forces(x) / (2.0 * steps[j])
        finally:
            self._set(theta)
        return out

    def _elastic_hessian(self, x: np.ndarray):
        return self.model.fields[self.world].hessian(x, project=False)

    # ------------------------------------------------------------------ forward
    def _wrist_scale(self, t: int, wrist: np.ndarray) -> float:
        """``L`` (m): the root-mean-square distance from the jaws' axis of the patch that
        turns in control step ``t`` (from the log's targets: the same for every ``theta``)."""
        log = self.log
        arms = log.targets[t][wrist] - log.wrist_points[t + 1]
        arms -= (arms @ log.wrist_axis)[:, None] * log.wrist_axis
        return max(float(np.sqrt(np.mean(np.sum(arms * arms, axis=1)))), 1e-4)

    def run(self, theta) -> ReplayResult:
        """Replay the log with material constants ``theta``."""
        self._set(theta)
        m, log = self.model, self.log
        n = m.n_vertices
        h = log.dt / log.substeps
        x, v = log.x0.copy(), log.v0.copy()
        xs, forces = [x.copy()], []
        tape, iterations, worst = [], 0, 0.0
        previous, self._previous = self._previous, []
        path, angle, scale = x.copy(), 0.0, 1.0  # the wrist: its patch's unturned places, its angle (rad)
        for t in range(log.steps):
            r_prev = np.zeros((n, 3))
            reaction = np.zeros((n, 3))
            start = x.copy(), v.copy()
            wrist = log.wrist_at(t)
            anew = log.grasps_anew(t)
            if anew:  # the jaws close on the patch where it is: unturned
                path, angle, scale = x.copy(), 0.0, self._wrist_scale(t, wrist)
            point = log.wrist_points[t].copy() if wrist.any() else None
            for k in range(1, log.substeps + 1):
                fraction = 1.0 / (log.substeps - k + 1)
                step = self._substep(t, h, fraction)
                x_n = x.copy()
                step.begin(x, v, r_prev if k == 1 else None)
                held = step.held
                turn = None
                if wrist.any():
                    path[wrist] += (log.targets[t][wrist] - path[wrist]) * fraction
                    point += (log.wrist_points[t + 1] - point) * fraction
                    turn = WristSubstep(step, wrist, log.wrist_axis, point, path, scale, self._forces, self._mass)
                    x[wrist] = turn.positions(turn.extend(x, angle))[wrist]
                    potential, hessian, gradient, free = turn.potential, turn.hessian, turn.gradient, turn.free
                else:
                    potential, hessian, free = step.potential, step.hessian, np.repeat(~held, 3)

                    def gradient(y, step=step):
                        return step.gradient(y).reshape(-1)

                def unknowns(y, turned, turn=turn):  # Newton's vector: y, and with a wrist its angle
                    return y if turn is None else turn.extend(y, turned)

                y0, best, warm = unknowns(x.copy(), angle), math.inf, False
                starts = [(step.x_n + h * step.v_n, angle), (step.x_n.copy(), angle)]
                if len(previous) > len(self._previous):  # where the previous run's Newton ended
                    y_end, angle_end = previous[len(self._previous)]
                    starts.append((y_end.copy(), angle_end))
                for i, (candidate, turned) in enumerate(starts):  # the lowest-potential start
                    candidate[held] = x[held]
                    candidate = unknowns(candidate, turned)
                    phi = potential(candidate)
                    if phi < best:
                        y0, best, warm = candidate, phi, i == 2
                if not math.isfinite(best):  # each turns a tet inside out: the held vertices moved past a neighbour
                    following = linear_response(step.hessian(step.x_n, True).tocsr(), step.x_n, x, held)
                    if following is not None:
                        y0 = unknowns(following, angle)
                with np.errstate(all="ignore"):
                    result = minimize(y0, potential, gradient, hessian, free, self.tol, self.max_iter,
                                      self._submatrix, self._linear, (free.tobytes(), h), stall_limit=None,
                                      min_iter=2 if warm else 0)  # (a warm start may lie within tol already)
                if not (result.finite and result.converged):
                    raise ReplayError(f"control step {t}, sub-step {k}: Newton stopped at a force residual of "
                                      f"{result.residual:.3g} N, above the replay's tolerance of {self.tol:.3g} N "
                                      f"({result.iterations} iterations): the material or the log is outside "
                                      "what the scene can follow")
                iterations += result.iterations
                worst = max(worst, result.residual)
                if turn is not None:
                    y, angle = turn.positions(result.x), turn.angle(result.x)
                else:
                    y = result.x.reshape(n, 3)
                self._previous.append((y.copy(), angle))
                x[:] = y
                ends = step.finish(x, v, reaction, r_prev)
                tape.append(dict(t=t, k=k, h=h, c=step.c, fraction=fraction, x_n=x_n, v_n=step.v_n.copy(),
                                 x_hat=step.x_hat.copy(), y=y.copy(), z=x.copy(), held=held, step=step,
                                 start=start if k == 1 else None, wrist=wrist, turn=turn,
                                 u=None if turn is None else result.x.copy(), angle=angle,
                                 grasp_start=anew and k == 1, **ends))
            reaction /= log.substeps
            forces.append(-reaction[log.gripped[t]].sum(axis=0))
            xs.append(x.copy())
        return ReplayResult(np.array(xs), np.array(forces), iterations, worst, self.tol, tape)

    def _solve(self, a, b: np.ndarray) -> np.ndarray:
        """``a^-1 b`` for the step's Hessian on the free dofs: a sparse Cholesky factor (the
        Hessian at a minimum is positive definite), else an LU solve."""
        try:
            if self._cholesky is None:
                self._cholesky = EnvelopeCholesky(a)
            else:
                self._cholesky.factor(a)  # (a new pattern is analysed afresh)
            x = self._cholesky.solve(b)
            if np.all(np.isfinite(x)):
                return x
        except (ValueError, np.linalg.LinAlgError):
            pass
        self._cholesky = None
        return spla.spsolve(a.tocsc(), b)

    # ------------------------------------------------------------------ reverse
    def _substep_gradient(self, e) -> np.ndarray:
        """The incremental potential's gradient (N) at the sub-step's minimiser ``e["y"]``,
        for the constants last set (its start, targets and sub-step as recorded)."""
        step = self._substep(e["t"], e["h"], e["fraction"])
        step.begin(e["x_n"].copy(), e["v_n"].copy())
        return step.gradient(e["y"])

    def _end_reaction(self, e) -> np.ndarray:
        """``m (v - v_n)/h - f(z) - m g + alpha m v`` (N): the end reaction on every vertex
        (the held rows are the reaction), for the constants last set."""
        mass, alpha = self._mass[:, None], self._alpha
        v = (e["z"] - e["x_n"]) / e["h"]  # (held rows: their prescribed path)
        return mass * (v - e["v_n"]) / e["h"] - self._forces(e["z"]) - mass * self.model.gravity + alpha * mass * v

    def _start_reaction(self, e) -> np.ndarray:
        """``-(f(x) + m g - alpha m v)`` (N) at the control step's start ``e["start"]``."""
        mass, alpha = self._mass[:, None], self._alpha
        x, v = e["start"]
        return -(self._forces(x) + mass * self.model.gravity - alpha * mass * v)

    def _dynamic_derivatives(self, theta, j, tape, dz, dy, dstart) -> None:
        """Add into column ``j`` (left 0 by :meth:`_force_derivatives`) of ``dz``, ``dy``,
        ``dstart``, for a constant of the dynamics: minus the derivatives of the end
        reaction, the sub-step gradient and the start reaction."""
        theta = np.asarray(theta, dtype=np.float64)
        step = self._difference_steps(theta)[j]
        try:
            for sign in (1.0, -1.0):
                shifted = theta.copy()
                shifted[j] += sign * step
                self._set(shifted)
                scale = -sign / (2.0 * step)
                for idx, e in enumerate(tape):
                    dz[idx][j] += scale * self._end_reaction(e)
                    dy[idx][j] += scale * self._substep_gradient(e)
                    if dstart[idx] is not None:
                        dstart[idx][j] += scale * self._start_reaction(e)
        finally:
            self._set(theta)

    def gradient(self, theta, result: ReplayResult, x_bar: np.ndarray, force_bar: np.ndarray | None = None
                 ) -> np.ndarray:
        """``dL/dtheta`` for a loss ``L`` whose derivative is ``x_bar`` (T + 1, n, 3) in the
        positions ``result.x`` and ``force_bar`` (T, 3) in ``result.force``, by the adjoint
        method through every sub-step of ``result`` (a :meth:`run` with the same ``theta``)."""
        theta = np.asarray(theta, dtype=np.float64)
        log, m = self.log, self.model
        n = m.n_vertices
        T, S = log.steps, log.substeps
        x_bar = np.asarray(x_bar, dtype=np.float64)
        if x_bar.shape != (T + 1, n, 3):
            raise ReplayError(f"x_bar: must have shape {(T + 1, n, 3)}, got {x_bar.shape}")
        force_bar = np.zeros((T, 3)) if force_bar is None else np.asarray(force_bar, dtype=np.float64)
        tape = result.tape
        configurations = [e["z"] for e in tape] + [e["y"] for e in tape] + \
                         [e["start"][0] for e in tape if e["start"] is not None]
        dynamic = self._dynamic_constants(theta)
        dfs = self._force_derivatives(theta, configurations, skip=dynamic)
        dz = dfs[:len(tape)]
        dy = dfs[len(tape):2 * len(tape)]
        dstart = iter(dfs[2 * len(tape):])
        dstart = [next(dstart) if e["start"] is not None else None for e in tape]
        # constants of the dynamics: the same three derivatives (minus the sub-step
        # gradient's, minus the end and start reactions') by central differences
        for j in dynamic:
            self._dynamic_derivatives(theta, j, tape, dz, dy, dstart)
        self._set(theta)
        mass = self._mass[:, None]
        alpha = self._alpha
        theta_bar = np.zeros(len(theta))
        zb = x_bar[T].copy()  # adjoint of the positions after the current sub-step
        vb = np.zeros((n, 3))  # and of the velocities
        r_bar = np.zeros((n, 3))  # of the current sub-step's end reaction (held rows)
        path_bar = np.zeros((n, 3))  # of the wrist's patch's unturned places
        for idx in range(len(tape) - 1, -1, -1):
            e = tape[idx]
            t, k, h, c = e["t"], e["k"], e["h"], e["c"]
            held, gripped = e["held"], log.gripped[t]
            if k == S:  # the control step's end: its force and reaction adjoints start here
                # force = -(1/S) sum_k 0.5 (r_{k-1} + r_k) over the gripped rows
                per_r = np.zeros((n, 3))
                per_r[gripped] = -force_bar[t] / S
                r_bar = 0.5 * per_r  # r_S's share (r_k for k < S gets per_r in all, below)
                r_carry = per_r
            # ---- the end reaction r_k = m (v - v_n)/h - f(z) - load + alpha m v on held rows
            rb = np.where(held[:, None], r_bar, 0.0)
            if rb.any():
                hz = self._elastic_hessian(e["z"])
                zb += (hz @ rb.reshape(-1)).reshape(n, 3)  # -df/dz = H
                theta_bar -= np.einsum("jnd,nd->j", dz[idx], rb)
                vb += np.where(held[:, None], rb * mass * (1.0 / h + alpha), 0.0)
                vb_n_from_r = np.where(held[:, None], -rb * mass / h, 0.0)
            else:
                vb_n_from_r = np.zeros((n, 3))
            # ---- velocities: v = Q (z - x_n)/h (free), (z - x_n)/h (held)
            nrm = e["normal"]
            vq = vb.copy()
            st = e["stopped"]
            if st.any():
                vq[st] -= np.einsum("id,id->i", vq[st], nrm[st])[:, None] * nrm[st]
            zb += vq / h
            xnb = -vq / h + 0.0
            vnb = vb_n_from_r
            # ---- projection onto the support: z = P y (projected free rows), z = y (free), z = p (held)
            yb = np.where(held[:, None], 0.0, zb)
            pr = e["projected"]
            if pr.any():
                yb[pr] -= np.einsum("id,id->i", yb[pr], nrm[pr])[:, None] * nrm[pr]
            pb = np.where(held[:, None], zb, 0.0)
            # ---- the minimisation: H w = y_bar on the free rows (and the wrist's angle)
            free = np.repeat(~held, 3)
            turn, wrist = e["turn"], e["wrist"]
            s_bar = 0.0 if turn is None else float(np.sum(pb[wrist] * turn.lever(e["y"])))  # dz_W/ds
            if (free.any() and yb.any()) or s_bar != 0.0:
                if turn is None:
                    hess = e["step"].hessian(e["y"], False)
                    w_free = self._solve(self._submatrix(hess, free), yb.reshape(-1)[free])
                    w = np.zeros(3 * n)
                    w[free] = w_free
                else:
                    hess = turn.hessian(e["u"], False)
                    w_free = self._solve(self._submatrix(hess, turn.free), np.append(yb.reshape(-1), s_bar)[turn.free])
                    w = np.zeros(3 * n + 1)
                    w[turn.free] = w_free
                if not np.all(np.isfinite(w_free)):
                    raise ReplayError(f"control step {t}, sub-step {k}: the step's Hessian is singular")
                w_s = float(w[-1]) if turn is not None else 0.0
                w = w[:3 * n].reshape(n, 3)
                xhat_b = c * mass * w
                if turn is not None:  # the turn moves the patch: w_s dz_W/ds on its rows
                    w[wrist] = w_s * turn.lever(e["y"])
                theta_bar += np.einsum("jnd,nd->j", dy[idx], w)
                he = self._elastic_hessian(e["y"])
                pb -= np.where(held[:, None], (he @ w.reshape(-1)).reshape(n, 3), 0.0)
                if turn is not None:  # the torque's own dependence on where the patch is
                    pb[wrist] -= (w_s / turn.scale) * np.cross(turn.axis, self._forces(e["y"])[wrist])
                xhat_b = np.where(held[:, None], 0.0, xhat_b)
                xnb += xhat_b
                vnb += xhat_b * h / (1.0 + alpha * h)
            # ---- the held path: p = x_n + fraction (target - x_n) for kinematic rows, x_n for fixed;
            # the wrist's patch: z_W = point + R (q - point), q = q_prev + fraction (target - q_prev)
            kin = log.kinematic[t] & ~m.fixed & ~wrist
            xnb += np.where(kin[:, None], (1.0 - e["fraction"]) * pb,
                            np.where((held & ~wrist)[:, None], pb, 0.0))
            if wrist.any():
                path_bar[wrist] += pb[wrist] @ rotation(turn.axis, e["angle"])
                path_bar *= 1.0 - e["fraction"]
                if e["grasp_start"]:  # q_0: where the patch was when the jaws closed
                    xnb[wrist] += path_bar[wrist]
                    path_bar[:] = 0.0
            # ---- the previous sub-step's end reaction, or the step start's holding force
            if k > 1:
                r_bar = r_carry.copy()  # r_{k-1} appears in two trapezoids: 0.5 + 0.5
            else:
                r0b = np.where(held[:, None], 0.5 * r_carry, 0.0)  # r_0 = -(f(x) + load - alpha m v) on held rows
                if r0b.any():
                    xs = e["start"][0]
                    hs = self._elastic_hessian(xs)
                    xnb += (hs @ r0b.reshape(-1)).reshape(n, 3)
                    theta_bar -= np.einsum("jnd,nd->j", dstart[idx], r0b)
                    vnb += alpha * mass * r0b
                r_bar = np.zeros((n, 3))
            zb, vb = xnb, vnb
            if k == 1:  # reached the control step's start: add the loss's direct term there
                zb = zb + x_bar[t]
        return theta_bar
