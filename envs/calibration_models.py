"""Which model of each task ``heml-gym calibrate`` fits by default, and which of an
observation file's quantities.

A fit's Young's modulus carries the fitted mesh's own stiffness: linear tetrahedra are
too stiff in bending on coarse meshes, so a coarse model fits a softer tissue than the
one observed (docs/studies/calibration.md, "Limits"). The task's own mesh is chosen for the
task's quantities (grasp force and exposure within 5 % of a fine model,
docs/studies/scene_convergence.md), not for a modulus within 5 %; so each task names the
cheapest model whose fit meets issue 34's bar (E within 5 %, nu within 0.02 of a tissue
observed on a finer mesh) from the quantities that do, measured in
docs/benchmarks/calibration_mesh.md and docs/studies/calibration.md:

* ``heml_gym/TissueRetraction-v1``: its own 12 x 12 x 2 mesh, every quantity the file
  has (points and force together, or the force, meet the bar there; the tracked points
  alone do not on any affordable mesh: next to the held line of the jaws the tissue
  stretches more on every finer mesh, so the flap's points have no mesh-converged truth,
  and are flagged);
* ``heml_gym/OrganRetraction-v2``: a 7 mm lobe (the task's: 10 mm), the tracked points
  when the file has them (on the lobe the jaws' force carries the larger model error, and
  weighing it in moves E outside the bar; a file without points is fitted to what it has,
  flagged).

The fitted constants are the tissue's, so an env built from the fit (``physics={"fit":
...}``) on the task's own mesh gets them as they are: that mesh is within the task's 5 %
of a fine model of the same tissue. ``--env-kwargs`` (the user's model) and ``--use``
(the user's quantities) override these. Other ids (a scene of one's own) fit the env as
given, every quantity.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

__all__ = ["CalibrationModel", "CALIBRATION_MODELS", "MeshCorrection", "calibration_model", "correct_for_mesh"]


@dataclass(frozen=True)
class CalibrationModel:
    """The model ``heml-gym calibrate`` fits an env id's observations on by default."""

    #: ``gym.make`` keyword arguments of the fitted model (``{}``: the env's own)
    env_kwargs: dict = field(default_factory=dict)
    #: how the fitted model is named on the console and in fit.json
    label: str = "the env's own model"
    #: the observed quantities fitted by default, those of them the file has (None: every one)
    prefer: tuple[str, ...] | None = None
    #: per observed quantity: why a fit of it on this model may miss the bar (a console warning
    #: when it is fitted without a quantity that meets it)
    caveats: dict = field(default_factory=dict)
    #: ``gym.make`` keyword arguments of a finer model the fit is corrected towards
    #: (:func:`correct_for_mesh`; None: no correction)
    reference: dict | None = None
    #: how the reference is named
    reference_label: str = ""

    def quantities(self, present: list[str]) -> list[str]:
        """The quantities of ``present`` (those a file has) fitted by default."""
        if self.prefer is None:
            return list(present)
        chosen = [q for q in present if q in self.prefer]
        return chosen or list(present)

    def warnings(self, fitted: list[str]) -> list[str]:
        """The caveats of a fit of ``fitted`` quantities: a quantity's caveat holds when it
        is fitted without one that has none."""
        if any(q not in self.caveats for q in fitted):
            return []
        return [self.caveats[q] for q in fitted]


_FLAP_POINTS = ("the flap's tracked points alone fit E low on every affordable mesh (next to the jaws' held line "
                "the tissue has no mesh-converged shape; docs/studies/calibration.md#limits): record the jaws' force too")
_LOBE_FORCE = ("the lobe's jaws' force fits E low on the calibration's 7 mm lobe (its model error; "
               "docs/studies/calibration.md#limits): tracked points are the better witness")

#: Each task's calibration model (see the module docstring for the measurements).
CALIBRATION_MODELS = {
    "heml_gym/TissueRetraction-v1": CalibrationModel(label="the task's own 12 x 12 x 2 cells",
                                                     caveats={"points": _FLAP_POINTS}),
    "heml_gym/OrganRetraction-v2": CalibrationModel(env_kwargs={"mesh_size": 0.007},
                                                    label="a 7 mm lobe (the task's: 10 mm)", prefer=("points",),
                                                    caveats={"force": _LOBE_FORCE},
                                                    reference={"mesh_size": 0.005, "physics": {"max_dt": 0.025}},
                                                    reference_label="a 5 mm lobe in 0.025 s steps"),
}


def calibration_model(env_id: str) -> CalibrationModel:
    """The calibration model of ``env_id`` (a task's from :data:`CALIBRATION_MODELS`; any
    other id: the env as given, every quantity)."""
    return CALIBRATION_MODELS.get(env_id, CalibrationModel())


@dataclass
class MeshCorrection:
    """A fit corrected for the fitted mesh's own stiffness (:func:`correct_for_mesh`)."""

    reference: str  #: the finer model's name
    raw: list  #: the fit on the fitted model
    refit: list  #: the fitted model's fit to the reference's noise-free replay of ``raw``
    corrected: list  #: ``raw`` less the fitted model's bias against the reference
    std: list  #: the fit's standard errors, moduli's scaled as their values were
    converged: bool  #: whether the refit converged
    wall_s: float  #: the reference's replay and the refit, s


def correct_for_mesh(env_reference, obs, replay, fit_names, names, result, bounds, reference_label: str = "",
                     wrist_reach: float | None = None, regions=None) -> MeshCorrection:
    """Correct ``result`` (a :func:`heml_gym.calibration.fit` of ``names`` by ``replay``, the
    fitted model, to ``obs``) for the fitted mesh's bias against a finer model, by
    simulation: the tissue ``result.theta`` is replayed along ``obs``'s control log on
    ``env_reference`` (the finer model, ``fit_names`` / ``regions`` as the fit was set up),
    the fitted model is fitted to that replay's noise-free tracked points and force (the
    quantities ``obs`` has, weighed by the scales ``result`` ended with), and each
    constant's bias (the refit against ``theta``) is taken off: moduli by their ratio
    (``E theta / E refit``: a mesh's stiffening scales with E), the others by their
    difference, within ``bounds``. That is one replay of the finer model and one fit of
    the fitted one, where a fit on the finer model replays it at every iteration. The
    bias is taken at the fitted tissue, so it holds as far as it changes little between
    there and the truth (it scales with E; docs/studies/calibration.md measures what is left).
    Depth is not corrected (its rendering is the fitted model's): ``obs`` must have points
    or force."""
    from heml_gym.calibration import Observed, embed_points, fit

    from .observations import calibration_problem

    if obs.points is None and obs.force is None:
        raise ValueError("mesh correction: needs tracked points or the jaws' force (depth is not corrected)")
    t0 = time.perf_counter()
    theta = np.asarray(result.theta, dtype=np.float64)
    reference, *_ = calibration_problem(env_reference, obs, tuple(fit_names), wrist_reach=wrist_reach, regions=regions)
    ref = reference.run(theta)
    points = None
    if obs.points is not None:
        B = embed_points(reference.model.mesh, obs.rest_points)
        points = np.stack([B @ x for x in ref.x])
    force = None if obs.force is None else np.concatenate([obs.force[:1] * 0.0, ref.force])
    observed = Observed(points=points, rest_points=None if points is None else obs.rest_points, force=force,
                        point_scale=result.scales["point_scale_m"], force_scale=result.scales["force_scale_N"])
    refit = fit(replay, observed, names, [theta], bounds)
    corrected, std = [], []
    for name, raw, biased, sd, (low, high) in zip(names, theta, refit.theta, result.std, bounds):
        modulus = name.startswith("young_modulus")
        value = float(np.clip(raw * raw / biased if modulus else raw + (raw - biased), low, high))
        corrected.append(value)
        std.append(float(sd) * value / raw if modulus else float(sd))
    return MeshCorrection(reference=reference_label, raw=[float(v) for v in theta],
                          refit=[float(v) for v in refit.theta], corrected=corrected, std=std,
                          converged=bool(refit.converged), wall_s=time.perf_counter() - t0)
