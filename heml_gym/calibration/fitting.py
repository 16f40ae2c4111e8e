"""Fit a scene's material constants to observed tracked points and gripper forces.

The loss (dimensionless) is the mean of squared residuals of each observed quantity over
its scale, summed over the quantities::

    L = mean_t,k |p_k(t) - p_obs_k(t)|^2 / s_p^2  +  mean_t |F(t) - F_obs(t)|^2 / s_F^2

with ``p_k(t)`` a tracked material point (a fixed barycentric combination of the vertices
of the rest tet it lies in), ``F(t)`` the step-mean force the tissue pulls the gripper with,
``s_p`` (m) and ``s_F`` (N) the scales (by default 1 mm and 0.05 N: the order of the
noise a tracker and a jaw force sensor have). :func:`fit` minimises it by bounded L-BFGS
(scipy's L-BFGS-B, the gradient by :meth:`Replay.gradient`) from several starts, and
reports each constant's standard error from the Gauss-Newton curvature ``J^T J`` of the
residuals at the optimum (``J`` by central differences of the replay), scaled by the
residuals' variance. Units: m, N, Pa.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
import scipy.optimize as so
import scipy.sparse as sp

from ..mesh import TetMesh
from .replay import Replay, ReplayError, ReplayResult

__all__ = ["Observed", "FitResult", "embed_points", "loss_terms", "fit", "DEFAULT_POINT_SCALE", "DEFAULT_FORCE_SCALE"]


def embed_points(mesh: TetMesh, points: np.ndarray) -> sp.csr_matrix:
    """``B`` (K, n): each point as the barycentric combination of the vertices of the rest
    tet that holds it (the nearest tet's, clipped to it, for a point just outside the
    surface), so that ``B @ x`` is where the material points are when the vertices are at ``x``."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    X, tets = mesh.vertices, mesh.tets
    corners = X[tets]  # (m, 4, 3)
    T = np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1))  # (m, 3, 3)
    T_inv = np.linalg.inv(T)
    rows, cols, vals = [], [], []
    for k, p in enumerate(points):
        lam = np.einsum("mij,mj->mi", T_inv, p - corners[:, 0])
        bary = np.column_stack([1.0 - lam.sum(axis=1), lam])
        outside = np.clip(-bary, 0.0, None).sum(axis=1)
        best = int(np.argmin(outside))
        b = np.clip(bary[best], 0.0, None)
        b /= b.sum()
        rows += [k] * 4
        cols += list(tets[best])
        vals += list(b)
    return sp.csr_matrix((vals, (rows, cols)), shape=(len(points), mesh.n_vertices))


#: The residual scales when none is given: about a tracker's noise (m) and a jaw force
#: sensor's (N).
DEFAULT_POINT_SCALE, DEFAULT_FORCE_SCALE = 1e-3, 0.05


@dataclass
class Observed:
    """What was observed at the control steps ``0..T`` (entry 0: the start), any of:
    ``points`` (T + 1, K, 3) m of material points at rest places ``rest_points`` (K, 3) m;
    ``force`` (T + 1, 3) N, the force the tissue pulls the gripper with (entry t: the mean
    over control step t; entry 0 unused). ``point_scale`` (m) and ``force_scale`` (N)
    weigh them (see the module docstring). ``extra``: further loss terms on the positions,
    each ``term(x) -> (loss, residuals, x_bar)`` for ``x`` (T + 1, n, 3) m, with a ``name``
    and ``term.rms(x)`` (its RMS residual, reported under its name): a depth camera's
    (``heml_gym.envs.depth_loss.DepthTerm``), which the physics layer does not render."""

    points: np.ndarray | None = None
    rest_points: np.ndarray | None = None
    force: np.ndarray | None = None
    point_scale: float = DEFAULT_POINT_SCALE
    force_scale: float = DEFAULT_FORCE_SCALE
    extra: tuple = ()

    def __post_init__(self):
        self.extra = tuple(self.extra)
        if self.points is None and self.force is None and not self.extra:
            raise ValueError("observed: give points (with rest_points), force or an extra term")
        for term in self.extra:
            if not (callable(term) and hasattr(term, "name") and hasattr(term, "rms")):
                raise ValueError(f"observed.extra: each term is called with the positions and has a name and an "
                                 f"rms, got {term!r}")
        if (self.points is None) != (self.rest_points is None):
            raise ValueError("observed: points and rest_points go together")
        for name in ("point_scale", "force_scale"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"observed.{name}: must be a positive number, got {value!r}")


def loss_terms(result: ReplayResult, observed: Observed, embedding: sp.csr_matrix | None):
    """``(loss, residuals, x_bar, force_bar, weights)``: the loss of a replay against the
    observed, the stacked residuals over their scales (for the Gauss-Newton curvature), the
    loss's derivatives in the replay's positions and forces, and each observed quantity's
    ``(name, residual count, weight)`` in stacking order, so that the loss is the sum over the
    quantities of ``weight * (their residuals ** 2).sum()`` (points' and force's weight is
    one over their count: each quantity's loss is a mean)."""
    x = result.x
    T1 = x.shape[0]
    x_bar = np.zeros_like(x)
    force_bar = np.zeros_like(result.force)
    loss, residuals, weights = 0.0, [], []
    if observed.points is not None:
        predicted = np.stack([embedding @ x[t] for t in range(T1)])  # (T + 1, K, 3)
        r = (predicted - observed.points) / observed.point_scale
        count = r[..., 0].size
        loss += float((r ** 2).sum() / count)
        residuals.append(r.reshape(-1))
        weights.append(("points", r.size, 1.0 / count))
        rb = 2.0 * r / (count * observed.point_scale)  # dL/dpredicted
        for t in range(T1):
            x_bar[t] += embedding.T @ rb[t]
    if observed.force is not None:
        r = (result.force - observed.force[1:]) / observed.force_scale
        count = r.shape[0]
        loss += float((r ** 2).sum() / count)
        residuals.append(r.reshape(-1))
        weights.append(("force", r.size, 1.0 / count))
        force_bar += 2.0 * r / (count * observed.force_scale)
    for term in observed.extra:
        value, r, bar = term(x)
        r = np.asarray(r, dtype=np.float64).reshape(-1)
        loss += float(value)
        residuals.append(r)
        # (a term's loss is a weighted sum of its residuals' squares; with every residual 0
        # any weight will do: their variance, and so the standard errors, are then 0)
        squares = float(r @ r)
        weights.append((term.name, r.size, float(value) / squares if squares > 0.0 else 1.0))
        x_bar += bar
    return loss, np.concatenate(residuals), x_bar, force_bar, weights


#: Resamples of :func:`paired_rms_interval`'s bootstrap.
BOOTSTRAP_SAMPLES = 2000


def paired_rms_interval(a: Sequence[float], b: Sequence[float], samples: int = BOOTSTRAP_SAMPLES,
                        seed: int = 0) -> tuple[float, float]:
    """95 % bootstrap interval of ``RMS(a) - RMS(b)``, where ``a`` and ``b`` are two
    predictions' RMS errors (m) at the same observed times: the times are resampled with
    replacement, ``samples`` times, and each resample's difference of the RMS over its
    times is kept (a pairs bootstrap: both predictions see the same resampled times). An
    interval that holds 0 says the data do not tell the two predictions apart."""
    a2, b2 = np.square(np.asarray(a, dtype=np.float64)), np.square(np.asarray(b, dtype=np.float64))
    if a2.shape != b2.shape or a2.ndim != 1 or a2.size == 0:
        raise ValueError(f"paired_rms_interval: a and b must be per-time RMS of one length, got shapes "
                         f"{a2.shape} and {b2.shape}")
    idx = np.random.default_rng(seed).integers(0, a2.size, size=(samples, a2.size))
    diff = np.sqrt(a2[idx].mean(axis=1)) - np.sqrt(b2[idx].mean(axis=1))
    return float(np.percentile(diff, 2.5)), float(np.percentile(diff, 97.5))


@dataclass
class FitResult:
    """A fit's outcome: ``theta`` (the constants), ``std`` (their standard errors),
    ``loss``, ``converged`` with ``message``, ``history`` (loss per iteration of the best
    start), ``starts`` (each start's theta, loss and iterations; with the residual weights
    re-fitted, those of the first fit, from every start), ``residual_rms`` (each
    observed quantity's RMS residual in its unit: ``points_m``, ``force_N``),
    ``wall_s``, ``by_quantity`` (with two or more observed quantities: each one's own
    estimate, ``{name: {"theta": ..., "std": ...}}``, one Gauss-Newton step from ``theta``
    on that quantity's residuals alone: its own fit's near ``theta``, its direction far off
    it; where they disagree beyond their errors, one of them carries a model error), ``scales`` (the residual scales of the last fit: ``point_scale_m``,
    ``force_scale_N``)."""

    names: list[str]
    theta: np.ndarray
    std: np.ndarray
    loss: float
    converged: bool
    message: str
    history: list[float] = field(default_factory=list)
    starts: list[dict] = field(default_factory=list)
    residual_rms: dict = field(default_factory=dict)
    wall_s: float = 0.0
    failed_trials: int = 0
    scales: dict = field(default_factory=dict)
    by_quantity: dict = field(default_factory=dict)


#: Weighing by the residuals: at most this many fits, and they stop when no scale changes
#: by more than :data:`SCALE_TOLERANCE` (relative).
SCALE_ROUNDS = 4
SCALE_TOLERANCE = 0.05


def fit(replay: Replay, observed: Observed, names: Sequence[str], starts: Sequence[Sequence[float]],
        bounds: Sequence[tuple[float, float]], max_iter: int = 40, gtol: float = 1e-7, ftol: float = 1e-8,
        progress: Callable[[int, float], None] | None = None, weigh_by_residuals: bool = False) -> FitResult:
    """Fit the constants ``names`` (what ``replay.material_of`` takes) to ``observed``,
    from each of ``starts`` within ``bounds``; the best start wins. A start stops when the
    projected gradient is below ``gtol`` or an iteration lowers the loss by less than
    ``ftol`` (absolute below a loss of 1, else relative): the loss has kinks where a vertex
    enters or leaves contact with the support, next to which L-BFGS would otherwise
    bounce between both sides. ``progress(i, loss)`` is called after each iteration (a
    progress bar). Raises :class:`ReplayError` when no start's replay can be followed
    (a fit that starts but stops short says so in its ``converged`` and ``message``).

    ``weigh_by_residuals``: with both points and force observed and neither's noise known,
    each is weighed by its own residual: after a fit, ``point_scale`` and ``force_scale``
    become the RMS residuals it left and the fit is repeated from its optimum, until no
    scale changes by more than 5 % (at most :data:`SCALE_ROUNDS` fits). That is maximum
    likelihood with an unknown noise level per sensor, and it keeps a quantity the model
    cannot follow (a model error) from outweighing one it can. The scales used are in the
    result's ``scales``."""
    result = _fit(replay, observed, names, starts, bounds, max_iter, gtol, ftol, progress)
    if not (weigh_by_residuals and observed.points is not None and observed.force is not None):
        return result
    history, wall, failed, starts = list(result.history), result.wall_s, result.failed_trials, result.starts
    for _ in range(SCALE_ROUNDS - 1):
        scales = (max(result.residual_rms["points_m"], 1e-6), max(result.residual_rms["force_N"], 1e-6))
        if all(abs(new / old - 1.0) <= SCALE_TOLERANCE
               for new, old in zip(scales, (observed.point_scale, observed.force_scale))):
            break
        observed = dataclasses.replace(observed, point_scale=scales[0], force_scale=scales[1])
        result = _fit(replay, observed, names, [result.theta], bounds, max_iter, gtol, ftol, progress)
        history += result.history
        wall += result.wall_s
        failed += result.failed_trials
    return dataclasses.replace(result, history=history, wall_s=wall, failed_trials=failed, starts=starts)


def _fit(replay: Replay, observed: Observed, names, starts, bounds, max_iter, gtol, ftol, progress) -> FitResult:
    """One fit of :func:`fit` at ``observed``'s scales."""
    t0 = time.perf_counter()
    embedding = None
    if observed.points is not None:
        embedding = embed_points(replay.model.mesh, observed.rest_points)
    # L-BFGS-B's first step is one unit long: in these units a unit is a 10 % change of a
    # positive constant (searched in log space) or a tenth of its bounds' span
    transform = _Units(bounds)
    unit_bounds = transform.bounds
    runs = []
    failures = [0]
    failed = {}  # search point (its _key) -> why its replay failed

    cache = {}

    def _key(u) -> bytes:
        return np.asarray(u, dtype=np.float64).tobytes()

    def objective(u):
        key = _key(u)
        if key in cache:  # (the iteration callback asks for the point just evaluated)
            return cache[key]
        cache.clear()
        cache[key] = value = _objective(u)
        return value

    def _objective(u):
        theta = transform.theta(u)
        try:
            result = replay.run(theta)
            loss, _, x_bar, force_bar, _ = loss_terms(result, observed, embedding)
            grad = replay.gradient(theta, result, x_bar, force_bar) * transform.dtheta_du(u)
        except ReplayError as exc:
            failures[0] += 1
            failed[_key(u)] = str(exc)
            return 1e6, np.zeros_like(u)  # a material the log cannot be followed with: far off (the line search backs off)
        return loss, grad

    for start in starts:
        history = []

        def callback(u, history=history):
            value = objective(u)[0]
            history.append(value)
            if progress is not None:
                progress(len(history), value)

        u0 = transform.u(np.asarray(start, dtype=np.float64))
        res = so.minimize(objective, u0, jac=True, method="L-BFGS-B", bounds=unit_bounds, callback=callback,
                          options={"maxiter": max_iter, "maxfun": 4 * max_iter, "maxls": 10, "gtol": gtol,
                                   "ftol": ftol})
        runs.append((res, history, np.asarray(start, dtype=np.float64)))
    replayed = [r for r in runs if _key(r[0].x) not in failed]
    if not replayed:  # (L-BFGS stops at once where the replay fails: zero gradient)
        res, _, start = runs[0]
        raise ReplayError(f"the fit cannot start: replaying the log with {dict(zip(names, start.tolist()))} fails "
                          f"({failed[_key(res.x)]})")
    best, history, _ = min(replayed, key=lambda r: r[0].fun)
    u = np.asarray(best.x, dtype=np.float64)
    message = best.message if isinstance(best.message, str) else best.message.decode()
    converged = bool(best.success)
    if not converged:
        u, converged, message = _compass_search(replay, observed, embedding, transform, u, float(best.fun), names,
                                                message, progress, history)
    theta = transform.theta(u)
    result = replay.run(theta)
    loss, residuals, _, _, weights = loss_terms(result, observed, embedding)
    std, by_quantity = _standard_errors(replay, observed, embedding, theta, residuals, weights)
    rms = {}
    if observed.points is not None:
        predicted = np.stack([embedding @ x for x in result.x])
        rms["points_m"] = float(np.sqrt(((predicted - observed.points) ** 2).sum(axis=-1).mean()))
    if observed.force is not None:
        rms["force_N"] = float(np.sqrt(((result.force - observed.force[1:]) ** 2).sum(axis=-1).mean()))
    for term in observed.extra:
        rms[term.name] = float(term.rms(result.x))
    return FitResult(list(names), theta, std, float(loss), converged, message, history,
                     [{"start": s.tolist(), "theta": transform.theta(r.x).tolist(), "loss": float(r.fun),
                       "iterations": int(r.nit), "converged": bool(r.success)} for r, _, s in runs],
                     rms, time.perf_counter() - t0, failures[0],
                     {"point_scale_m": observed.point_scale, "force_scale_N": observed.force_scale}, by_quantity)


#: A fit whose search stopped without its convergence test goes on by changing each
#: constant by this much (search units: 1 % of a positive constant, 1 % of the bounds'
#: span of another) both ways, as long as that lowers the loss, at most
#: :data:`COMPASS_MOVES` times.
PROBE = 0.1
COMPASS_MOVES = 20


def _compass_search(replay, observed, embedding, transform, u, loss, names, message, progress, history):
    """``(u, converged, message)`` for a search that stopped short of its own test
    (L-BFGS-B's line search ends at a kink of the loss: a depth pixel crossing the model's
    silhouette, a vertex reaching the support): a compass search at :data:`PROBE` (1 %)
    resolution from there. Each move tries every constant up and down by 1 % (within the
    bounds) and goes to the lowest loss; where none is lower, the fit is a minimum at that
    resolution (converged); after :data:`COMPASS_MOVES` moves it is not. Each move's loss
    is appended to ``history``."""
    u = np.array(u, dtype=np.float64)
    moves = 0
    while True:
        best_u, best_loss, best_name = None, loss, ""
        for j, name in enumerate(names):
            for sign in (1.0, -1.0):
                probe = u.copy()
                probe[j] = np.clip(probe[j] + sign * PROBE, *transform.bounds[j])
                if probe[j] == u[j]:
                    continue
                try:
                    value = loss_terms(replay.run(transform.theta(probe)), observed, embedding)[0]
                except ReplayError:
                    continue
                if value < best_loss:
                    best_u, best_loss, best_name = probe, value, f"{name} {'+' if sign > 0 else '-'}1 %"
        if best_u is None:
            how = f" after {moves} compass moves" if moves else ""
            return u, True, (f"a minimum at 1 % resolution{how}: the search stopped at a kink of the loss ({message}), "
                             "and no change of any constant by 1 % either way lowers it")
        if moves == COMPASS_MOVES:
            return u, False, (f"{message}; not a minimum after {moves} compass moves of 1 %: {best_name} still lowers "
                              f"the loss to {best_loss:.6g} (from {loss:.6g})")
        u, loss, moves = best_u, best_loss, moves + 1
        history.append(loss)  # (a compass move counts as an iteration of the fit)
        if progress is not None:
            progress(len(history), loss)


class _Units:
    """The search's units: ``u = 10 ln(theta)`` for a constant with positive bounds, else
    ``u = 10 theta / (hi - lo)``."""

    def __init__(self, bounds):
        self.log = np.array([lo > 0 for lo, _ in bounds])
        self.span = np.array([hi - lo for lo, hi in bounds], dtype=np.float64)
        self.bounds = [(10.0 * math.log(lo), 10.0 * math.log(hi)) if lo > 0 else (10.0 * lo / s, 10.0 * hi / s)
                       for (lo, hi), s in zip(bounds, self.span)]

    def u(self, theta):
        theta = np.asarray(theta, dtype=np.float64)
        return np.where(self.log, 10.0 * np.log(np.where(self.log, theta, 1.0)), 10.0 * theta / self.span)

    def theta(self, u):
        u = np.asarray(u, dtype=np.float64)
        return np.where(self.log, np.exp(u / 10.0), u * self.span / 10.0)

    def dtheta_du(self, u):
        return np.where(self.log, self.theta(u) / 10.0, self.span / 10.0)


def _standard_errors(replay, observed, embedding, theta, residuals, weights) -> tuple[np.ndarray, dict]:
    """Each constant's standard error from the sandwich ``H^-1 M H^-1`` of the loss the fit
    minimises, ``sum_q w_q |r_q|^2`` over the observed quantities q (``weights``: each one's
    residual count and weight ``w_q``): ``H = sum_q w_q J_q^T J_q`` and ``M = sum_q w_q^2
    s_q^2 J_q^T J_q`` (``J_q`` the quantity's residual Jacobian by central differences of
    the replay, ``s_q^2`` the variance of its residuals, a quantity's residuals taken as
    independent). One quantity: ``s^2 (J^T J)^-1``, Gauss-Newton's. Each quantity's loss
    being a mean, a sparse one (30 force samples beside 300 point positions) weighs more per
    residual than its noise alone would give it, and ``s^2 (J^T J)^-1`` of the stacked
    residuals would understate the spread of the estimate. Also returns each quantity's own
    estimate (with two or more): one Gauss-Newton step from ``theta`` on its residuals
    alone, and its standard errors ``s_q (J_q^T J_q)^-1/2`` (:class:`FitResult`'s
    ``by_quantity``)."""
    p = len(theta)
    J = np.zeros((residuals.size, p))
    for j in range(p):
        step = 1e-4 * abs(theta[j]) if theta[j] != 0 else 1e-6
        cols = []
        for sign in (1.0, -1.0):
            shifted = np.array(theta, dtype=np.float64)
            shifted[j] += sign * step
            cols.append(loss_terms(replay.run(shifted), observed, embedding)[1])
        # a residual that appears or vanishes between the two (a depth pixel crossing the
        # model's silhouette) is a jump, not a slope: it is left out of J
        switched = (cols[0] == 0.0) != (cols[1] == 0.0)
        J[:, j] = np.where(switched, 0.0, (cols[0] - cols[1]) / (2.0 * step))
    replay.run(theta)  # (the model's material back to theta)
    # (the residuals' degrees of freedom: p constants were fitted to them; a residual that
    # is exactly 0, a depth pixel that does not count, is not one)
    counted = max(int(np.count_nonzero(residuals)), p + 1)
    dof = counted / (counted - p)
    H = np.zeros((p, p))
    M = np.zeros((p, p))
    start = 0
    by_quantity = {}
    for name, size, weight in weights:
        part = slice(start, start + size)
        start += size
        r = residuals[part]
        n = max(int(np.count_nonzero(r)), 1)
        variance = float(r @ r) / n * dof
        JtJ = J[part].T @ J[part]
        H += weight * JtJ
        M += weight ** 2 * variance * JtJ
        if len(weights) > 1:
            try:  # (a quantity that cannot fix every constant alone: no estimate of its own)
                own = np.linalg.inv(JtJ)
            except np.linalg.LinAlgError:
                continue
            if np.all(np.isfinite(own)) and np.all(np.diag(own) > 0.0):
                by_quantity[name] = {"theta": (np.asarray(theta) - own @ (J[part].T @ r)).tolist(),
                                     "std": np.sqrt(np.diag(own) * variance).tolist()}
    try:
        Hinv = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return np.full(p, math.inf), by_quantity
    covariance = Hinv @ M @ Hinv
    return np.sqrt(np.clip(np.diag(covariance), 0.0, None)), by_quantity
