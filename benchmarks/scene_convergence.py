"""Scene convergence: is TissueRetraction's default model within 5% of a fine model?

The rule (docs/scene_convergence.md): each scene uses the cheapest mesh, law and
integrator whose exposure and grasp force stay within 5% of a fine model of the same
scene. For ``heml_gym/TissueRetraction-v0`` the law (Neo-Hookean HEML) and the
integrator (explicit symplectic Euler) are fixed by the task; what can change is the mesh
(``TissueRetractionEnv(cells=...)``) and the explicit sub-step (``TaskSettings(safety=...)``).

Protocol. For each seed, the scripted fold-back policy runs ``STEPS`` steps on the default
model (cells (8, 8, 1), safety 0.5; past its success) and its action sequence is recorded;
that same sequence (the same gripper path) is replayed on every model, ignoring
termination. Every model draws the same E, target and gripper start for a seed. Per step
we record exposure, grasp force magnitude, largest edge strain, grasped vertices and the
time of the step (wall and CPU, one thread).

Errors against the reference (the finest mesh at safety 0.25), per seed, over the default
model's episode (until its success, at most ``STEPS`` steps; the "window"):
``force error`` = max_t |F(t) - F_ref(t)| / max_t F_ref(t); ``exposure error`` =
max_t |e(t) - e_ref(t)| (exposure is a fraction, so 0.05 is 5 percentage points); and
the shift of the step at which exposure first reaches 0.8. A model is within 5% when
both errors, worst over the seeds, are <= 0.05. The same errors over all ``STEPS`` steps
(the fold continued past the default's success) are kept too.

Two side studies: a finer mesh than the reference (``CHECK``, fewer seeds) estimates the
reference's own discretisation error; and a "controlled grasp" (``CONTROLLED``: the
gripper starts right above the free edge's middle top vertex, which every mesh has, and
holds only that vertex, ``jaw_radius`` = 0) separates the grasp discretisation (which
vertices are held) from the discretisation of the tissue itself.

Writes docs/benchmarks/scene_convergence.{json,md}, docs/img/scene_convergence.png and
docs/img/scene_convergence_traces.png.

    python benchmarks/scene_convergence.py [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numba
import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import IMAGES, RESULTS, machine_info, markdown_table, write_json  # noqa: E402
from heml_gym.envs.core import TaskSettings  # noqa: E402
from heml_gym.envs.tissue_retraction import TissueRetractionEnv  # noqa: E402

SEEDS = (0, 1, 2, 3, 4)
STEPS = 40
TOLERANCE = 0.05
DEFAULT = ((8, 8, 1), 0.5)
REFERENCE = ((24, 24, 3), 0.25)
#: (cells, safety[, jaw_radius m]), cheapest first: the default, integrator checks on it,
#: mesh refinements, and the reference mesh with a one-vertex grasp (jaw_radius 0)
MODELS = [
    ((8, 8, 1), 0.5),
    ((8, 8, 1), 0.25),
    ((8, 8, 1), 0.9),
    ((12, 12, 1), 0.5),
    ((8, 8, 2), 0.5),
    ((12, 12, 2), 0.5),
    ((16, 16, 2), 0.5),
    ((16, 16, 3), 0.5),
    ((24, 24, 3), 0.5),
    ((24, 24, 3), 0.5, 0.0),
    ((24, 24, 3), 0.25),
]
#: finer than the reference, to estimate the reference's own error (fewer seeds)
CHECK = (((32, 32, 4), 0.5), (0, 1))
#: controlled grasp: every mesh holds the same material vertex (free edge, middle, top)
CONTROLLED_START = (0.12, 0.06, 0.010)  # m: 2 mm above that vertex
CONTROLLED = ([((8, 8, 1), 0.5, 0.0), ((12, 12, 2), 0.5, 0.0), ((16, 16, 2), 0.5, 0.0),
               ((24, 24, 3), 0.5, 0.0), ((32, 32, 4), 0.5, 0.0)], (0, 1))


def label(model) -> str:
    cells, safety = model[:2]
    jaw = f" jaw={1e3 * model[2]:g}mm" if len(model) > 2 else ""
    return f"{cells[0]}x{cells[1]}x{cells[2]} s={safety:g}{jaw}"


def settings_of(model) -> TaskSettings:
    st = TaskSettings(safety=model[1])
    if len(model) > 2:
        st.jaw_radius = model[2]
    return st


def _policy():
    from heml_gym.envs import scripted

    if hasattr(scripted, "scripted_policy"):
        return scripted.scripted_policy("TissueRetraction")
    return scripted.FoldBackPolicy()


def _reset(env, seed, gripper_start):
    obs, info = env.reset(seed=seed)
    if gripper_start is not None:  # benchmark-only override of the start state
        env.task.gripper[0] = gripper_start
        obs = env._obs()
    return obs, info


def record_actions(seed: int, steps: int, gripper_start=None) -> tuple[np.ndarray, int]:
    """The scripted policy's actions on the default model, ``steps`` steps from ``reset(seed)``,
    and the length of the default's episode (its first termination, or ``steps``)."""
    env = TissueRetractionEnv(cells=DEFAULT[0], settings=settings_of(DEFAULT))
    policy = _policy()
    obs, _ = _reset(env, seed, gripper_start)
    policy.reset()
    actions, episode = [], None
    for k in range(steps):
        a = policy(obs)
        actions.append(a)
        obs, _, terminated, truncated, _ = env.step(a)  # past termination: the same path for all
        if episode is None and (terminated or truncated):
            episode = k + 1
    return np.array(actions), episode or steps


def replay(model, seed: int, actions: np.ndarray, gripper_start=None) -> dict:
    """Run ``actions`` on ``model`` from ``reset(seed)``; per-step measurements."""
    cells, safety = model[:2]
    env = TissueRetractionEnv(cells=cells, settings=settings_of(model))
    obs, info0 = _reset(env, seed, gripper_start)
    task = env.task
    rec = {k: [] for k in ("exposure", "grasp_force", "max_strain", "held", "wall_s", "cpu_s",
                           "success", "torn", "diverged")}
    held_offset = None
    for a in actions:
        c0, t0 = time.thread_time(), time.perf_counter()
        obs, _, terminated, truncated, info = env.step(a)
        rec["wall_s"].append(time.perf_counter() - t0)
        rec["cpu_s"].append(time.thread_time() - c0)
        rec["exposure"].append(info["exposure"])
        rec["grasp_force"].append(info["grasp_force"])
        rec["max_strain"].append(info["max_strain"])
        rec["held"].append(int(task.held[0].sum()))
        rec["success"].append(bool(info["is_success"]))
        rec["torn"].append(bool(info["tissue_torn"]))
        rec["diverged"].append(bool(info["simulation_diverged"]))
        if held_offset is None and task.held[0].any():
            held_offset = task.offsets[0, task.held[0]].mean(axis=0).tolist()
    mesh = task.scene.mesh
    return {"model": label(model), "cells": list(cells), "safety": safety,
            "jaw_radius": task.settings.jaw_radius, "seed": seed,
            "young_modulus": info0["young_modulus"], "n_vertices": mesh.n_vertices, "n_tets": mesh.n_tets,
            "substeps": task.substeps, "held_offset_m": held_offset, **rec}


def _first(flags, n=None):
    idx = np.flatnonzero(np.asarray(flags)[:n])
    return int(idx[0]) + 1 if idx.size else None


def errors(run: dict, ref: dict, window: int) -> dict:
    """Errors of ``run`` against ``ref`` over the first ``window`` steps and over all steps."""
    out = {"window": window}
    for tag, n in (("", window), ("_all", None)):
        f, fr = np.asarray(run["grasp_force"])[:n], np.asarray(ref["grasp_force"])[:n]
        e, er = np.asarray(run["exposure"])[:n], np.asarray(ref["exposure"])[:n]
        s, sr = np.asarray(run["max_strain"])[:n], np.asarray(ref["max_strain"])[:n]
        cross, cross_ref = _first(e >= 0.8), _first(er >= 0.8)
        out.update({
            "force_rel_err" + tag: float(np.max(np.abs(f - fr)) / np.max(fr)),
            "force_rel_err_mean" + tag: float(np.mean(np.abs(f - fr)) / np.max(fr)),
            "exposure_abs_err" + tag: float(np.max(np.abs(e - er))),
            "exposure_abs_err_mean" + tag: float(np.mean(np.abs(e - er))),
            "exposure_cross_shift" + tag: (None if cross is None or cross_ref is None else cross - cross_ref),
            "strain_rel_err" + tag: float(np.max(np.abs(s - sr)) / np.max(sr)),
            "peak_strain" + tag: float(s.max()),
            "peak_force_N" + tag: float(f.max()),
            "success_step" + tag: _first(run["success"], n),
            "torn_step" + tag: _first(run["torn"], n),
        })
    out["diverged"] = bool(any(run["diverged"]))
    return out


def summarise(runs: dict, models, seeds, ref_label: str, windows: dict) -> list[dict]:
    rows = []
    for m in models:
        lab = label(m)
        have = [s for s in seeds if s in runs.get(lab, {}) and s in runs[ref_label]]
        errs = [errors(runs[lab][s], runs[ref_label][s], windows[s]) for s in have]
        one = runs[lab][have[0]]
        cpu = np.concatenate([runs[lab][s]["cpu_s"] for s in have])
        wall = np.concatenate([runs[lab][s]["wall_s"] for s in have])
        row = {"model": lab, "cells": one["cells"], "safety": one["safety"], "jaw_radius": one["jaw_radius"],
               "n_vertices": one["n_vertices"], "n_tets": one["n_tets"], "substeps": one["substeps"],
               "M_tet_substeps_per_step": one["n_tets"] * one["substeps"] / 1e6,
               "median_cpu_ms_per_step": 1e3 * float(np.median(cpu)),
               "median_wall_ms_per_step": 1e3 * float(np.median(wall)),
               "held_vertices": sorted({max(runs[lab][s]["held"]) for s in have}),
               "held_offsets_mm": [[round(1e3 * c, 1) for c in runs[lab][s]["held_offset_m"]] for s in have],
               "seeds": have}
        for k in ("force_rel_err", "force_rel_err_mean", "exposure_abs_err", "exposure_abs_err_mean",
                  "strain_rel_err", "force_rel_err_all", "exposure_abs_err_all", "strain_rel_err_all"):
            vals = [e[k] for e in errs]
            row[k + "_worst"] = float(np.max(vals))
            row[k + "_median"] = float(np.median(vals))
        for k in ("peak_strain", "peak_force_N", "peak_strain_all", "peak_force_N_all"):
            row[k + "_median"] = float(np.median([e[k] for e in errs]))
        for k in ("exposure_cross_shift", "exposure_cross_shift_all", "success_step", "torn_step",
                  "torn_step_all"):
            row[k] = [e[k] for e in errs]
        row["diverged"] = any(e["diverged"] for e in errs)
        row["within_5pct"] = bool(row["force_rel_err_worst"] <= TOLERANCE
                                  and row["exposure_abs_err_worst"] <= TOLERANCE and not row["diverged"])
        row["per_seed"] = errs
        rows.append(row)
    return rows


def _steps(steps, signed=False):
    return ", ".join("-" if s is None else (f"{s:+d}" if signed else str(s)) for s in steps)


def markdown(res: dict) -> str:
    md = ("# Scene convergence: TissueRetraction-v0\n\n"
          f"Generated by `benchmarks/scene_convergence.py` in {res['wall_s']:.0f} s on {res['machine']['cpu']} "
          f"({res['machine']['cores']} cores, shared: times are medians and noisy; CPU time is the steadier "
          "cost). Method and discussion: [docs/scene_convergence.md](../scene_convergence.md). "
          f"Scripted fold-back path recorded on the default model for {res['steps']} steps and replayed on "
          f"every model; seeds {list(res['seeds'])}; reference {res['reference']}; the default's episodes "
          f"(the comparison window) last {res['windows']} steps.\n\n"
          "Errors over the window, worst over the seeds (median in brackets). Force: max over steps of "
          "|F - F_ref| / max F_ref. Exposure: max over steps of |e - e_ref| (fraction). Crossing shift: "
          "the step at which exposure first reaches 0.8, minus the reference's, per seed (over all steps). "
          "Success/torn: first step, per seed, within the window (- if none).\n\n")
    table = []
    for r in res["table"]:
        table.append([
            r["model"], r["n_vertices"], r["n_tets"], r["substeps"], f"{r['M_tet_substeps_per_step']:.2f}",
            f"{r['median_cpu_ms_per_step']:.1f}", f"{r['median_wall_ms_per_step']:.1f}",
            "/".join(str(h) for h in r["held_vertices"]),
            f"{100 * r['force_rel_err_worst']:.1f} ({100 * r['force_rel_err_median']:.1f})",
            f"{r['exposure_abs_err_worst']:.3f} ({r['exposure_abs_err_median']:.3f})",
            _steps(r["exposure_cross_shift_all"], signed=True),
            f"{r['peak_force_N_median']:.3f}", f"{r['peak_strain_median']:.2f}",
            _steps(r["success_step"]), _steps(r["torn_step"]),
            ("yes" if r["within_5pct"] else "no") + (" (diverged)" if r["diverged"] else ""),
        ])
    md += markdown_table(["model", "vertices", "tets", "sub-steps", "M tet-sub-steps/step", "CPU ms/step",
                          "wall ms/step", "held vertices", "force err % worst (median)",
                          "exposure err worst (median)", "0.8-crossing shift (steps)", "peak force N (median)",
                          "peak strain (median)", "success step", "torn step", "within 5%"], table)
    md += (f"\nThe fold continued to {res['steps']} steps (past the default's success), same errors over all "
           "steps:\n\n")
    md += markdown_table(
        ["model", "force err % worst (median)", "exposure err worst", "peak force N (median)",
         "peak strain (median)", "torn step"],
        [[r["model"], f"{100 * r['force_rel_err_all_worst']:.1f} ({100 * r['force_rel_err_all_median']:.1f})",
          f"{r['exposure_abs_err_all_worst']:.3f}", f"{r['peak_force_N_all_median']:.3f}",
          f"{r['peak_strain_all_median']:.2f}", _steps(r["torn_step_all"])] for r in res["table"]])
    if res.get("check"):
        c = res["check"]
        md += (f"\nReference check (the reference's own discretisation error), seeds {c['seeds']}: {c['model']} "
               f"against {res['reference']}: force {100 * c['force_rel_err_worst']:.1f}% "
               f"({100 * c['force_rel_err_all_worst']:.1f}% over all steps), exposure {c['exposure_abs_err_worst']:.3f}, "
               f"largest edge strain {100 * c['strain_rel_err_worst']:.0f}%; held vertices "
               f"{'/'.join(str(h) for h in c['held_vertices'])}; {c['median_cpu_ms_per_step']:.0f} CPU ms per step.\n")
    if res.get("controlled"):
        cr = res["controlled"]
        md += (f"\nControlled grasp (gripper starts at {cr['start_m']} m, 2 mm above the free edge's middle top "
               f"vertex, which every mesh has; jaw_radius 0: every mesh holds that one vertex), seeds {cr['seeds']}, "
               f"against {cr['reference']}:\n\n")
        md += markdown_table(
            ["model", "CPU ms/step", "held vertices", "force err % (window)", "force err % (all steps)",
             "exposure err (window)", "peak force N (all, median)", "peak strain (all, median)"],
            [[r["model"], f"{r['median_cpu_ms_per_step']:.1f}", "/".join(str(h) for h in r["held_vertices"]),
              f"{100 * r['force_rel_err_worst']:.1f}", f"{100 * r['force_rel_err_all_worst']:.1f}",
              f"{r['exposure_abs_err_worst']:.3f}", f"{r['peak_force_N_all_median']:.3f}",
              f"{r['peak_strain_all_median']:.2f}"] for r in cr["table"]])
    md += "\n" + res["verdict"] + "\n"
    return md


def _ms_per_m(rows) -> float:
    """Median CPU ms per million tet-sub-steps over the models with >= 1 M per step."""
    big = [r["median_cpu_ms_per_step"] / r["M_tet_substeps_per_step"] for r in rows if r["M_tet_substeps_per_step"] >= 1]
    return float(np.median(big)) if big else float("nan")


def verdict(rows, reference: str) -> str:
    default = next(r for r in rows if r["model"] == label(DEFAULT))
    ok = [r for r in rows if r["within_5pct"] and r["model"] != reference and "jaw" not in r["model"]]
    cheapest = min(ok, key=lambda r: r["median_cpu_ms_per_step"]) if ok else None
    lines = [f"Default {label(DEFAULT)}: force error {100 * default['force_rel_err_worst']:.1f}%, exposure error "
             f"{default['exposure_abs_err_worst']:.3f}: " + ("within 5%." if default["within_5pct"] else "NOT within 5%.")]
    if cheapest is not None:
        lines.append(f"Cheapest model within 5% of the reference: {cheapest['model']} "
                     f"({cheapest['median_cpu_ms_per_step']:.1f} CPU ms per step, "
                     f"{cheapest['median_cpu_ms_per_step'] / default['median_cpu_ms_per_step']:.0f}x the default).")
    else:
        lines.append("No model cheaper than the reference is within 5%.")
    return "\n\n".join(lines)


def charts(res: dict, runs: dict):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in res["table"] if r["model"] != res["reference"]]
    fig, ax = plt.subplots(1, 2, figsize=(12.5, 4.8))
    keys = ("force_rel_err_worst", "exposure_abs_err_worst")
    for i, r in enumerate(rows):
        x = r["M_tet_substeps_per_step"]
        c = "tab:green" if r["within_5pct"] else ("tab:purple" if "jaw" in r["model"] else "tab:red")
        mk = {0.25: "v", 0.5: "o", 0.9: "^"}.get(r["safety"], "s")
        dy = {0.25: -12, 0.9: 12}.get(r["safety"], 3 - 11 * (i % 2))
        for a, key in zip(ax, keys):
            a.plot(x, 100 * r[key], mk, color=c, ms=8)
            a.annotate(r["model"], (x, 100 * r[key]), fontsize=7, xytext=(5, dy), textcoords="offset points")
    chk = res.get("check")
    if chk:
        for a, key in zip(ax, keys):
            a.plot(chk["M_tet_substeps_per_step"], 100 * chk[key], "*", color="tab:gray", ms=12)
            a.annotate(chk["model"] + " (finer than ref)", (chk["M_tet_substeps_per_step"], 100 * chk[key]),
                       fontsize=7, xytext=(-70, 7), textcoords="offset points")
    for a, title in zip(ax, ("grasp force: max |F - F_ref| / max F_ref", "exposure: max |e - e_ref|")):
        a.axhline(100 * TOLERANCE, color="k", ls="--", lw=1, label="5% tolerance")
        a.set_xscale("log")
        a.set_xlabel("cost: M tet-sub-steps per env step (physics is 80-95% of a step;\n"
                     f"~{res['ms_per_M_tet_substeps']:.0f} CPU ms per M here, see the table for measured times)")
        a.set_ylabel("worst error over seeds (%)")
        a.set_title(title, fontsize=10)
        a.grid(alpha=0.3, which="both")
        a.set_ylim(bottom=0)
        a.legend(fontsize=8)
    fig.suptitle(f"TissueRetraction-v0 against {res['reference']} over the default's episodes "
                 "(green within 5%, red not, purple one-vertex grasp; o safety 0.5, v 0.25, ^ 0.9)", fontsize=9.5)
    fig.tight_layout()
    fig.savefig(IMAGES / "scene_convergence.png", dpi=120)
    plt.close(fig)

    show = [label(DEFAULT), "12x12x2 s=0.5", "16x16x2 s=0.5", "24x24x3 s=0.5 jaw=0mm", res["reference"],
            label(CHECK[0])]
    trace_seeds = res["seeds"][:2]
    fig, axes = plt.subplots(len(trace_seeds), 3, figsize=(14.5, 3.9 * len(trace_seeds)), squeeze=False)
    for row, seed in zip(axes, trace_seeds):
        for lab in show:
            run = runs.get(lab, {}).get(seed)
            if run is None:
                continue
            t = 0.1 * np.arange(1, len(run["exposure"]) + 1)
            lw = 2.2 if lab in (res["reference"], label(DEFAULT)) else 1.1
            for a, key in zip(row, ("grasp_force", "exposure", "max_strain")):
                a.plot(t, run[key], lw=lw, label=lab)
        window = res["windows"][res["seeds"].index(seed)]
        for a, name in zip(row, ("grasp force (N)", "exposure", "largest edge strain")):
            a.axvline(0.1 * window, color="k", lw=0.8, ls=":")
            a.set_xlabel("time (s)")
            a.set_ylabel(name)
            a.set_title(f"seed {seed}", fontsize=9)
            a.grid(alpha=0.3)
        row[2].axhline(0.5, color="tab:orange", ls="--", lw=1, label="damage strain")
        row[2].axhline(1.0, color="tab:red", ls="-.", lw=1, label="tear strain")
    axes[0, 0].legend(fontsize=7)
    axes[0, 2].legend(fontsize=7)
    fig.suptitle("The same gripper path on every model (dotted: the default's success, the end of its episode)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(IMAGES / "scene_convergence_traces.png", dpi=120)
    plt.close(fig)


def _int_keys(runs: dict) -> dict:
    return {lab: {int(s): r for s, r in by_seed.items()} for lab, by_seed in runs.items()}


def resummarise():
    """Rebuild the tables, verdict, markdown and charts from the stored runs."""
    import json

    path = RESULTS / "scene_convergence.json"
    res = json.loads(path.read_text())
    runs, ctrl_runs = _int_keys(res["runs"]), _int_keys(res.get("controlled_runs", {}))
    seeds = res["seeds"]
    windows = dict(zip(seeds, res["windows"]))
    ref = res["reference"]
    models = [m for m in MODELS if label(m) in runs]
    res["table"] = summarise(runs, models, seeds, ref, windows)
    check_model, check_seeds = CHECK
    if label(check_model) in runs:
        res["check"] = summarise(runs, [check_model], list(check_seeds), ref, windows)[0]
    if ctrl_runs:
        cr = res["controlled"]
        ctrl_models = [m for m in CONTROLLED[0] if label(m) in ctrl_runs]
        cr["table"] = summarise(ctrl_runs, ctrl_models, cr["seeds"], cr["reference"],
                                dict(zip(cr["seeds"], cr["windows"])))
    res["verdict"] = verdict(res["table"], ref)
    res["ms_per_M_tet_substeps"] = _ms_per_m(res["table"])
    md = markdown(res)
    write_json("scene_convergence.json", res)
    (RESULTS / "scene_convergence.md").write_text(md)
    charts(res, runs)
    print(md)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="two seeds, 15 steps, no side studies, print only")
    ap.add_argument("--steps", type=int, default=None, help="steps per trajectory (smoke tests)")
    ap.add_argument("--no-write", action="store_true", help="print only")
    ap.add_argument("--from-json", action="store_true",
                    help="re-summarise the stored runs (docs/benchmarks/scene_convergence.json), no simulation")
    args = ap.parse_args()
    if args.from_json:
        return resummarise()
    numba.set_num_threads(1)
    seeds = SEEDS[:2] if args.quick else SEEDS
    steps = args.steps or (15 if args.quick else STEPS)
    start = time.perf_counter()
    recorded = {s: record_actions(s, steps) for s in seeds}
    actions = {s: a for s, (a, _) in recorded.items()}
    windows = {s: w for s, (_, w) in recorded.items()}
    check_model, check_seeds = CHECK
    ctrl_models, ctrl_seeds = CONTROLLED
    side = not args.quick
    ctrl_actions = {s: record_actions(s, steps, CONTROLLED_START) for s in ctrl_seeds} if side else {}
    jobs = [("main", m, s) for m in MODELS for s in seeds]
    if side:
        jobs += [("main", check_model, s) for s in check_seeds]
        jobs += [("ctrl", m, s) for m in ctrl_models for s in ctrl_seeds]
    runs, ctrl_runs = {}, {}
    for kind, m, s in tqdm(jobs, desc="model x seed"):
        if kind == "main":
            runs.setdefault(label(m), {})[s] = replay(m, s, actions[s])
        else:
            ctrl_runs.setdefault(label(m), {})[s] = replay(m, s, ctrl_actions[s][0], CONTROLLED_START)
    ref = label(REFERENCE)
    rows = summarise(runs, MODELS, seeds, ref, windows)
    res = {"machine": machine_info(), "steps": steps, "seeds": list(seeds), "tolerance": TOLERANCE,
           "default": label(DEFAULT), "reference": ref, "windows": [windows[s] for s in seeds], "table": rows}
    if side:
        res["check"] = summarise(runs, [check_model], list(check_seeds), ref, windows)[0]
        ctrl_ref = label(ctrl_models[-1])
        ctrl_windows = {s: ctrl_actions[s][1] for s in ctrl_seeds}
        res["controlled"] = {"start_m": list(CONTROLLED_START), "seeds": list(ctrl_seeds), "reference": ctrl_ref,
                             "windows": [ctrl_windows[s] for s in ctrl_seeds],
                             "table": summarise(ctrl_runs, ctrl_models, list(ctrl_seeds), ctrl_ref, ctrl_windows)}
    res["verdict"] = verdict(rows, ref)
    res["ms_per_M_tet_substeps"] = _ms_per_m(rows)
    res["wall_s"] = time.perf_counter() - start
    res["actions"] = {str(s): actions[s].tolist() for s in seeds}
    res["runs"] = {lab: {str(s): r for s, r in by_seed.items()} for lab, by_seed in runs.items()}
    res["controlled_runs"] = {lab: {str(s): r for s, r in by_seed.items()} for lab, by_seed in ctrl_runs.items()}
    md = markdown(res)
    if not (args.quick or args.no_write):
        write_json("scene_convergence.json", res)
        (RESULTS / "scene_convergence.md").write_text(md)
        IMAGES.mkdir(parents=True, exist_ok=True)
        charts(res, runs)
    print(md)


if __name__ == "__main__":
    main()
