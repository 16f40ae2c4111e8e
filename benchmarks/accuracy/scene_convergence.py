"""Scene convergence: is each retraction scene's default model within 5 % of a fine model?

The rule (docs/studies/scene_convergence.md): each scene uses the cheapest mesh, law and
integrator whose exposure and grasp force stay within 5 % of a fine model of the same
scene. Both scenes are Neo-Hookean HEML; what varies is the mesh, the integrator (explicit
sub-steps at ``safety`` times the critical step; backward Euler by L-BFGS or by Newton,
its step and tolerance) and, on the default mesh, the law. Both defaults are backward Euler
by L-BFGS (``heml_gym.QuasiNewtonSolver``).

Protocol, per scene and seed: the scripted baseline runs ``steps`` steps on the default
model and its actions are recorded; the same actions (the same gripper path) are replayed
on every model, ignoring termination. A seed fixes E, the target and the gripper start on
every model. Errors against the reference, over the default's episode (until its success:
the "window"; also over all steps):

* force: ``max_t |F(t) - F_ref(t)| / max_t F_ref(t)`` (F: the step-mean grasp force, N);
* exposure, strict: ``max_t |e(t) - e_ref(t)|`` (exposure is a fraction: 0.05 is 5 points);
* exposure, timing-tolerant: the same with ``e_ref`` read anywhere within half a step
  (0.05 s) of ``t`` (linear between steps). Where the flap edge crosses the tumour, exposure
  changes by up to 0.5 per step, so the strict error there measures a sub-millimetre
  difference in where the edge is;
* the shift (ms) of the time at which exposure first reaches 0.5 (linear between steps);
* the success step (exposure >= 0.8 with gauge strain < 0.5) of the model and of the reference.

A model is within 5 % when the force error and the timing-tolerant exposure error are
both <= 0.05 on its worst seed (and nothing diverged). A finer "check" model than the
reference estimates the reference's own error. Costs: median CPU ms per step on one
thread, and the deterministic M tet-sub-steps per step.

Writes docs/benchmarks/scene_convergence.{json,md}, scene_convergence_verdict.md (one line per
scene, for the top of docs/studies/scene_convergence.md) and docs/img/scene_convergence*.png.

    python benchmarks/accuracy/scene_convergence.py [tissue] [organ] [--quick] [--from-json]
    python benchmarks/accuracy/scene_convergence.py tissue --variation {jaws_adhesion,jaws,adhesion}
    python benchmarks/accuracy/scene_convergence.py organ --variation jaws
    python benchmarks/accuracy/scene_convergence.py tissue --variation wrist
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
from tqdm import tqdm
from heml_gym.benchmarks.common import IMAGES, RESULTS, machine_info, markdown_table, write_json
from heml_gym.envs import scripted
from heml_gym.envs.organ_retraction import DEFAULT_JAW_SIZE, OrganRetractionEnv, organ_scene
from heml_gym.envs.organ_retraction import JAWS_AND_ADHESION as ORGAN_JAWS_AND_ADHESION
from heml_gym.envs.tissue_retraction import JAWS_AND_ADHESION, TissueRetractionEnv, tissue_scene

TOLERANCE = 0.05
#: the scenes by their command-line names
SCENE_ARGS = {"tissue": "TissueRetraction", "organ": "OrganRetraction"}
#: ``--variation``: per-episode variation that is not a default, applied to every model of
#: a scene: jaws shorter than the grasp region, on each scene's default (whose underside is
#: stuck to the support, since 2026-11-25): the flap's 40 mm jaws
#: (``configs/experiments/quick_jaws_adhesion.yaml``), the lobe's 20 mm (the middle half of the 40 mm
#: footprint, where they close)
#: (the flap's ``wrist``: its jaws holding the 10 mm next to the edge on a free wrist,
#: ``scene.gripper.wrist_reach``; every model then by L-BFGS, the only integrator that steps it)
VARIATIONS = {"TissueRetraction": {"jaws": {"gripper": JAWS_AND_ADHESION["gripper"]},
                                   "wrist": {"gripper": {"wrist_reach": 0.01}}},
              "OrganRetraction": {"jaws": {"gripper": ORGAN_JAWS_AND_ADHESION["gripper"]}}}


@dataclass(frozen=True)
class Model:
    """One model of a scene: a label, how to build its scene, its explicit safety factor and
    any other physics (``(key, value)`` pairs of :class:`~heml_gym.envs.scene.PhysicsSpec`:
    the law, the integrator and its step)."""

    label: str
    scene_args: tuple
    safety: float
    physics: tuple = ()

    def env(self, scene_name: str, changes: dict | None = None):
        """The env of this model; ``changes``: scene fields merged into its scene (a
        ``--variation``)."""
        build = tissue_scene if scene_name == "TissueRetraction" else organ_scene
        cls = TissueRetractionEnv if scene_name == "TissueRetraction" else OrganRetractionEnv
        scene = build(*self.scene_args)
        if changes:
            scene = scene.updated(changes)
        return cls(scene=scene, physics={"safety": self.safety, **dict(self.physics)})

    @property
    def integrator(self) -> str:
        return dict(self.physics).get("integrator", "explicit")


def _tag(physics) -> str:
    p = dict(physics)
    parts = []
    if p.get("field", "heml") != "heml":
        parts.append(p["field"])
    if "material" in p:
        parts.append({"StVenantKirchhoff": "StVK", "StableNeoHookean": "SNH"}.get(p["material"], p["material"]))
    if p.get("integrator", "explicit") != "explicit":
        parts.append(f"{p['integrator']}{' BDF2' if p.get('scheme') == 'bdf2' else ''} dt={p.get('max_dt', 1 / 30):.3g}")
        if "newton_tol" in p:
            parts.append(f"tol={p['newton_tol']:g}")
    return (" " + " ".join(parts)) if parts else ""


def tissue(cells, safety=0.75, mirrored=True, **physics) -> Model:
    """A model of the flap: explicit unless ``physics`` names another integrator (the
    scene's own default is the quasi-Newton one, so explicit models say so)."""
    physics.setdefault("integrator", "explicit")
    tag = "" if mirrored else " uniform split"
    step = "" if physics["integrator"] != "explicit" else f" s={safety:g}"
    return Model(f"{'x'.join(map(str, cells))}{tag}{step}{_tag(physics)}", (tuple(cells), mirrored), safety,
                 tuple(sorted(physics.items())))


def organ(size, safety=0.5, jaw=None, edge=None, **physics) -> Model:
    """A model of the lobe held by the jaws' footprint (the scene's grasp): ``size`` (m)
    away from the jaws, ``jaw`` (m) around them, ``edge`` (m) along the thin edge (None:
    ``size``); explicit unless ``physics`` names another integrator (the scene's own
    default is the quasi-Newton one, so explicit models say so)."""
    physics.setdefault("integrator", "explicit")
    step = "" if physics["integrator"] != "explicit" else f" s={safety:g}"
    return Model(f"{lobe_mesh_label(size, edge, jaw)}{step}{_tag(physics)}", (size, edge, "patch", jaw), safety,
                 tuple(sorted(physics.items())))


def lobe_mesh_label(size: float, edge: float | None = None, jaw: float | None = None) -> str:
    """How a lobe mesh is named in the tables: its size (m), and its edge and jaw
    refinements (m) where it has them."""
    return (f"{1e3 * size:g} mm" + (f" / {1e3 * edge:g} mm edge" if edge else "")
            + (f" / {1e3 * jaw:g} mm at the jaws" if jaw else ""))


#: the lobe's element size around the jaws (m; configs/scenes/organ_retraction.yaml)
J = DEFAULT_JAW_SIZE
#: both scenes' default physics (configs/scenes/*.yaml)
QN = dict(integrator="quasi_newton", max_dt=0.05, newton_tol=3e-3, max_newton=100)
ORGAN_QN = QN
#: quadratic tets (physics field "quadratic"), stepped by Newton's backward Euler
P2 = dict(field="quadratic", integrator="implicit")


#: per scene: default, models (cheapest first), reference, check (finer than the reference)
#: and its seeds, seeds, steps
SCENES = {
    "TissueRetraction": dict(
        default=tissue((12, 12, 2), **QN),
        models=[tissue((8, 8, 1)), tissue((10, 10, 1)), tissue((12, 12, 1)), tissue((12, 12, 1), 0.5),
                tissue((8, 8, 1), mirrored=False), tissue((12, 12, 2)), tissue((16, 16, 2)), tissue((24, 24, 3)),
                # backward Euler by L-BFGS (the default) and by Newton, on the default and other meshes
                tissue((12, 12, 2), **QN), tissue((12, 12, 2), **{**QN, "newton_tol": 1e-2}),
                tissue((12, 12, 2), **{**QN, "max_dt": 0.1}), tissue((8, 8, 1), **QN), tissue((10, 10, 1), **QN),
                tissue((12, 12, 1), **QN), tissue((16, 16, 1), **QN), tissue((16, 16, 2), **QN),
                # the same by BDF2 (second order, the same cost per step)
                tissue((12, 12, 2), **QN, scheme="bdf2"), tissue((12, 12, 2), **{**QN, "max_dt": 0.1}, scheme="bdf2"),
                tissue((12, 12, 2), integrator="implicit", max_dt=0.1),
                tissue((12, 12, 2), integrator="implicit", max_dt=0.05),
                # the other laws on the default mesh and integrator
                tissue((12, 12, 2), **QN, material="StVenantKirchhoff"),
                tissue((12, 12, 2), **QN, material="StableNeoHookean"),
                # quadratic (10-node) tets by Newton's backward Euler: 6 x 6 x 1 has the default's nodes
                tissue((6, 6, 1), **P2, max_dt=0.05), tissue((6, 6, 1), **P2, max_dt=0.025),
                tissue((8, 8, 1), **P2, max_dt=0.025)],
        reference=tissue((32, 32, 4), 0.5), check=(tissue((40, 40, 5), 0.5), (1, 2)),
        seeds=(0, 1, 2, 3, 4), steps=50),
    "OrganRetraction": dict(
        default=organ(0.010, jaw=J, **ORGAN_QN),
        models=[organ(0.016), organ(0.012), organ(0.010), organ(0.008), organ(0.007),
                organ(0.008, 0.75, jaw=J), organ(0.008, 0.5, jaw=J), organ(0.008, 0.25, jaw=J),
                organ(0.008, 0.5, jaw=J, material="StableNeoHookean"),
                # backward Euler by L-BFGS (the default) and by Newton, on the default and other meshes
                organ(0.008, jaw=J, **ORGAN_QN),
                organ(0.008, jaw=J, **{**ORGAN_QN, "newton_tol": 1e-2}),
                organ(0.008, jaw=J, **{**ORGAN_QN, "max_dt": 0.1, "newton_tol": 1e-2}),
                organ(0.008, jaw=J, **{**ORGAN_QN, "max_dt": 0.1, "newton_tol": 1e-3}),
                organ(0.008, jaw=J, **{**ORGAN_QN, "max_dt": 0.025}),
                organ(0.010, jaw=J, **ORGAN_QN), organ(0.007, jaw=0.003, **ORGAN_QN), organ(0.006, jaw=J, **ORGAN_QN),
                organ(0.008, **ORGAN_QN), organ(0.007, **ORGAN_QN), organ(0.006, edge=0.004, **ORGAN_QN),
                organ(0.005, edge=0.003, **ORGAN_QN),
                # the same by BDF2 (second order, the same cost per step)
                organ(0.008, jaw=J, **ORGAN_QN, scheme="bdf2"),
                organ(0.008, jaw=J, **{**ORGAN_QN, "max_dt": 0.1}, scheme="bdf2"),
                organ(0.008, jaw=J, integrator="implicit", max_dt=0.1),
                organ(0.008, jaw=J, integrator="implicit", max_dt=0.05)],
        # the finest meshes of benchmarks/accuracy/grasp_convergence.py (0.9 % apart there)
        reference=organ(0.004, edge=0.0025), check=(organ(0.004, edge=0.002), (2, 3)),
        seeds=(0, 1, 2, 3, 4), steps=40),
}


#: ``--variation`` runs, on the flap, its models and these: more rows along the grasp edge,
#: more layers (where the error comes from); on the lobe, the
#: default, its mesh stepped explicitly, by L-BFGS in half the step and by BDF2 (the
#: integrator's share of the error), and finer meshes by L-BFGS (is there a model within
#: 5 %, and at what cost)
VARIATION_SPECS = {
    "TissueRetraction": {**SCENES["TissueRetraction"],
                         "models": SCENES["TissueRetraction"]["models"]
                         + [tissue((12, 24, 2), **QN), tissue((12, 12, 3), **QN), tissue((24, 24, 3), **QN)]},
    "OrganRetraction": {**SCENES["OrganRetraction"],
                        "models": [organ(0.010, 0.75, jaw=J), organ(0.010, jaw=J, **ORGAN_QN),
                                   organ(0.008, jaw=J, **ORGAN_QN),
                                   organ(0.008, jaw=J, **{**ORGAN_QN, "max_dt": 0.025}),
                                   organ(0.008, jaw=J, **ORGAN_QN, scheme="bdf2"),
                                   organ(0.008, jaw=J, **{**ORGAN_QN, "max_dt": 0.1}, scheme="bdf2"),
                                   organ(0.007, jaw=0.003, **ORGAN_QN), organ(0.006, jaw=J, **ORGAN_QN),
                                   organ(0.006, edge=0.004, **ORGAN_QN), organ(0.005, edge=0.003, **ORGAN_QN),
                                   organ(0.005, jaw=J, **ORGAN_QN)],
                        "check": (SCENES["OrganRetraction"]["check"][0], ())},
}


#: ``--variation wrist``: the flap's quasi-Newton models, the default's step and tolerance
#: varied, against a reference and a check stepped by L-BFGS in 0.0125 s steps to 1e-4 of the
#: weight (the explicit reference of the other runs cannot step a free wrist)
FINE_QN = {**QN, "max_dt": 0.0125, "newton_tol": 1e-4, "max_newton": 500}
WRIST_SPEC = {
    **SCENES["TissueRetraction"],
    "models": [tissue((8, 8, 1), **QN), tissue((10, 10, 1), **QN), tissue((12, 12, 1), **QN),
               tissue((12, 12, 2), **QN), tissue((12, 12, 2), **{**QN, "newton_tol": 1e-2}),
               tissue((12, 12, 2), **{**QN, "max_dt": 0.1}), tissue((12, 12, 2), **{**QN, "max_dt": 0.025}),
               tissue((16, 16, 2), **QN), tissue((18, 18, 3), **QN), tissue((24, 24, 3), **QN),
               tissue((32, 32, 4), **{**QN, "max_dt": 0.025})],
    "reference": tissue((32, 32, 4), **FINE_QN), "check": (tissue((40, 40, 5), **FINE_QN), (1, 2))}
#: the specs of the variations that have their own models (the others: VARIATION_SPECS)
OWN_SPECS = {("TissueRetraction", "wrist"): WRIST_SPEC}


def after_the_grasp(res: dict) -> str:
    """A table of each model's force error (worst seed, % of the reference's peak, over the
    default's episode) in the step in which the jaws close and over the steps after it:
    the closing step's force holds the impulse that sets the held tissue moving, which
    depends on how much tissue the mesh's vertex rows put in the jaws."""
    runs = {lab: {int(s): r for s, r in by.items()} for lab, by in res["runs"].items()}
    ref = runs[res["reference"]]
    windows = dict(zip(res["seeds"], res["windows"]))
    rows = []
    for lab, by in runs.items():
        closing, after = [], []
        for s, run in by.items():
            if lab == res["reference"] or s not in ref:
                continue
            F, F_ref = np.asarray(run["grasp_force"]), np.asarray(ref[s]["grasp_force"])
            w = windows[s]
            k = int(np.argmax(F_ref[:w] > 0))  # the step in which the jaws close
            err = np.abs(F[:w] - F_ref[:w]) / F_ref[:w].max()
            closing.append(err[k])
            after.append(err[k + 1:].max())
        if closing:
            rows.append([lab, f"{100 * max(closing):.1f}", f"{100 * max(after):.1f}"])
    return ("\nThe force error split at the jaws' closing (worst seed, % of the reference's peak force): the step "
            "in which they close, and every step after it.\n\n"
            + markdown_table(["model", "closing step", "after it"], rows))


def variation_name(scene: str, variation: str) -> str:
    """The results name of ``--variation``: ``scene_convergence_VARIATION`` for the flap (as
    first stored), ``scene_convergence_organ_VARIATION`` for the lobe."""
    return f"scene_convergence_{variation}" if scene == "TissueRetraction" else f"scene_convergence_organ_{variation}"


def record(scene: str, model: Model, seed: int, steps: int, changes: dict | None = None,
           policy_for=scripted.scripted_policy) -> tuple[np.ndarray, int]:
    """The actions of ``policy_for(scene)`` (default: the scripted baseline) on ``model``
    (its scene with ``changes``) from ``reset(seed)``, and its episode length."""
    env = model.env(scene, changes)
    policy = policy_for(env.scene)
    obs, _ = env.reset(seed=seed)
    policy.reset()
    actions, episode = [], None
    for k in range(steps):
        actions.append(policy(obs))
        obs, _, terminated, truncated, _ = env.step(actions[-1])  # past the end: the same path for all
        if episode is None and (terminated or truncated):
            episode = k + 1
    return np.array(actions), episode or steps


def replay(scene: str, model: Model, seed: int, actions: np.ndarray, probes=None,
           changes: dict | None = None) -> dict:
    """Per-step grasp force (N), exposure, gauge strain, outcomes and CPU time of ``model``
    (its scene with ``changes``); ``probes``: ``{name: fn(env) -> float}`` also recorded
    after every step."""
    env = model.env(scene, changes)
    _, info0 = env.reset(seed=seed)
    probes = probes or {}
    rec = {k: [] for k in ("grasp_force", "exposure", "max_strain", "success", "diverged", "unconverged", "cpu_s",
                           *probes)}
    for a in actions:
        c0 = time.thread_time()
        _, _, _, _, info = env.step(a)
        rec["cpu_s"].append(time.thread_time() - c0)
        for name, fn in probes.items():
            rec[name].append(float(fn(env)))
        for k in ("grasp_force", "exposure", "max_strain"):
            rec[k].append(float(info[k]))
        rec["success"].append(bool(info["is_success"]))
        rec["diverged"].append(bool(info["simulation_diverged"]))
        rec["unconverged"].append(not bool(info["solver_converged"]))
    task = env.task
    return {**rec, "young_modulus": float(info0["young_modulus"]), "n_tets": task.scene.mesh.n_tets,
            "n_vertices": task.scene.mesh.n_vertices, "substeps": task.substeps,
            "held": int(task.held[0].sum())}


def first(flags, n=None):
    idx = np.flatnonzero(np.asarray(flags)[:n])
    return int(idx[0]) + 1 if idx.size else None


def tolerant_exposure_error(e: np.ndarray, e_ref: np.ndarray, n: int | None = None) -> float:
    """``max`` over the first ``n`` steps of the distance of ``e(t)`` to the range of ``e_ref``
    within half a step of ``t`` (``e_ref`` linear between steps, held at the ends of the
    whole run, so that the window's last step may still look half a step ahead)."""
    e, e_ref = np.asarray(e, dtype=np.float64), np.asarray(e_ref, dtype=np.float64)
    padded = np.concatenate([e_ref[:1], e_ref, e_ref[-1:]])
    half_before = 0.5 * (padded[:-2] + padded[1:-1])
    half_after = 0.5 * (padded[1:-1] + padded[2:])
    lo = np.minimum(np.minimum(half_before, half_after), e_ref)
    hi = np.maximum(np.maximum(half_before, half_after), e_ref)
    gap = np.maximum(0.0, np.maximum(lo - e, e - hi))[:n]
    return float(gap.max()) if gap.size else 0.0


def crossing(e: np.ndarray, level: float = 0.5) -> float | None:
    """The (fractional) step at which ``e`` first reaches ``level``, linear between steps."""
    above = np.flatnonzero(np.asarray(e) >= level)
    if above.size == 0:
        return None
    k = int(above[0])
    if k == 0:
        return 1.0
    return k + (level - e[k - 1]) / (e[k] - e[k - 1])  # steps are numbered from 1


def errors(run: dict, ref: dict, window: int) -> dict:
    out = {}
    for tag, n in (("", window), ("_all", None)):
        f, fr = np.asarray(run["grasp_force"])[:n], np.asarray(ref["grasp_force"])[:n]
        e, er = np.asarray(run["exposure"])[:n], np.asarray(ref["exposure"])[:n]
        out.update({
            "force" + tag: float(np.max(np.abs(f - fr)) / np.max(fr)),
            "force_step" + tag: int(np.argmax(np.abs(f - fr))) + 1,  # the env step (1-based) it is largest after
            "force_mean" + tag: float(np.mean(np.abs(f - fr)) / np.max(fr)),
            "exposure_strict" + tag: float(np.max(np.abs(e - er))),
            "exposure" + tag: tolerant_exposure_error(run["exposure"], ref["exposure"], n),
            "peak_force_N" + tag: float(f.max()),
            "peak_strain" + tag: float(np.max(run["max_strain"][:n])),
            "peak_strain_ref" + tag: float(np.max(ref["max_strain"][:n])),
        })
    c, c_ref = crossing(np.asarray(run["exposure"])), crossing(np.asarray(ref["exposure"]))
    out["crossing_shift_ms"] = None if c is None or c_ref is None else 100.0 * abs(c - c_ref)
    out["success_step"] = first(run["success"])
    out["success_step_ref"] = first(ref["success"])
    out["diverged"] = bool(any(run["diverged"]))
    out["unconverged_steps"] = int(sum(run.get("unconverged", [])))
    return out


def summarise(scene: str, spec: dict, runs: dict, windows: dict, ref_label: str, model: Model, seeds) -> dict:
    errs = [errors(runs[model.label][s], runs[ref_label][s], windows[s]) for s in seeds]
    one = runs[model.label][seeds[0]]
    cpu = np.concatenate([runs[model.label][s]["cpu_s"] for s in seeds])
    row = {"scene": scene, "model": model.label, "default": model == spec["default"], "seeds": list(seeds),
           "n_vertices": one["n_vertices"], "n_tets": one["n_tets"], "substeps": one["substeps"],
           "held": one["held"], "M_tet_substeps_per_step": one["n_tets"] * one["substeps"] / 1e6,
           "cpu_ms_per_step": 1e3 * float(np.median(cpu)), "per_seed": errs,
           "success_steps": [e["success_step"] for e in errs],
           "success_steps_ref": [e["success_step_ref"] for e in errs],
           "diverged": any(e["diverged"] for e in errs), "integrator": model.integrator,
           "unconverged_steps": int(sum(e["unconverged_steps"] for e in errs))}
    shifts = [e["crossing_shift_ms"] for e in errs if e["crossing_shift_ms"] is not None]
    row["crossing_shift_ms"] = float(max(shifts)) if shifts else None
    for k in ("force", "force_mean", "exposure_strict", "exposure", "force_all", "exposure_all",
              "exposure_strict_all"):
        row[k] = float(max(e[k] for e in errs))
    row["force_step"] = max(errs, key=lambda e: e["force"])["force_step"]  # the worst seed's
    for k in ("peak_force_N", "peak_strain", "peak_strain_ref"):
        row[k] = float(np.median([e[k] for e in errs]))
    row["within_5pct"] = bool(row["force"] <= TOLERANCE and row["exposure"] <= TOLERANCE and not row["diverged"]
                              and row["unconverged_steps"] == 0)
    return row


def run_scene(scene: str, spec: dict, quick: bool, changes: dict | None = None) -> dict:
    """Record the scripted path on the default and replay it on every model of ``spec``,
    each scene with ``changes`` (a ``--variation``)."""
    seeds = spec["seeds"][:2] if quick else spec["seeds"]
    steps = 12 if quick else spec["steps"]
    check, check_seeds = spec["check"]
    models = spec["models"] + [spec["reference"]] + ([] if quick else [check])
    runs = {m.label: {} for m in models}
    windows, actions = {}, {}
    for seed in tqdm(seeds, desc=scene):
        actions[seed], windows[seed] = record(scene, spec["default"], seed, steps, changes)
        for m in models:
            if m is check and seed not in check_seeds:
                continue
            runs[m.label][seed] = replay(scene, m, seed, actions[seed], changes=changes)
    out = {"scene": scene, "seeds": list(seeds), "steps": steps, "windows": [windows[s] for s in seeds],
           "default": spec["default"].label, "reference": spec["reference"].label,
           "runs": {lab: {str(s): r for s, r in by.items()} for lab, by in runs.items()},
           "actions": {str(s): a.tolist() for s, a in actions.items()}}
    return tabulate(scene, spec, out)


def rerun_scene(scene: str, spec: dict, stored: dict, integrator: str) -> dict:
    """Replay again, on the stored seeds and paths, only the models stepped by
    ``integrator`` (its solver changed; the other models' code did not), keeping the
    stored runs of the others. The scripted path is recorded again on the default model
    first: if it is not the stored one, every model must be replayed, and this stops
    saying so."""
    check, check_seeds = spec["check"]
    chosen = [m for m in spec["models"] + [spec["reference"], check] if m.integrator == integrator]
    if not chosen:
        raise SystemExit(f"{scene} has no model stepped by {integrator!r}")
    for k, seed in enumerate(tqdm(stored["seeds"], desc=f"{scene} ({integrator} rows)")):
        actions, window = record(scene, spec["default"], seed, stored["steps"])
        same = np.array_equal(actions, np.asarray(stored["actions"][str(seed)])) and window == stored["windows"][k]
        if not same:
            raise SystemExit(f"{scene}, seed {seed}: the scripted path on the default model changed, so every "
                             f"model must replay it: run `python benchmarks/accuracy/scene_convergence.py "
                             f"{next(k for k, v in SCENE_ARGS.items() if v == scene)}` (no --rerun)")
        for m in chosen:
            if m is check and seed not in check_seeds:
                continue
            stored["runs"].setdefault(m.label, {})[str(seed)] = replay(scene, m, seed, actions)
    stored["rerun"] = {"integrator": integrator, "date": time.strftime("%Y-%m-%d"), "cpu": machine_info()["cpu"],
                       "models": [m.label for m in chosen]}
    return tabulate(scene, spec, stored)


def tabulate(scene: str, spec: dict, out: dict) -> dict:
    """(Re)compute the tables of ``out`` from its stored runs."""
    runs = {lab: {int(s): r for s, r in by.items()} for lab, by in out["runs"].items()}
    seeds, ref = out["seeds"], out["reference"]
    windows = dict(zip(seeds, out["windows"]))
    out["table"] = [summarise(scene, spec, runs, windows, ref, m, seeds) for m in spec["models"]]
    check, check_seeds = spec["check"]
    have = [s for s in check_seeds if s in runs.get(check.label, {})]
    if have:
        out["check"] = summarise(scene, spec, runs, windows, ref, check, have)
        out["check"]["against"] = ref
    return out


def tighter_twin_outside(scene: str, row: dict, rows: list[dict]) -> dict | None:
    """A model of ``scene`` with ``row``'s mesh and physics but a tighter solver tolerance
    (``newton_tol``) that is NOT within 5 %, if there is one."""
    models = {m.label: m for m in SCENES[scene]["models"]}
    own = models.get(row["model"])
    if own is None or "newton_tol" not in dict(own.physics):
        return None
    own_physics = dict(own.physics)
    for other in rows:
        m = models.get(other["model"])
        if m is None or m.scene_args != own.scene_args or other["within_5pct"]:
            continue
        physics = dict(m.physics)
        tol = physics.pop("newton_tol", None)
        if (tol is not None and tol < own_physics["newton_tol"]
                and physics == {k: v for k, v in own_physics.items() if k != "newton_tol"}):
            return other
    return None


def verdict(res: dict) -> str:
    rows = res["table"]
    default = next(r for r in rows if r["default"])
    ok = [r for r in rows if r["within_5pct"]]
    cheapest = min(ok, key=lambda r: r["cpu_ms_per_step"]) if ok else None
    text = (f"{res['scene']}: default {default['model']}: force error {100 * default['force']:.1f} %, exposure "
            f"error {default['exposure']:.3f} (strict {default['exposure_strict']:.3f}): "
            + ("within 5 %." if default["within_5pct"] else "NOT within 5 %."))
    if cheapest is not None:
        text += (f" Cheapest model within 5 %: {cheapest['model']} ({cheapest['cpu_ms_per_step']:.1f} CPU ms per "
                 "step)")
        tighter = tighter_twin_outside(res["scene"], cheapest, rows)
        if tighter is not None:
            text += (f", but the same step solved more tightly ({tighter['model']}) is not ({100 * tighter['force']:.1f} "
                     "% in force): its pass is a cancellation between the step's error and the loose solve's, not "
                     "a margin")
        text += "."
    if "check" in res:
        c = res["check"]
        text += (f" Reference check: {c['model']} differs from the reference {res['reference']} by "
                 f"{100 * c['force']:.1f} % in force and {c['exposure']:.3f} in exposure (seeds {c['seeds']}).")
        if not c["within_5pct"]:
            text += (" **The reference is not converged** (its check is not within 5 %): these errors are "
                     "not measured against a converged model.")
    return text


def _steps(values) -> str:
    return ", ".join("-" if v is None else str(v) for v in values)


def markdown(results: dict, wall: float) -> str:
    md = (f"Generated by `benchmarks/accuracy/scene_convergence.py` in {wall:.0f} s on one thread of a shared 2-core "
          "machine (CPU times are medians and noisy; M tet-sub-steps per step is the deterministic cost). "
          "Method and discussion: [docs/studies/scene_convergence.md](../studies/scene_convergence.md).\n\n"
          "Errors over the default's episode, worst over the seeds. Force: max |F - F_ref| / max F_ref (at step: "
          "the env step after which the worst seed's is largest); exposure: "
          "max |e - e_ref| with half a step of timing tolerance (strict: none). Crossing shift: how much "
          "earlier or later (ms, linear between steps) exposure first reaches 0.5 than on the reference; "
          "success: the step at which each seed succeeds on the model / on the reference.\n")
    for scene, res in results.items():
        md += (f"\n### {scene}\n\nReference {res['reference']}; seeds {res['seeds']}; the scripted baseline's "
               f"path ({res['steps']} steps) recorded on the default {res['default']}; its episodes (the window) "
               f"last {res['windows']} steps."
               + (f" The {res['rerun']['integrator']} rows were re-run on {res['rerun']['date']} ({res['rerun']['cpu']}; "
                  "`--rerun`: their solver changed, the other models' code did not, and the scripted path recorded on "
                  "the default was the stored one to the bit), the others are the stored runs."
                  if "rerun" in res else "") + "\n\n")
        rows = res["table"] + ([res["check"]] if "check" in res else [])
        md += markdown_table(
            ["model", "tets", "sub-steps", "M tet-sub-steps/step", "CPU ms/step", "held vertices",
             "force err %", "(at step)", "(mean %)", "exposure err", "(strict)", "exposure 0.5-crossing shift (ms)",
             "force err % all steps",
             "peak gauge strain (ref.)", "success step (ref.)", "within 5 %"],
            [[("**" + r["model"] + "** (default)") if r.get("default") else
              (r["model"] + (f" vs {r['against']} (check)" if "against" in r else "")),
              r["n_tets"], r["substeps"], f"{r['M_tet_substeps_per_step']:.2f}", f"{r['cpu_ms_per_step']:.1f}",
              r["held"], f"{100 * r['force']:.1f}", r["force_step"], f"{100 * r['force_mean']:.1f}", f"{r['exposure']:.3f}",
              f"{r['exposure_strict']:.3f}",
              "-" if r["crossing_shift_ms"] is None else f"{r['crossing_shift_ms']:.0f}", f"{100 * r['force_all']:.1f}",
              f"{r['peak_strain']:.2f} ({r['peak_strain_ref']:.2f})",
              f"{_steps(r['success_steps'])} ({_steps(r['success_steps_ref'])})",
              ("yes" if r["within_5pct"] else "no") + (" (diverged)" if r["diverged"] else "")
              + (f" ({r['unconverged_steps']} unconverged steps)" if r.get("unconverged_steps") else "")]
             for r in rows])
        md += "\n" + verdict(res) + "\n"
    return md


def charts(results: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(results), 2, figsize=(13, 4.8 * len(results)), squeeze=False)
    floor = 0.1  # % (a log axis: errors of 0 are drawn here)
    for row, (scene, res) in zip(axes, results.items()):
        table = res["table"]
        # labelled: the default, and the cheapest other model within 5 % (the table has every model)
        green = sorted((r for r in table if r["within_5pct"] and not r["default"]), key=lambda r: r["cpu_ms_per_step"])
        labelled = {id(r) for r in green[:1]} | {id(r) for r in table if r["default"]}
        for r in table:
            c = "tab:green" if r["within_5pct"] else "tab:red"
            for a, key in zip(row, ("force", "exposure")):
                y = max(100 * r[key], floor)
                a.plot(r["cpu_ms_per_step"], y, "*" if r["default"] else "o", color=c,
                       ms=14 if r["default"] else 6, mec="k" if r["default"] else c, zorder=3 if r["default"] else 2)
                if id(r) in labelled:
                    a.annotate(("default: " if r["default"] else "") + r["model"], (r["cpu_ms_per_step"], y),
                               fontsize=7, xytext=(6, 9 if r["default"] else -14), textcoords="offset points",
                               bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8})
        for a, title in zip(row, ("grasp force: max |F - F_ref| / max F_ref",
                                  "exposure: max |e - e_ref|, half a step of timing tolerance")):
            a.axhline(100 * TOLERANCE, color="k", ls="--", lw=1, label="5 % tolerance")
            a.set_xscale("log")
            a.set_yscale("log")
            a.set_ylim(floor * 0.8, 150)
            a.set_xlabel("cost: CPU ms per env step (one thread, median)")
            a.set_ylabel("worst error over seeds (%)")
            a.set_title(f"{scene} vs {res['reference']}\n{title}", fontsize=9)
            a.grid(alpha=0.3, which="both")
            a.legend(fontsize=8, loc="upper right")
    fig.suptitle("Error against a fine model vs cost (green within 5 %, red not; star: the default)", fontsize=10)
    fig.tight_layout()
    fig.savefig(IMAGES / "scene_convergence.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(len(results), 3, figsize=(14.5, 3.9 * len(results)), squeeze=False)
    for row, (scene, res) in zip(axes, results.items()):
        seed = str(res["seeds"][1 if len(res["seeds"]) > 1 else 0])
        labels = [res["default"], res["table"][0]["model"], res["reference"]]
        for lab in dict.fromkeys(labels):
            run = res["runs"][lab][seed]
            t = 0.1 * np.arange(1, len(run["exposure"]) + 1)
            for a, key in zip(row, ("grasp_force", "exposure", "max_strain")):
                a.plot(t, run[key], lw=2.0 if lab != labels[1] else 1.0, label=lab)
        window = res["windows"][res["seeds"].index(int(seed))]
        for a, name in zip(row, ("grasp force (N)", "exposure", "largest gauge strain")):
            a.axvline(0.1 * window, color="k", lw=0.8, ls=":")
            a.set_xlabel("time (s)")
            a.set_ylabel(name)
            a.set_title(f"{scene}, seed {seed}", fontsize=9)
            a.grid(alpha=0.3)
        row[0].legend(fontsize=7)
    fig.suptitle("The same gripper path on each model (dotted: the default's success)", fontsize=10)
    fig.tight_layout()
    fig.savefig(IMAGES / "scene_convergence_traces.png", dpi=110)
    plt.close(fig)
    speed_accuracy_chart(results, IMAGES / "scene_speed_accuracy.png")


def pareto(rows) -> list:
    """The rows no other row beats on both CPU time and error."""
    front = []
    for r in sorted(rows, key=lambda r: (r["cpu_ms_per_step"], max(r["force"], r["exposure"]))):
        err = max(r["force"], r["exposure"])
        if not front or err < max(front[-1]["force"], front[-1]["exposure"]):
            front.append(r)
    return front


def speed_accuracy_chart(results: dict, path: Path) -> None:
    """CPU time per env step against the worst error (max of force and exposure errors),
    every model of each scene, the Pareto front, the default starred, the 5 % line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from matplotlib.ticker import FuncFormatter, NullFormatter

    markers = {"explicit": "o", "implicit": "s", "quasi_newton": "^"}
    top = 100.0  # a diverged or unconverged model is drawn at the top, as an x
    fig, axes = plt.subplots(1, len(results), figsize=(6.5 * len(results), 5.6), squeeze=False)
    for ax, (scene, res) in zip(axes[0], results.items()):
        rows = [r for r in res["table"] if not r["diverged"]]
        front = pareto(rows)
        labelled = {id(r) for r in front}
        for r in sorted(res["table"], key=lambda r: r["default"]):  # the default drawn last, on top
            failed = r["diverged"] or r.get("unconverged_steps", 0) > 0
            err = top if failed else 100 * max(r["force"], r["exposure"])
            marker = "*" if r["default"] else ("x" if failed else markers.get(r.get("integrator"), "o"))
            ax.plot(r["cpu_ms_per_step"], err, marker, color="tab:green" if r["within_5pct"] else "tab:red",
                    ms=15 if r["default"] else 7, mew=2 if failed else 1, zorder=5 if r["default"] else 3)
            if r["default"] or failed or id(r) in labelled:
                text = r["model"] + (" (default)" if r["default"] else "") + (" failed" if failed else "")
                ax.annotate(text, (r["cpu_ms_per_step"], err), fontsize=6, xytext=(5, -3),
                            textcoords="offset points")
        ax.plot([r["cpu_ms_per_step"] for r in front], [100 * max(r["force"], r["exposure"]) for r in front],
                "-", color="0.5", lw=1, label="Pareto front")
        ax.axhline(100 * TOLERANCE, color="k", ls="--", lw=1, label="5 % tolerance")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylim(0.5, 2 * top)
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            axis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("CPU ms per env step (one thread, median)")
        ax.set_ylabel("worst error over seeds: max(force, exposure) (%)")
        ax.set_title(f"{scene} vs {res['reference']}", fontsize=9)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, title="o explicit, s implicit, ^ quasi-Newton, * default,\nx diverged or unconverged "
                  "(drawn at 100 %); labelled: the default, failures\nand the Pareto front (the others: in the table)", title_fontsize=7, loc="upper center",
                  bbox_to_anchor=(0.5, -0.14), ncol=2)
    fig.suptitle("Speed vs accuracy on the env scenes (green: within 5 % of the fine model)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*", help="tissue and/or organ (default: both)")
    ap.add_argument("--quick", action="store_true", help="two seeds, 12 steps, no check model; print only")
    ap.add_argument("--from-json", action="store_true", help="rebuild the tables and charts from the stored runs")
    ap.add_argument("--rerun", choices=("quasi_newton", "explicit", "implicit"), default=None,
                    help="replay only the models of this integrator (after a change to its solver), keeping the "
                         "stored runs of the others; stops if the default's scripted path changed")
    ap.add_argument("--variation", choices=sorted(VARIATIONS["TissueRetraction"]), default=None,
                    help="one scene with per-episode variation that is not a default (every model); writes only "
                         "docs/benchmarks/scene_convergence_VARIATION.{json,md} (the lobe: "
                         "scene_convergence_organ_VARIATION)")
    args = ap.parse_args(argv)
    if args.variation:
        if len(args.scenes) != 1 or args.scenes[0] not in SCENE_ARGS or args.from_json or args.rerun or args.quick:
            ap.error("--variation: run it as 'scene_convergence.py tissue --variation NAME' (or organ) alone")
        scene = SCENE_ARGS[args.scenes[0]]
        if args.variation not in VARIATIONS[scene]:
            ap.error(f"--variation: {args.scenes[0]} has {sorted(VARIATIONS[scene])}, got {args.variation!r}")
        changes = VARIATIONS[scene][args.variation]
        name = variation_name(scene, args.variation)
        numba.set_num_threads(1)
        start = time.perf_counter()
        spec = OWN_SPECS.get((scene, args.variation), VARIATION_SPECS[scene])
        results = {scene: run_scene(scene, spec, False, changes)}
        what = "The flap" if scene == "TissueRetraction" else "The lobe"
        md = (f"{what} with `--variation {args.variation}` ({changes}) on every model: not the "
              "default task; the tables of docs/studies/scene_convergence.md are the default's.\n\n"
              + markdown(results, time.perf_counter() - start) + after_the_grasp(results[scene]))
        write_json(f"{name}.json", {"machine": machine_info(), "wall_s": time.perf_counter() - start,
                                    "variation": args.variation, "changes": changes, "results": results})
        (RESULTS / f"{name}.md").write_text(md)
        print(md)
        return
    unknown = set(args.scenes) - set(SCENE_ARGS)
    if unknown:
        ap.error(f"unknown scenes {sorted(unknown)}: choose from tissue, organ")
    chosen = [SCENE_ARGS[s] for s in (args.scenes or SCENE_ARGS)]
    if args.from_json:
        stored = json.loads((RESULTS / "scene_convergence.json").read_text())
        results = {s: tabulate(s, SCENES[s], r) for s, r in stored["results"].items()}
        wall = stored["wall_s"]
    elif args.rerun:
        numba.set_num_threads(1)
        stored = json.loads((RESULTS / "scene_convergence.json").read_text())
        start = time.perf_counter()
        results = {s: (rerun_scene(s, SCENES[s], r, args.rerun) if s in chosen else tabulate(s, SCENES[s], r))
                   for s, r in stored["results"].items()}
        wall = stored["wall_s"] + time.perf_counter() - start
    else:
        numba.set_num_threads(1)
        start = time.perf_counter()
        results = {s: run_scene(s, SCENES[s], args.quick) for s in chosen}
        wall = time.perf_counter() - start
        stored_path = RESULTS / "scene_convergence.json"
        if not args.quick and stored_path.is_file() and set(chosen) != set(SCENE_ARGS.values()):
            stored = json.loads(stored_path.read_text())  # one scene re-run: keep the other's stored results
            results = {**{s: r for s, r in stored["results"].items() if s not in results}, **results}
            wall += stored["wall_s"]
    md = markdown(results, wall)
    print(md)
    if args.quick:
        return
    if args.from_json or args.rerun:
        stored["results"] = results
        stored["wall_s"] = wall
        write_json("scene_convergence.json", stored)
    else:
        write_json("scene_convergence.json", {"machine": machine_info(), "wall_s": wall, "results": results})
    (RESULTS / "scene_convergence.md").write_text(md)
    (RESULTS / "scene_convergence_verdict.md").write_text(
        "\n".join(f"* {verdict(res)}" for res in results.values()) + "\n")
    charts(results)


if __name__ == "__main__":
    main()
