"""Reliability soak: hostile-but-fair actions in both envs, and every bad input we know of.

Part 1, the soak. For each environment (TissueRetraction, OrganRetraction), single and
vector (N = 8), state and point-cloud observations, with these action streams:

* ``random``: uniform in [-1, 1]^4;
* ``extreme``: bang-bang, every component -1 or +1, times up to 50 (clipped by the env);
* ``toggling``: random motion with the grasp command flipping every step;
* ``out_of_range``: uniform in [-100, 100]^4 (clipped by the env);
* ``push_release``: grasp, push the held edge towards the attachment for 7 steps, release
  (the pattern that made the explicit physics diverge before the fix of issue 12);
* ``scripted``: the fold-back baseline.

It counts env steps, episodes, physics divergences (``info["simulation_diverged"]``),
unconverged solves, non-finite values anywhere in an observation, reward or ``info``,
observations outside their space, exceptions, the slowest step, and the steps the solver
re-took in shorter sub-steps or by its Newton fallback.

Part 1b, the streams (``--stream-steps``): per environment, 20 seeded streams of each of
``push_release``, ``random`` and ``extreme`` (a 20-scene vector env), each ``--stream-steps``
env steps long, with the failures of every stream counted: the acceptance check of
"every step converges, on any CPU".

With ``--targets host,haswell`` the whole run is repeated with the Numba kernels compiled
for each target (a child process per target, one core each, concurrently; non-host
targets with ``NUMBA_CPU_NAME=<target> NUMBA_CPU_FEATURES=""`` and their own cache), and
every row records the target it ran under (``codegen``): rounding, and so the solver's
convergence, differs between instruction sets.

Part 2, bad inputs: every bad argument of the public entry points this project knows of,
each run, and the error it gets (the first line of its message).

Writes docs/benchmarks/reliability.{json,md} and docs/img/reliability.png.

    python benchmarks/reliability/reliability.py [--steps 2000]      # env steps per env (split over the streams)
    python benchmarks/reliability/reliability.py --steps 200000,60000 --stream-steps 2000 --targets host,haswell
                                    # the published run: over 1,000,000 env steps in all
    python benchmarks/reliability/reliability.py --envs heml_gym/OrganRetraction-v2 --steps 50000 --merge
                                    # re-soak one env, keeping the stored rows of the others
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import traceback
from pathlib import Path

import gymnasium as gym
import numpy as np
from tqdm import tqdm
import heml_gym.envs  # noqa: F401  (registers the envs)
from heml_gym.benchmarks.common import IMAGES, RESULTS, checkout_file, codegen_target, machine_info, markdown_table, write_json
from heml_gym.envs.scripted import scripted_policy

ENV_IDS = ("heml_gym/TissueRetraction-v1", "heml_gym/OrganRetraction-v2", "heml_gym/BimanualRetraction-v0",
           "heml_gym/TissueManipulation-v0", "heml_gym/PushRetraction-v0", "heml_gym/GallbladderDissection-v0")
STREAMS = ("random", "extreme", "toggling", "out_of_range", "push_release", "scripted")
VECTOR_N = 8
ACCEPTANCE_STREAMS = ("push_release", "random", "extreme")  # part 1b
ACCEPTANCE_N = 20


class Actions:
    """An action stream for ``n`` scenes (``n = 0``: a single env's actions) of ``size``
    entries (4 per grasper: velocity x, y, z and the grasp command)."""

    def __init__(self, kind: str, n: int, rng: np.random.Generator, scene, size: int = 4):
        self.kind, self.n, self.rng, self.size = kind, n, rng, size
        self.k = np.zeros(max(n, 1), dtype=np.int64)
        self.fold = [scripted_policy(scene) for _ in range(max(n, 1))]
        self.toward_hinge = -scene.fold.direction

    def reset(self, i: int) -> None:
        self.k[i] = 0
        self.fold[i].reset()

    def one(self, i: int, obs) -> np.ndarray:
        rng, kind, k, size = self.rng, self.kind, self.k[i], self.size
        self.k[i] += 1
        graspers = size // 4
        if kind == "random":
            return rng.uniform(-1, 1, size)
        if kind == "extreme":
            return rng.choice([-1.0, 1.0], size) * rng.uniform(1, 50)
        if kind == "toggling":
            return np.concatenate([np.append(rng.uniform(-1, 1, 3), 1.0 if k % 2 == 0 else -1.0)
                                   for _ in range(graspers)])
        if kind == "out_of_range":
            return rng.uniform(-100, 100, size)
        if kind == "push_release":  # every grasper at once
            phase = k % 10
            if phase < 8:
                return np.tile([self.toward_hinge if phase else 0.0, 0.0, 0.0, 1.0], graspers)
            return np.tile([0.0, 0.0, 0.0, -1.0], graspers)
        return self.fold[i](obs)

    def __call__(self, obs) -> np.ndarray:
        if self.n == 0:
            return self.one(0, obs).astype(np.float32)
        pick = (lambda i: {key: v[i] for key, v in obs.items()}) if isinstance(obs, dict) else (lambda i: obs[i])
        return np.stack([self.one(i, pick(i)) for i in range(self.n)]).astype(np.float32)


def _all_finite(value) -> bool:
    if isinstance(value, dict):
        return all(_all_finite(v) for v in value.values())
    arr = np.asarray(value)
    if arr.dtype.kind in "biu":
        return True
    return bool(np.all(np.isfinite(arr.astype(np.float64))))


def soak(env_id: str, vector: bool, obs_mode: str, kind: str, steps: int, seed: int) -> dict:
    """``steps`` env steps of one configuration; counts of everything that went wrong."""
    rng = np.random.default_rng(seed)
    if vector:
        env = gym.make_vec(env_id, num_envs=VECTOR_N, vectorization_mode="vector_entry_point", obs_mode=obs_mode)
        space = env.unwrapped.single_observation_space
    else:
        env = gym.make(env_id, obs_mode=obs_mode)
        space = env.observation_space
    scene = env.unwrapped.scene
    n = VECTOR_N if vector else 0
    actions = Actions(kind, n, rng, scene, size=int(env.unwrapped.task.action_size))
    rec = {"env": env_id, "mode": "vector" if vector else "single", "obs_mode": obs_mode, "actions": kind,
           "codegen": codegen_target()["cpu"], "fallback_steps": 0, "refined_steps": 0,
           "env_steps": 0, "episodes": 0, "diverged": 0, "unconverged": 0, "non_finite": 0, "outside_space": 0,
           "exceptions": 0, "exception_messages": [], "slowest_step_s": 0.0, "wall_s": 0.0}
    t_start = time.perf_counter()
    try:
        obs, _ = env.reset(seed=seed)
        calls = math.ceil(steps / max(n, 1))
        for _ in range(calls):
            a = actions(obs)
            t0 = time.perf_counter()
            try:
                obs, reward, terminated, truncated, info = env.step(a)
            except Exception as exc:  # noqa: BLE001 - counted and reported, never hidden
                rec["exceptions"] += 1
                rec["exception_messages"].append(f"{type(exc).__name__}: {exc}"[:300])
                obs, _ = env.reset()
                continue
            rec["slowest_step_s"] = max(rec["slowest_step_s"], time.perf_counter() - t0)
            rec["env_steps"] += max(n, 1)
            diverged = np.atleast_1d(info["simulation_diverged"])
            converged = np.atleast_1d(info["solver_converged"])
            rec["diverged"] += int(diverged.sum())
            rec["unconverged"] += int((~converged & ~diverged).sum())  # diverged ones are counted above
            rec["fallback_steps"] += int(np.sum(info["solver_fallback"]))
            rec["refined_steps"] += int(np.sum(np.asarray(info["substep_refinement"]) > 1))
            if not (_all_finite(obs) and _all_finite(reward) and _all_finite(info)):
                rec["non_finite"] += 1
            if vector:
                batch = obs if not isinstance(obs, dict) else [{k: v[i] for k, v in obs.items()} for i in range(n)]
                rec["outside_space"] += sum(not space.contains(o) for o in batch)
                done = np.asarray(terminated) | np.asarray(truncated)
                rec["episodes"] += int(done.sum())
                for i in np.flatnonzero(done):
                    actions.reset(i)
            else:
                rec["outside_space"] += not space.contains(obs)
                if terminated or truncated:
                    rec["episodes"] += 1
                    actions.reset(0)
                    obs, _ = env.reset()
    except Exception as exc:  # noqa: BLE001
        rec["exceptions"] += 1
        rec["exception_messages"].append("".join(traceback.format_exception_only(type(exc), exc)).strip()[:300])
    env.close()
    rec["wall_s"] = time.perf_counter() - t_start
    return rec


def streams(env_id: str, kind: str, steps: int, seed: int) -> dict:
    """Part 1b: ``ACCEPTANCE_N`` seeded ``kind`` streams of ``steps`` env steps each (one
    per scene of a vector env, seeds ``seed .. seed + ACCEPTANCE_N - 1``), with the failed
    steps (diverged, unconverged, non-finite) of each stream."""
    n = ACCEPTANCE_N
    env = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point")
    rng = np.random.default_rng(seed)
    actions = Actions(kind, n, rng, env.unwrapped.scene, size=int(env.unwrapped.task.action_size))
    failed = np.zeros(n, dtype=np.int64)
    fallback = np.zeros(n, dtype=np.int64)
    refined = np.zeros(n, dtype=np.int64)
    rec = {"env": env_id, "actions": kind, "streams": n, "steps_per_stream": steps, "seeds": [seed, seed + n - 1],
           "codegen": codegen_target()["cpu"], "exceptions": 0, "exception_messages": []}
    t_start = time.perf_counter()
    try:
        obs, _ = env.reset(seed=list(range(seed, seed + n)))
        for _ in range(steps):
            obs, reward, terminated, truncated, info = env.step(actions(obs))
            bad = np.asarray(info["simulation_diverged"]) | ~np.asarray(info["solver_converged"])
            if not (_all_finite(obs) and _all_finite(reward) and _all_finite(info)):
                bad = np.ones(n, dtype=bool)
            failed += bad
            fallback += np.asarray(info["solver_fallback"])
            refined += np.asarray(info["substep_refinement"]) > 1
            for i in np.flatnonzero(np.asarray(terminated) | np.asarray(truncated)):
                actions.reset(i)
    except Exception as exc:  # noqa: BLE001 - counted and reported, never hidden
        rec["exceptions"] += 1
        rec["exception_messages"].append("".join(traceback.format_exception_only(type(exc), exc)).strip()[:300])
    env.close()
    rec.update(env_steps=int(n * steps), failed_per_stream=failed.tolist(), fallback_steps=int(fallback.sum()),
               refined_steps=int(refined.sum()), wall_s=time.perf_counter() - t_start)
    return rec


# ------------------------------------------------------------------- bad inputs
def bad_inputs() -> list[dict]:
    """Each bad input, what was tried, and the error it got (first line)."""
    import heml_gym as hg
    from heml_gym import materials as M
    from heml_gym.agents.vec_env import RetractionSb3VecEnv
    from heml_gym.envs.core import RewardWeights, TaskSettings
    from heml_gym.envs.tissue_retraction import TissueRetractionEnv, TissueRetractionVectorEnv

    tissue = "heml_gym/TissueRetraction-v1"
    box = hg.box_mesh((0.02, 0.02, 0.02), 2)

    def env_step(action):
        env = TissueRetractionEnv()
        env.reset(seed=0)
        env.step(action)

    def sb3_step(action):
        venv = RetractionSb3VecEnv(TissueRetractionVectorEnv(num_envs=2))
        venv.reset()
        venv.step(action)

    def sim(**kw):
        return hg.Simulation(hg.HemlForce(box, M.NeoHookean(E=5e3, nu=0.45)), 1000.0, **kw)

    cases = [
        ("env action NaN", lambda: env_step(np.array([np.nan, 0, 0, 0]))),
        ("env action of shape (3,)", lambda: env_step(np.zeros(3))),
        ("SB3 adapter action inf", lambda: sb3_step(np.array([[0, 0, 0, np.inf], [0, 0, 0, 0]]))),
        ("SB3 adapter flat (4N,) action", lambda: sb3_step(np.zeros(8))),
        ("settings control_dt = NaN", lambda: TaskSettings(control_dt=float("nan"))),
        ("settings control_dt = 1e4 s", lambda: TaskSettings(control_dt=1e4)),
        ("settings max_speed = 0", lambda: TaskSettings(max_speed=0.0)),
        ("settings max_steps = 0", lambda: TaskSettings(max_steps=0)),
        ("settings tear_strain = NaN", lambda: TaskSettings(tear_strain=float("nan"))),
        ("weights exposure = NaN", lambda: RewardWeights(exposure=float("nan"))),
        ("settings as a mapping with a typo", lambda: gym.make(tissue, settings={"max_stepz": 3})),
        ("physics integrator 'rk4'", lambda: gym.make(tissue, physics={"integrator": "rk4"})),
        ("physics safety 1.5", lambda: gym.make(tissue, physics={"safety": 1.5})),
        ("physics material 'Rubber'", lambda: gym.make(tissue, physics={"material": "Rubber"})),
        ("scene cells [0, 4, 1]", lambda: gym.make(tissue, scene={"tissue": {"cells": [0, 4, 1]}})),
        ("scene file missing", lambda: gym.make(tissue, scene="no/such/scene.yaml")),
        ("make_vec render_mode 'foo'", lambda: gym.make_vec(tissue, num_envs=2, vectorization_mode="vector_entry_point",
                                                             render_mode="foo")),
        ("make_vec num_envs 2.7", lambda: gym.make_vec(tissue, num_envs=2.7, vectorization_mode="vector_entry_point")),
        ("mesh with a sliver", lambda: hg.TetMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.3, 0.3, 1e-7]], [[0, 1, 2, 3]])),
        ("mesh with an unused vertex", lambda: hg.TetMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [5, 5, 5]],
                                                          [[0, 1, 2, 3]])),
        ("mesh with a duplicated tet", lambda: hg.TetMesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
                                                          [[0, 1, 2, 3], [0, 1, 2, 3]])),
        ("Simulation density -1", lambda: hg.Simulation(hg.HemlForce(box, M.NeoHookean(E=5e3, nu=0.45)), -1.0)),
        ("Simulation safety 2", lambda: sim(integrator="explicit", safety=2.0)),
        ("Simulation step dt = 0", lambda: sim().step(0.0)),
        ("Model n_worlds 0", lambda: hg.Model(box, M.NeoHookean(E=5e3, nu=0.45), n_worlds=0)),
        ("material nu = 0.5", lambda: M.NeoHookean(E=5e3, nu=0.5)),
    ]
    out = []
    for label, fn in cases:
        try:
            fn()
            out.append({"input": label, "error": None, "message": "ACCEPTED (no error)"})
        except Exception as exc:  # noqa: BLE001
            out.append({"input": label, "error": type(exc).__name__, "message": str(exc).splitlines()[0][:200]})
    out += cli_inputs()
    return out


def cli_inputs() -> list[dict]:
    """Bad input to ``heml-gym train``: the exit code, whether a traceback showed, the
    error line, and whether a run folder was left behind."""
    import subprocess
    import tempfile

    quick = checkout_file("configs/quick.yaml").read_text()
    cases = [("config: a YAML list", "- 1\n- 2\n"), ("config: empty file", ""),
             ("config: misspelt hyperparameter n_stepz",
              quick.replace("n_steps: 128", "n_stepz: 128")),
             ("config: batch_size -3", quick.replace("batch_size: 256", "batch_size: -3")),
             ("config: env.kwargs.physics.integrator rk4",
              quick.replace("obs_mode: state", "obs_mode: state\n  kwargs: {physics: {integrator: rk4}}"))]
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, text in cases + [("config: a directory", None)]:
            path = Path(tmp) / "cfg.yaml"
            if text is None:
                path = Path(tmp)
            else:
                path.write_text(text)
            run = Path(tmp) / "run"
            p = subprocess.run([sys.executable, "-m", "heml_gym.agents.cli", "train", str(path), "--run-dir", str(run)],
                               capture_output=True, text=True, timeout=300)
            err = p.stderr.strip().splitlines()
            out.append({"input": f"heml-gym train, {label}", "error": f"exit {p.returncode}",
                        "message": (err[-1] if err else "")[:200] + ("; TRACEBACK" if "Traceback" in p.stderr else "")
                        + ("; RUN FOLDER LEFT" if run.exists() else "")})
    return out


# ------------------------------------------------------------------------ report
def chart(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(ENV_IDS), figsize=(11, 3.6), sharey=False)
    for ax, env_id in zip(np.atleast_1d(axes), ENV_IDS):
        rows = [r for r in results["soak"] if r["env"] == env_id]
        labels = STREAMS
        steps = [sum(r["env_steps"] for r in rows if r["actions"] == k) for k in labels]
        bad = [sum(r["diverged"] + r["unconverged"] + r["non_finite"] + r["exceptions"] for r in rows
                   if r["actions"] == k) for k in labels]
        x = np.arange(len(labels))
        ax.bar(x, steps, color="#4c78a8", label="env steps")
        for xi, s, b in zip(x, steps, bad):
            ax.text(xi, s, f"{b} failures", ha="center", va="bottom", fontsize=8, color="#c00" if b else "#333")
        ax.set_xticks(x, labels, rotation=30, ha="right", fontsize=8)
        ax.set_title(env_id.split("/")[-1], fontsize=10)
        ax.set_ylabel("env steps")
    fig.suptitle("Reliability soak: env steps per action stream, failures (divergence, unconverged, "
                 "non-finite, exception) on top", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def merged_note(results: dict) -> str:
    """Which envs' rows were re-run with ``--merge``, and whether any row is older."""
    merged = {tuple(g["envs"]): g for g in results.get("merged", [])}
    if not merged:
        return ""
    redone = {e for envs in merged for e in envs}
    older = [e for e in results["steps_per_env"] if e not in redone]
    text = "".join(f" The rows of {', '.join(e.split('/')[-1] for e in envs)} were last re-run with `--merge` on "
                   f"{g['machine']['cpu']}, {g['machine']['date']} (after a change of that env's defaults)."
                   for envs, g in merged.items())
    if older:
        text += f" The rows of {', '.join(e.split('/')[-1] for e in older)} are from the earlier run."
    return text


def report(results: dict) -> str:
    m = results["machine"]
    soak_rows = results["soak"]
    stream_rows = results.get("streams", [])
    total = sum(r["env_steps"] for r in soak_rows) + sum(r["env_steps"] for r in stream_rows)
    targets = results.get("targets", ["host"])
    command = (f"benchmarks/reliability/reliability.py --envs {','.join(results['steps_per_env'])} "
               f"--steps {','.join(str(v) for v in results['steps_per_env'].values())}"
               + (f" --stream-steps {results['stream_steps']}" if results.get("stream_steps") else "")
               + (f" --targets {','.join(targets)}" if targets != ["host"] else ""))
    lines = [
        "# Reliability soak",
        "",
        f"Generated by `{command}` in {results['wall_s'] / 60:.0f} min on {m['cpu']} ({m['cores']} cores, "
        f"{m.get('vector_isa', '?')}), {m['date']}: {total:,} env steps in all"
        + (f", with the kernels compiled for each of {', '.join(targets)} (column codegen: the LLVM CPU name)"
           if targets != ["host"] else "") + "." + merged_note(results),
        "",
        "## Soak",
        "",
    ]
    header = ["env", "codegen", "mode", "obs", "actions", "env steps", "episodes", "diverged", "unconverged",
              "non-finite", "outside space", "exceptions", "re-taken shorter", "Newton fallback", "slowest step (ms)"]
    rows = [[r["env"].split("/")[-1], r.get("codegen", "?"), r["mode"], r["obs_mode"], r["actions"],
             f"{r['env_steps']:,}", r["episodes"], r["diverged"], r["unconverged"], r["non_finite"],
             r["outside_space"], r["exceptions"], r.get("refined_steps", "-"), r.get("fallback_steps", "-"),
             f"{1e3 * r['slowest_step_s']:.0f}"] for r in soak_rows]
    lines.append(markdown_table(header, rows))
    sums = {k: sum(r[k] for r in soak_rows) for k in ("diverged", "unconverged", "non_finite", "outside_space",
                                                       "exceptions")}
    lines.append("Totals: " + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in sums.items())
                 + f"; re-taken in shorter sub-steps {sum(r.get('refined_steps', 0) for r in soak_rows):,}, "
                 f"by the Newton fallback {sum(r.get('fallback_steps', 0) for r in soak_rows):,}. (The "
                 "slowest step of the first configurations includes compiling the Numba kernels they first "
                 "use: seconds, once per process.)\n")
    for r in soak_rows:
        for msg in r["exception_messages"][:3]:
            lines.append(f"- exception in {r['env']} {r['mode']} {r['actions']}: `{msg}`")
    if stream_rows:
        lines += ["", "## Seeded streams", "",
                  f"Per env and action pattern, {stream_rows[0]['streams']} streams (one per scene of a vector env, "
                  f"each its own seed) of {stream_rows[0]['steps_per_stream']:,} env steps; a step fails when it "
                  "diverged, stayed unconverged or put a non-finite value anywhere.", ""]
        header = ["env", "codegen", "actions", "streams", "env steps", "streams with a failed step", "failed steps",
                  "re-taken shorter", "Newton fallback", "exceptions", "wall (min)"]
        lines.append(markdown_table(header, [
            [r["env"].split("/")[-1], r["codegen"], r["actions"], f"{r['streams']} (seeds {r['seeds'][0]}-"
             f"{r['seeds'][1]})", f"{r['env_steps']:,}", sum(1 for f in r["failed_per_stream"] if f),
             sum(r["failed_per_stream"]), r["refined_steps"], r["fallback_steps"], r["exceptions"],
             f"{r['wall_s'] / 60:.1f}"] for r in stream_rows]))
        for r in stream_rows:
            for msg in r["exception_messages"][:3]:
                lines.append(f"- exception in {r['env']} {r['actions']} streams: `{msg}`")
    if results["bad_inputs"]:
        where = results.get("bad_inputs_machine")
        when = (f" (re-measured on their own: {where['cpu']}, {where['date']}, "
                "`python -m heml_gym.benchmarks.reliability.reliability --bad-inputs-only`)") if where else ""
        lines += ["", "## Bad inputs", "", f"Each input below was tried; the error it got is its first line{when}.", ""]
        lines.append(markdown_table(["input", "error", "message"],
                                    [[b["input"], b["error"] or "**none**", b["message"].replace("|", "/")]
                                     for b in results["bad_inputs"]]))
    lines.append("![reliability soak](../img/reliability.png)")
    return "\n".join(lines) + "\n"


def run_target(target: str, budget: dict, stream_steps: int) -> dict:
    """The soak (and the streams) of every env in ``budget`` in this process: its rows."""
    env_ids = list(budget)
    configs = [(e, v, o, k) for e in env_ids for v in (False, True) for o in ("state", "pointcloud") for k in STREAMS]
    per_env = len(configs) // len(env_ids)
    soak_rows = []
    for i, (env_id, vector, obs_mode, kind) in enumerate(tqdm(configs, desc=f"soak ({target})", unit="config")):
        soak_rows.append(soak(env_id, vector, obs_mode, kind, max(1, budget[env_id] // per_env), seed=1000 + i))
    stream_rows = []
    if stream_steps:
        jobs = [(e, k) for e in env_ids for k in ACCEPTANCE_STREAMS]
        for j, (env_id, kind) in enumerate(tqdm(jobs, desc=f"streams ({target})", unit="kind")):
            stream_rows.append(streams(env_id, kind, stream_steps, seed=5000 + 100 * j))
    return {"soak": soak_rows, "streams": stream_rows}


def run_targets(targets: list[str], argv: list[str]) -> dict:
    """Each target in a child process (concurrently, one Numba thread each); their rows."""
    import json
    import os
    import subprocess
    import tempfile

    children = []
    with tempfile.TemporaryDirectory() as tmp:
        for target in targets:
            env = {**os.environ, "NUMBA_NUM_THREADS": "1"}
            if target != "host":
                env.update(NUMBA_CPU_NAME=target, NUMBA_CPU_FEATURES="",
                           NUMBA_CACHE_DIR=str(Path(tempfile.gettempdir()) / f"heml-gym-numba-{target}"))
            part = Path(tmp) / f"{target}.json"
            cmd = [sys.executable, __file__, *argv, "--part", str(part)]
            children.append((target, part, subprocess.Popen(cmd, env=env)))
        rows = {"soak": [], "streams": []}
        for target, part, child in children:
            if child.wait() != 0:
                raise SystemExit(f"reliability: the {target} run failed (exit {child.returncode})")
            got = json.loads(part.read_text())
            rows["soak"] += got["soak"]
            rows["streams"] += got["streams"]
    return rows


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", default="2000", help="env steps per environment, split over its "
                    "configurations: one number, or one per environment (comma-separated); default 2000, a "
                    "smoke run")
    ap.add_argument("--stream-steps", type=int, default=0, help="part 1b: env steps per stream of the 20 seeded "
                    "push_release, random and extreme streams per env (default 0: skipped)")
    ap.add_argument("--targets", default="host", help="comma-separated Numba codegen targets to repeat the run "
                    "under (host, haswell, znver3, x86-64, ...), each in its own process; default host")
    ap.add_argument("--envs", default=",".join(ENV_IDS), help="comma-separated environment ids")
    ap.add_argument("--out", default=str(RESULTS), help="folder for reliability.json / .md")
    ap.add_argument("--from-json", action="store_true", help="rewrite the report and chart from the stored run")
    ap.add_argument("--no-bad-inputs", action="store_true", help="the soak only (scripts/cpu_matrix.sh)")
    ap.add_argument("--merge", action="store_true", help="replace only these envs' soak rows in the stored "
                    "reliability.json (the other envs' rows are kept, with the machine they ran on)")
    ap.add_argument("--bad-inputs-only", action="store_true", help="re-measure part 2 only (every bad input's "
                    "error) into the stored reliability.json, keeping its soak and stream rows")
    ap.add_argument("--part", help=argparse.SUPPRESS)  # internal: one target's rows to this JSON
    args = ap.parse_args(argv)
    if (args.merge or args.bad_inputs_only) and not (Path(args.out) / "reliability.json").is_file():
        ap.error(f"--{'merge' if args.merge else 'bad-inputs-only'}: there is no stored {Path(args.out) / 'reliability.json'} to update")
    if args.bad_inputs_only:
        import json

        stored = json.loads((Path(args.out) / "reliability.json").read_text())
        stored["bad_inputs"] = bad_inputs()
        stored["bad_inputs_machine"] = machine_info()  # part 2 re-measured on its own: when and where
        write_json("reliability.json", stored, folder=Path(args.out))
        (Path(args.out) / "reliability.md").write_text(report(stored))
        accepted = [b["input"] for b in stored["bad_inputs"] if b["error"] is None or "TRACEBACK" in b["message"]
                    or "LEFT" in b["message"]]
        print(f"{len(stored['bad_inputs'])} bad inputs; {len(accepted)} not handled cleanly {accepted}")
        return 1 if accepted else 0
    if args.from_json:
        import json

        results = json.loads((Path(args.out) / "reliability.json").read_text())
        (Path(args.out) / "reliability.md").write_text(report(results))
        chart(results, IMAGES / "reliability.png")
        return 0
    env_ids = [e for e in args.envs.split(",") if e]
    try:
        steps = [int(float(v)) for v in args.steps.split(",")]
    except ValueError:
        ap.error(f"--steps must be integers, got {args.steps!r}")
    if len(steps) == 1:
        steps = steps * len(env_ids)
    if len(steps) != len(env_ids) or min(steps) < 1:
        ap.error(f"--steps: give one number >= 1, or one per environment ({len(env_ids)})")
    if args.stream_steps < 0:
        ap.error(f"--stream-steps must be >= 0, got {args.stream_steps}")
    targets = [t for t in args.targets.split(",") if t]
    if not targets:
        ap.error("--targets: name at least one target (host, haswell, ...)")
    budget = dict(zip(env_ids, steps))
    if args.part:
        import json

        rows = run_target(codegen_target()["cpu"], budget, args.stream_steps)
        Path(args.part).write_text(json.dumps(rows))
        return 0
    t0 = time.perf_counter()
    if targets == ["host"]:
        rows = run_target("host", budget, args.stream_steps)
    else:
        child_argv = [a for a in argv if not a.startswith("--targets")]
        if "--targets" in argv:
            k = argv.index("--targets")
            child_argv = argv[:k] + argv[k + 2:]
        rows = run_targets(targets, child_argv)
    soak_rows = rows["soak"]
    results = {"machine": machine_info(), "steps_per_env": budget, "targets": targets,
               "stream_steps": args.stream_steps, "soak": soak_rows, "streams": rows["streams"]}
    results["bad_inputs"] = [] if args.no_bad_inputs else bad_inputs()
    results["wall_s"] = time.perf_counter() - t0
    if args.merge:
        import json

        stored = json.loads((Path(args.out) / "reliability.json").read_text())
        kept = [r for r in stored["soak"] if r["env"] not in budget]
        earlier = {e: n for e, n in stored["steps_per_env"].items() if e not in budget}
        for r in kept:
            r.setdefault("machine", stored["machine"])
        for r in soak_rows:
            r["machine"] = results["machine"]
        soak_rows = kept + soak_rows
        results = {**results, "soak": soak_rows, "steps_per_env": {**earlier, **budget},
                   "streams": [r for r in stored.get("streams", []) if r["env"] not in budget] + rows["streams"],
                   "merged": stored.get("merged", []) + [{"envs": sorted(budget), "machine": results["machine"],
                                                          "wall_s": results["wall_s"]}],
                   "wall_s": stored["wall_s"] + results["wall_s"],
                   # (--no-bad-inputs: the stored part 2 stays)
                   "bad_inputs": results["bad_inputs"] or stored.get("bad_inputs", [])}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if out == RESULTS:
        write_json("reliability.json", results)
        IMAGES.mkdir(parents=True, exist_ok=True)
        chart(results, IMAGES / "reliability.png")
    else:
        write_json("reliability.json", results, folder=out)
    (out / "reliability.md").write_text(report(results))
    failures = sum(r["diverged"] + r["unconverged"] + r["non_finite"] + r["outside_space"] + r["exceptions"]
                   for r in soak_rows)
    failures += sum(sum(r["failed_per_stream"]) + r["exceptions"] for r in results["streams"])
    accepted = [b["input"] for b in results["bad_inputs"] if b["error"] is None or "TRACEBACK" in b["message"]
                or "LEFT" in b["message"]]
    total = sum(r["env_steps"] for r in soak_rows) + sum(r["env_steps"] for r in results["streams"])
    print(f"{total:,} env steps: {failures} failures; {len(accepted)} bad inputs not handled cleanly {accepted}")
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
