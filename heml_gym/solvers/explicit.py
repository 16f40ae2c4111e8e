"""Explicit symplectic Euler over N worlds, sub-stepped below the critical step.

Per sub-step of length ``h``, for every free vertex: ``v += h (f + f_ext + m g - alpha m v
- beta K v) / m``, ``x += h v``, then out of the supports; held vertices follow their
targets, fixed ones stay. The elastic forces come from the world's force field; the
work is done by the kernels of :mod:`heml_gym.solvers.kernels_explicit`, picked by what
the worlds allow:

* Neo-Hookean HEML (constant ``Psi_1``), N > 1: every world in lockstep, vectorised
  across worlds (:func:`~heml_gym.solvers.kernels_explicit.lane_substeps`);
* any HEML law: all sub-steps of all worlds in one compiled call, worlds over threads;
* anything else (F-FEM, mass-tensor, mass-spring, stiffness damping ``beta``, or one
  mesh large enough for the force kernels' own threads): sub-step by sub-step from
  Python, with :func:`~heml_gym.solvers.kernels_explicit.symplectic_euler_update`.

Every path uses the same update. A world that goes non-finite or faster than
``max_speed`` is flagged (``StepStats.diverged``) and keeps the state it had before the
step; the others go on.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..control import Control
from ..forces.heml import HemlForce
from ..model import Model
from ..state import State
from . import kernels_explicit as ke
from .base import Solver, StepStats, stiffness_damping

__all__ = ["ExplicitSolver"]


class ExplicitSolver(Solver):
    """Symplectic Euler for every world of ``model``.

    Parameters
    ----------
    model : Model
    safety : float in (0, 1]
        Sub-steps are at most ``safety`` times the rest-state critical step of the
        stiffest world (:meth:`Model.critical_dt`). Large deformations stiffen most laws
        (a 15 % squeeze of a Neo-Hookean cube diverged at 0.9), hence the default 0.5.
    max_speed : float, m/s
        A vertex faster than this counts as exploded.
    refinements : sequence of int
        A world that goes bad is stepped again from where it was with this many times
        more sub-steps, each in turn, before it is reported diverged: the rest-state
        critical step can be too long for strongly compressed or stretched tissue, whose
        stiffness grows (``StepStats.refinement`` says which factor a world needed). Only
        those worlds pay for it. ``()``: no second try.

    Hold springs (``Control.hold_stiffness``) are stepped sub-step by sub-step, their pull
    added to the forces, and the critical step shortened for them
    (:meth:`spring_critical_dt`).
    """

    takes_hold_springs = True
    takes_tools = True

    def __init__(self, model: Model, safety: float = 0.5, max_speed: float = 1e3, refinements=(4, 16)):
        super().__init__(model, max_speed)
        safety = float(safety)
        if not (0 < safety <= 1):
            raise ValueError(f"safety must lie in (0, 1], got {safety}")
        refinements = tuple(int(r) for r in refinements)
        if any(r < 2 for r in refinements):
            raise ValueError(f"refinements must be integers >= 2, got {refinements}")
        self.safety = safety
        self.refinements = refinements

    def substeps(self, dt: float, critical_dt: float | None = None) -> int:
        """Sub-steps for a step of ``dt`` s: enough to stay below ``safety`` times
        ``critical_dt`` (default: the model's, over all worlds)."""
        critical = self.model.critical_dt() if critical_dt is None else float(critical_dt)
        return max(1, math.ceil(dt / (self.safety * critical)))

    def step(self, state_in: State, state_out: State, control: Control, dt: float,
             substeps: int | None = None, active=None) -> StepStats:
        """Advance the ``active`` worlds (default: all) by ``dt`` s in ``substeps`` equal
        sub-steps (default: :meth:`substeps`); inactive worlds are not touched."""
        dt, active = self._check(state_in, state_out, control, dt, active)
        n_sub = self.substeps(dt) if substeps is None else int(substeps)
        if n_sub < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        m = self.model
        springs = (control.spring_stiffness(m.fixed) > 0.0) & active[:, None]
        if springs.any():  # the hold springs shorten the critical step: more sub-steps if they need them
            n_sub = max(n_sub, self.substeps(dt, self.spring_critical_dt(control, springs)))
        stats = StepStats.empty(m.n_worlds, m.n_vertices, n_sub)
        state = state_out
        x0, v0 = state.x.copy(), state.v.copy()
        h = dt / n_sub
        fields = m.fields
        heml = all(isinstance(f, HemlForce) for f in fields) and not m.damping.beta
        one_big_mesh = m.n_worlds == 1 and fields[0].kernel_threads() > 1
        tools = len(m.tools) > 0
        tool_force = np.zeros((m.n_worlds, len(m.tools), 3)) if tools else None
        with np.errstate(all="ignore"):
            if springs.any() or tools:  # (hold springs, tools: sub-step by sub-step, the springs' pull added)
                bad = self._stepwise(state, control, h, n_sub, x0, active, stats.reaction, tool_force)
            elif heml and not one_big_mesh and all(f.split for f in fields) and m.n_worlds > 1:
                bad = self._lanes(state, control, h, n_sub, x0, stats.reaction)
            elif heml and not one_big_mesh:
                bad = self._fused(state, control, h, n_sub, x0, active, stats.reaction)
            else:
                bad = self._stepwise(state, control, h, n_sub, x0, active, stats.reaction)
            bad[~active] = -1
            for factor in self.refinements:  # bad worlds again, from where they were, finer
                retry = bad >= 0
                if not retry.any():
                    break
                state.x[retry], state.v[retry] = x0[retry], v0[retry]
                stats.reaction[retry] = 0.0
                stats.refinement[retry] = factor
                if heml and not one_big_mesh and not springs.any() and not tools:
                    again = self._fused(state, control, h / factor, n_sub * factor, x0, retry, stats.reaction)
                else:
                    if tools:
                        tool_force[retry] = 0.0
                    again = self._stepwise(state, control, h / factor, n_sub * factor, x0, retry, stats.reaction,
                                           tool_force)
                bad[retry] = again[retry]
        inactive = ~active
        state.x[inactive] = x0[inactive]
        state.v[inactive] = v0[inactive]
        for s in np.flatnonzero(bad >= 0):
            message, elements = self.divergence(state.x[s], state.v[s])
            stats.messages[s] = message or f"vertex {bad[s]} went non-finite or too fast"
            stats.elements[s] = elements
            state.x[s], state.v[s] = x0[s], v0[s]
            stats.reaction[s] = 0.0
        stats.diverged = bad >= 0
        stats.converged = ~stats.diverged
        if tools:
            stats.tool_force = np.where((active & ~stats.diverged)[:, None, None], tool_force, 0.0)
        done = springs & ~stats.diverged[:, None]
        control.anchors[done] = control.targets[done]  # (the anchors reached their targets)
        return stats

    def spring_critical_dt(self, control: Control, springs: np.ndarray) -> float:
        """The critical step (s) with the hold springs ``springs`` (an ``(N, n)`` mask of
        ``control``'s): a spring ``k`` on a vertex of mass ``m`` adds at most ``k / m`` to
        the largest eigenvalue of ``M^-1 K`` (Gershgorin), so ``2 / sqrt((2 / dt_c)^2 +
        max k / m)`` with ``dt_c`` the model's critical step."""
        critical = self.model.critical_dt()
        extra = float((np.where(springs, control.hold_stiffness, 0.0) / self.model.mass[None, :]).max())
        return 2.0 / math.sqrt((2.0 / critical) ** 2 + extra)

    # ------------------------------------------------------------------ paths
    def _fused(self, state, control, h, n_sub, x0, active, reaction):
        m = self.model
        N = m.n_worlds
        bad = np.full(N, -1, dtype=np.int64)
        parallel = N > 1 and numba.get_num_threads() > 1
        worlds = ke.ExplicitWorlds(state.x, state.v, np.empty_like(state.x), reaction, np.empty_like(state.x),
                                   control.external_forces, control.kinematic, x0, control.targets)
        laws = m.heml_laws()
        if laws.split:
            kernel = ke.split_substeps_parallel if parallel else ke.split_substeps_serial
        else:
            kernel = ke.heml_substeps_parallel if parallel else ke.heml_substeps_serial
        kernel(worlds, m.heml_body(), laws, m.supports.kernel_args(), self._step(h, n_sub), active, bad)
        return bad

    def _step(self, h, n_sub) -> ke.ExplicitStep:
        return ke.ExplicitStep(float(h), int(n_sub), float(self.max_speed))

    def _lanes(self, state, control, h, n_sub, x0, reaction_out):
        """All worlds in lockstep, vectorised across worlds (Neo-Hookean HEML)."""
        m = self.model
        N = m.n_worlds
        per_thread = math.ceil(N / numba.get_num_threads())
        lanes = min(ke.LANES, 4 * math.ceil(per_thread / 4))
        blocks = math.ceil(N / lanes)
        pad = blocks * lanes - N  # extra lanes repeat world 0

        def to_lanes(a):
            a = np.concatenate([a, np.repeat(a[:1], pad, axis=0)]) if pad else a
            a = a.reshape((blocks, lanes) + a.shape[1:])
            return np.ascontiguousarray(np.moveaxis(a, 1, -1))

        def from_lanes(a):
            return np.moveaxis(a, -1, 1).reshape((blocks * lanes,) + a.shape[1:-1])[:N]

        laws = m.heml_laws()
        xl, vl = to_lanes(state.x), to_lanes(state.v)
        reaction = np.empty_like(xl)
        bad_lanes = np.empty((blocks, lanes), dtype=np.int64)
        worlds = ke.LaneWorlds(xl, vl, np.empty_like(xl), reaction, to_lanes(control.external_forces),
                               to_lanes(control.kinematic), to_lanes(x0), to_lanes(control.targets),
                               to_lanes(laws.params[:, 0]), to_lanes(laws.params[:, 1]), to_lanes(laws.psi1), bad_lanes)
        ke.lane_substeps(worlds, m.heml_body(), laws.law[0], m.supports.kernel_args(), self._step(h, n_sub))
        state.x[:] = from_lanes(xl)
        state.v[:] = from_lanes(vl)
        reaction_out[:] = from_lanes(reaction)
        return bad_lanes.reshape(-1)[:N].copy()

    def _stepwise(self, state, control, h, n_sub, x0, active, reaction, tool_force=None):
        """Sub-step by sub-step from Python: any force field, stiffness damping, hold
        springs (each spring-held vertex is free, pulled by ``k (anchor - x)`` with its
        anchor on the straight path to its target; that pull is its reaction), rigid tools
        (each free vertex inside one is put back on its surface, as the supports do, and
        loses its velocity into it: the momentum it loses, over the sub-step, is the tool's
        push, averaged over the step into ``tool_force (N, T, 3)``)."""
        m = self.model
        N, n = m.n_worlds, m.n_vertices
        supports = m.supports.kernel_args()
        f = np.zeros((n, 3))
        sub_reaction = np.zeros((n, 3))
        bad = np.full(N, -1, dtype=np.int64)
        beta = m.damping.beta
        exact = control.exactly_held()
        free = ~(m.fixed[None, :] | exact) if tool_force is not None else None
        for s in np.flatnonzero(active):
            field = m.fields[s]
            x, v = state.x[s], state.v[s]
            spring = np.flatnonzero(control.spring_stiffness(m.fixed)[s] > 0.0)
            k_spring = control.hold_stiffness[s, spring, None]
            a0, a1 = control.anchors[s, spring], control.targets[s, spring]
            for k in range(1, n_sub + 1):
                field.forces(x, out=f)
                if beta:
                    f += stiffness_damping(field, x, v, f, beta)
                pull = k_spring * (a0 + (a1 - a0) * ((k - 1) / n_sub) - x[spring])  # (at the sub-step's start)
                f[spring] += pull
                b = ke.symplectic_euler_update(x, v, f, m.mass, m.gravity, control.external_forces[s],
                                               m.damping.alpha, h, m.fixed, exact[s], x0[s],
                                               control.targets[s], k / n_sub, self.max_speed, sub_reaction,
                                               supports)
                if b >= 0:
                    bad[s] = b
                    break
                if tool_force is not None:
                    tool_force[s] += self._push_out_of_tools(x, v, control.tool_pose[s], free[s], h) / n_sub
                sub_reaction[spring] = pull
                reaction[s] += sub_reaction / n_sub
        return bad

    def _push_out_of_tools(self, x, v, pose, free, h) -> np.ndarray:
        """Put the ``free`` vertices of one world inside a tool (posed at ``pose``) back on
        its surface, in place, and take away their velocity into it; returns each tool's
        push on the tissue (N, ``(T, 3)``): the momentum it took over ``h``. Tools are
        taken in turn, each from where the previous one left the vertices."""
        m = self.model
        tools = m.tools
        push = np.zeros((len(tools), 3))
        idx = np.flatnonzero(free)
        for t in range(len(tools)):
            d, normal = tools.each_distance(x[idx], pose)
            inside = d[t] < 0.0
            if not inside.any():
                continue
            i, nrm = idx[inside], normal[t, inside]
            x[i] -= d[t, inside, None] * nrm
            into = np.minimum(np.einsum("ka,ka->k", v[i], nrm), 0.0)  # m/s, the velocity into the tool
            v[i] -= into[:, None] * nrm
            push[t] = -(m.mass[i, None] * into[:, None] * nrm).sum(axis=0) / h
        return push
