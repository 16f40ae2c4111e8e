"""Seed and hyperparameter sweeps on Ray Tune, on this machine or any Ray cluster.

``heml-gym sweep CONFIG --seeds 0,1,2 [--set key=value ...] [--grid key=v1,v2 ...]
[--address ADDRESS] [--out DIR] [--cpus-per-trial 1]``: every (seed, grid point) is a Ray
Tune trial that runs the same training as ``heml-gym train`` (:func:`heml_gym.agents.train.train`)
into its own run folder ``OUT/<config>-<grid point>-seed<seed>/``. Every trial's config is
built and validated before Ray starts. A failed trial is reported with its error and the
others go on; a trial whose run folder holds ``result.json`` is finished and is not run
again, so interrupting and re-running a sweep resumes it. The sweep writes
``OUT/summary.json`` (per trial: overrides, seed, node, env steps, wall time, final
success rate and its interval, or the error) and ``OUT/summary.png`` (success vs env
steps, every seed and the IQM across seeds with its 95 % bootstrap interval).

Ray is an optional dependency: ``pip install -e ".[ray]"``. Without ``--address`` a local
Ray instance is started (and stopped) for the sweep; with one (``auto``, ``HOST:PORT``),
the trials go to that cluster, whose nodes must all see ``OUT`` (a shared file system)
and have heml-gym installed (docs/studies/scale_out.md).
"""

from __future__ import annotations

import copy
import itertools
import json
import math
import socket
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from .config import ConfigError, RunConfig, config_from_dict
from .stats import iqm, iqm_interval

__all__ = ["Trial", "plan_sweep", "run_sweep", "parse_assignments", "parse_grid"]

RESULT_FILE = "result.json"


def _parse_value(text: str):
    """A command-line value as YAML reads it (numbers, booleans, lists, strings)."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def _set_dotted(data: dict, key: str, value) -> None:
    parts = key.split(".")
    if not all(parts):
        raise ConfigError(f"--set / --grid key {key!r} is not a dotted config key (e.g. algorithm.total_timesteps)")
    node = data
    for p in parts[:-1]:
        if not isinstance(node.setdefault(p, {}), dict):
            raise ConfigError(f"--set / --grid key {key!r}: {p!r} is not a section")
        node = node[p]
    node[parts[-1]] = value


def parse_assignments(items) -> dict:
    """``["a.b=1", "c=x"]`` -> ``{"a.b": 1, "c": "x"}`` (values read as YAML)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        key, value = item.split("=", 1)
        out[key.strip()] = _parse_value(value.strip())
    return out


def parse_grid(items) -> dict:
    """``["a.b=1,2,3"]`` -> ``{"a.b": [1, 2, 3]}``."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"--grid {item!r}: expected KEY=V1,V2,...")
        key, values = item.split("=", 1)
        parsed = [_parse_value(v.strip()) for v in values.split(",") if v.strip()]
        if not parsed:
            raise ConfigError(f"--grid {item!r}: no values")
        out[key.strip()] = parsed
    return out


@dataclass
class Trial:
    """One training run of a sweep."""

    name: str
    seed: int
    overrides: dict  # dotted key -> value (the --set values and this grid point)
    grid_point: dict  # dotted key -> value (this grid point only)
    config: RunConfig
    run_dir: Path

    @property
    def finished(self) -> bool:
        return (self.run_dir / RESULT_FILE).is_file()

    def as_param(self) -> dict:
        return {"name": self.name, "seed": self.seed, "overrides": self.overrides, "grid_point": self.grid_point,
                "config": self.config.to_dict(), "run_dir": str(self.run_dir)}


def _label(value) -> str:
    text = json.dumps(value) if not isinstance(value, str) else value
    return "".join(c if c.isalnum() or c in ".-" else "_" for c in text)


def plan_sweep(config_path: str | Path, seeds, sets: dict | None = None, grid: dict | None = None,
               out: str | Path | None = None) -> list[Trial]:
    """The trials of a sweep, each config validated (:class:`ConfigError` naming the trial
    and the key) before anything runs."""
    path = Path(config_path)
    from .config import load_config

    base = load_config(path).to_dict()  # validates the file itself
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ConfigError("--seeds: give at least one seed")
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"--seeds: repeated seeds in {seeds}")
    grid = grid or {}
    # absolute: Ray Tune runs each trial in a working folder of its own
    out = (Path(out) if out is not None else Path("runs") / f"sweep-{base['name']}").resolve()
    keys = list(grid)
    trials = []
    for values in itertools.product(*(grid[k] for k in keys)):
        point = dict(zip(keys, values))
        for seed in seeds:
            data = copy.deepcopy(base)
            for key, value in {**(sets or {}), **point}.items():
                _set_dotted(data, key, value)
            data["seed"] = seed
            tag = "-".join(f"{k.split('.')[-1]}{_label(v)}" for k, v in point.items())
            name = f"{base['name']}{'-' + tag if tag else ''}-seed{seed}"
            try:
                cfg = config_from_dict(data)
            except ConfigError as exc:
                raise ConfigError(f"trial {name}: {exc}") from None
            trials.append(Trial(name, seed, {**(sets or {}), **point}, point, cfg, out / name))
    return trials


def _trial_main(param: dict) -> None:
    """Ray Tune's trainable: one training run, its result written beside it."""
    import numba
    import ray
    from ray import tune

    import heml_gym.envs  # noqa: F401  (registers the environments in this worker)

    from .train import train

    trial = param["trial"]
    cpus = max(1, int(param.get("cpus", 1)))
    numba.set_num_threads(min(cpus, numba.config.NUMBA_NUM_THREADS))
    cfg = config_from_dict(trial["config"])
    started = time.time()
    result = train(cfg, run_dir=trial["run_dir"], progress_bar=False)
    final = result["final_evaluation"]
    record = {
        "name": trial["name"], "seed": trial["seed"], "overrides": trial["overrides"],
        "grid_point": trial["grid_point"], "run_dir": trial["run_dir"], "status": "finished",
        "node_id": ray.get_runtime_context().get_node_id(), "hostname": socket.gethostname(),
        "env_steps": result["timesteps"], "wall_s": time.time() - started,
        "success_rate": final["success_rate"], "success_ci95": final["success_ci95"],
        "stopped_early": bool(result.get("stopped_early")),
    }
    Path(trial["run_dir"], RESULT_FILE).write_text(json.dumps(record, indent=1))
    tune.report({"success_rate": final["success_rate"], "env_steps": result["timesteps"]})


def run_sweep(trials: list[Trial], out: str | Path, address: str | None = None, cpus_per_trial: float = 1,
              verbose: bool = True) -> dict:
    """Run the unfinished ``trials`` on Ray Tune and write ``summary.json`` / ``summary.png``
    into ``out``; returns the summary."""
    try:
        import ray
        from ray import tune
    except ImportError:
        raise ImportError("sweeps run on Ray: pip install -e '.[ray]' (or pip install 'ray[tune]')") from None
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    pending = [t for t in trials if not t.finished]
    if verbose:
        print(f"sweep: {len(trials)} trials, {len(trials) - len(pending)} already finished, {len(pending)} to run",
              flush=True)
    errors: dict[str, str] = {}
    if pending:
        started_ray = not ray.is_initialized()
        if started_ray:
            ray.init(address=address, include_dashboard=False, log_to_driver=verbose,
                     runtime_env={"env_vars": {"OMP_WAIT_POLICY": "PASSIVE"}})
        try:
            trainable = tune.with_resources(_trial_main, {"cpu": cpus_per_trial})
            tuner = tune.Tuner(
                trainable,
                param_space={"trial": tune.grid_search([t.as_param() for t in pending]), "cpus": cpus_per_trial},
                tune_config=tune.TuneConfig(num_samples=1),
                run_config=tune.RunConfig(name="tune", storage_path=str(out.resolve()), verbose=1 if verbose else 0,
                                          failure_config=tune.FailureConfig(max_failures=0)),
            )
            grid = tuner.fit()
            for r in grid:
                if r.error is not None:
                    name = r.config["trial"]["name"]
                    errors[name] = f"{type(r.error).__name__}: {r.error}".strip().splitlines()[-1][:500]
        finally:
            if started_ray:
                ray.shutdown()
    summary = summarise(trials, errors)
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    chart(trials, summary, out / "summary.png")
    return summary


def summarise(trials: list[Trial], errors: dict | None = None) -> dict:
    """Per trial its result (or error), and per grid point the IQM of the final success
    rates across seeds with a 95 % bootstrap interval."""
    errors = errors or {}
    rows = []
    for t in trials:
        path = t.run_dir / RESULT_FILE
        if path.is_file():
            rows.append(json.loads(path.read_text()))
        else:
            rows.append({"name": t.name, "seed": t.seed, "overrides": t.overrides, "grid_point": t.grid_point,
                         "run_dir": str(t.run_dir), "status": "failed" if t.name in errors else "missing",
                         "error": errors.get(t.name, "no result (interrupted?)")})
    points = []
    for key in sorted({json.dumps(r["grid_point"], sort_keys=True) for r in rows}):
        done = [r for r in rows if json.dumps(r["grid_point"], sort_keys=True) == key and r["status"] == "finished"]
        entry = {"grid_point": json.loads(key), "seeds": [r["seed"] for r in done],
                 "success_rates": [r["success_rate"] for r in done]}
        if done:
            entry["iqm"] = iqm(entry["success_rates"])
            entry["iqm_ci95"] = list(iqm_interval(entry["success_rates"]))
        points.append(entry)
    return {"trials": rows, "grid_points": points,
            "finished": sum(r["status"] == "finished" for r in rows), "failed": sum(r["status"] == "failed" for r in rows)}


def chart(trials: list[Trial], summary: dict, path: Path) -> None:
    """Success rate vs env steps (top row: every seed's evaluations, and the IQM across
    seeds with its 95 % bootstrap interval) and vs wall time (bottom row: every seed),
    one column per grid point."""
    try:
        import matplotlib
    except ImportError:
        return
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = summary["grid_points"]
    cols = max(1, len(points))
    fig, axes = plt.subplots(2, cols, figsize=(5 * cols, 6.4), squeeze=False)
    for ax, wall_ax, point in zip(axes[0], axes[1], points):
        key = json.dumps(point["grid_point"], sort_keys=True)
        curves = {}
        for t in trials:
            if json.dumps(t.grid_point, sort_keys=True) != key:
                continue
            history = t.run_dir / "evaluations.json"
            if history.is_file():
                h = json.loads(history.read_text())
                steps = [e["timesteps"] for e in h]
                rate = [e["success_rate"] for e in h]
                curves[t.seed] = (steps, rate)
                color = f"C{(len(curves) - 1) % 10}"
                ax.plot(steps, rate, color=color, alpha=0.7, lw=1, marker=".", label=f"seed {t.seed}")
                if all("wall_s" in e for e in h):
                    wall_ax.plot([e["wall_s"] / 60 for e in h], rate, color=color, alpha=0.7, lw=1, marker=".",
                                 label=f"seed {t.seed}")
        if curves:
            grid_steps = sorted({s for steps, _ in curves.values() for s in steps})
            values = np.array([[np.interp(s, st, r, right=math.nan) for s in grid_steps] for st, r in curves.values()])
            centre, lo, hi = [], [], []
            for col in values.T:
                col = col[np.isfinite(col)]
                centre.append(iqm(col))
                a, b = iqm_interval(col, reps=500)
                lo.append(a)
                hi.append(b)
            ax.plot(grid_steps, centre, color="black", lw=2, label="IQM across seeds")
            ax.fill_between(grid_steps, lo, hi, color="black", alpha=0.12, label="95 % bootstrap interval")
        ax.set_xlabel("env steps")
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v / 1000:g} k"))
        wall_ax.set_xlabel("wall time (min, one CPU per trial)")
        ax.set_title(", ".join(f"{k}={v}" for k, v in point["grid_point"].items()) or "all seeds", fontsize=9)
        for a in (ax, wall_ax):
            a.set_ylim(-0.02, 1.02)
            a.set_ylabel("evaluated success rate")
            a.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

