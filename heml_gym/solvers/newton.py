"""Newton's method, and L-BFGS, on a potential over the free degrees of freedom, as the
implicit and static solvers use them (one world at a time)."""

from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse.linalg as spla

from ..linear_solvers import FreeSubmatrix

__all__ = ["NewtonResult", "minimize", "minimize_lbfgs", "linear_response"]


class NewtonResult:
    """``x`` (the last iterate), ``iterations``, ``residual`` (N: the force residual's norm
    on the free dofs), ``converged`` (``residual <= tol``), ``finite``."""

    __slots__ = ("x", "iterations", "residual", "converged", "finite")

    def __init__(self, x, iterations, residual, tol):
        self.x = x
        self.iterations = int(iterations)
        self.residual = float(residual)
        self.finite = bool(np.isfinite(residual))
        self.converged = bool(residual <= tol)


def minimize(x, potential, gradient, hessian, free, tol, max_iter, submatrix: FreeSubmatrix,
             pcg=None, pcg_key=None, stall_limit: int | None = 5, min_iter: int = 0) -> NewtonResult:
    """Minimise ``potential`` over the free dofs (``free``: ``(3n,)`` mask) from ``x`` by Newton.

    Each iteration solves with the exact Hessian first and, if that gives no descent
    direction (the law is not convex there), with the per-element projected one, which
    is positive semi-definite; by ``pcg`` (a :class:`~heml_gym.linear_solvers.LaggedFactorPCG`)
    if given, else by a sparse direct solve. A backtracking line search accepts a step
    that satisfies the Armijo condition on the potential or, near convergence where the
    potential's round-off hides the decrease, that reduces the residual; steps to
    non-finite energies (inverted elements of ln J laws) are halved. It stops when the
    residual is below ``tol`` (N), after ``max_iter`` iterations, when the line search
    finds no progress, or after ``stall_limit`` iterations in a row that cut the residual
    by less than 1 % (the round-off floor; None: never); it takes at least ``min_iter``
    iterations (a start already within ``tol`` of another problem's minimum, such as the
    solution for nearby constants, is still moved to this one's). ``hessian(x, project)``
    returns a CSR matrix.
    """
    g = gradient(x)
    gnorm = float(np.linalg.norm(g[free]))
    it = 0
    stalled = 0
    phi_x = None
    limit = np.inf if stall_limit is None else stall_limit
    while (gnorm > tol or it < min_iter) and it < max_iter and stalled < limit:
        it += 1
        gf = g[free]
        for project in (False, True):
            a = submatrix(hessian(x, project), free)
            if pcg is not None:
                dx = pcg.solve(a, -gf, key=(pcg_key, project))
            else:
                dx = spla.spsolve(a.tocsc(), -gf, permc_spec="MMD_AT_PLUS_A")  # symmetric: 2x faster
            slope = float(gf @ dx)
            ok = bool(np.all(np.isfinite(dx)) and slope < 0)
            if ok:
                break
        if not ok:  # no Newton direction: steepest descent, scaled by the diagonal
            dx = -gf / float(np.abs(a.diagonal()).max())
            slope = float(gf @ dx)
        phi0 = potential(x) if phi_x is None else phi_x
        step = 1.0
        trial = x.copy()
        for _ in range(40):
            trial.reshape(-1)[free] = x.reshape(-1)[free] + step * dx
            phi = potential(trial)
            if np.isfinite(phi):
                if phi <= phi0 + 1e-4 * step * slope:
                    g_trial = gradient(trial)
                    break
                g_trial = gradient(trial)
                if np.linalg.norm(g_trial[free]) < (1.0 - 1e-4 * step) * gnorm:
                    break
            step *= 0.5
        else:
            break  # no progress possible at this precision: keep the best iterate
        x = trial
        g = g_trial
        phi_x = phi  # the next iteration's phi0
        previous, gnorm = gnorm, float(np.linalg.norm(g[free]))
        # at the round-off floor the residual stops falling: stop after stall_limit such steps
        stalled = stalled + 1 if gnorm > 0.99 * previous else 0
    return NewtonResult(x, it, gnorm, tol)


def minimize_lbfgs(x, potential, gradient, precondition, free, tol, max_iter, history: int = 8) -> NewtonResult:
    """Minimise ``potential`` over the free dofs (``free``: ``(3n,)`` mask) from ``x`` by L-BFGS.

    The quasi-Newton method of :class:`~heml_gym.QuasiNewtonSolver` for any force field,
    in Python: each iteration's direction is the two-loop recursion over the last
    ``history`` pairs of steps and gradient changes, its initial inverse Hessian
    ``precondition(r)`` (``r`` the gradient on the free dofs, returns an approximation of
    the Hessian's inverse applied to it; it must be symmetric positive definite); a
    backtracking line search accepts a step that satisfies the Armijo condition on the
    potential or, near convergence where its round-off hides the decrease, that reduces
    the residual, and halves steps to non-finite energies. A direction that is not one of
    descent restarts the recursion from ``precondition``. It stops when the residual (N,
    the gradient's norm on the free dofs) is below ``tol``, after ``max_iter`` iterations
    or when the line search finds no progress; the result says whether it converged.
    """
    x = np.array(x, dtype=np.float64)
    flat = x.reshape(-1)
    g = gradient(x)[free]
    phi = potential(x)
    gnorm = float(np.linalg.norm(g))
    pairs: list = []  # (s, y, 1 / s.y), oldest first
    it = 0
    while gnorm > tol and it < max_iter:
        it += 1
        q = g.copy()
        alphas = []
        for s_k, y_k, rho in reversed(pairs):
            a = rho * float(s_k @ q)
            alphas.append(a)
            q -= a * y_k
        d = precondition(q)
        for (s_k, y_k, rho), a in zip(pairs, reversed(alphas)):
            d += (a - rho * float(y_k @ d)) * s_k
        d = -d
        slope = float(g @ d)
        if not slope < 0.0:  # not a descent direction: restart from the initial inverse Hessian
            pairs.clear()
            d = -precondition(g)
            slope = float(g @ d)
            if not slope < 0.0:
                break
        step = 1.0
        trial = x.copy()
        trial_flat = trial.reshape(-1)
        for _ in range(40):
            trial_flat[free] = flat[free] + step * d
            phi_t = potential(trial)
            if np.isfinite(phi_t):
                g_t = gradient(trial)[free]
                if phi_t <= phi + 1e-4 * step * slope or np.linalg.norm(g_t) < (1.0 - 1e-4 * step) * gnorm:
                    break
            step *= 0.5
        else:
            break  # no progress possible at this precision: keep the best iterate
        s_k, y_k = step * d, g_t - g
        sy = float(s_k @ y_k)
        if sy > 1e-300:
            pairs.append((s_k, y_k, 1.0 / sy))
            if len(pairs) > history:
                pairs.pop(0)
        x, flat, g, phi = trial, trial_flat, g_t, phi_t
        gnorm = float(np.linalg.norm(g))
    return NewtonResult(x, it, gnorm, tol)


def linear_response(a, x_start: np.ndarray, x_moved: np.ndarray, moved: np.ndarray) -> np.ndarray | None:
    """A Newton start for a step whose ``moved`` vertices ((n,) bool) went from
    ``x_start`` to ``x_moved`` (m, (n, 3)): ``x_moved`` with every other vertex moved by
    its linear response to that motion, one solve with ``a`` (CSR, 3n x 3n: the step's
    Hessian at ``x_start``, N/m). Where the held vertices moved past a free neighbour,
    the start ``x_moved`` itself turns tets inside out; this one follows them. None where
    ``a`` is not finite or singular there."""
    held = np.repeat(np.asarray(moved, dtype=bool), 3)
    free = ~held
    d = (x_moved - x_start).reshape(-1)
    if not np.all(np.isfinite(a.data)):
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("error", spla.MatrixRankWarning)
        try:
            u = spla.spsolve(a[free][:, free].tocsc(), -(a[free][:, held] @ d[held]))
        except (spla.MatrixRankWarning, RuntimeError):  # RuntimeError: SuperLU failed
            return None
    if not np.all(np.isfinite(u)):
        return None
    y = x_moved.copy().reshape(-1)
    y[free] = x_start.reshape(-1)[free] + u
    return y.reshape(x_moved.shape)
