"""Learning results across seeds: PPO, SAC (with HER on the goal task) and behaviour cloning on every task.

Collects the seed sweeps of the shipped configs (each run by ``benchmarks/learning/quick_sweep.py``,
i.e. ``heml-gym sweep CONFIG --seeds ...``, one CPU per trial; ``SWEEPS`` below names
them and the command that made each) and writes, per env and algorithm: every seed's
evaluation history (success rate vs env steps and vs wall time), its final success on 20
fresh seeded episodes, its first evaluation at >= 90 %, and across seeds the
interquartile mean (IQM) of the final success with a 95 % stratified-bootstrap interval
(Agarwal et al. 2021, `heml_gym.agents.stats`), and the IQM of the success curves with
their intervals. The scripted baseline's success on the same task comes from
docs/benchmarks/task_difficulty.json (the retraction tasks' difficulty levels), else from
docs/benchmarks/scripted_experts.json. A sweep that has not been run is listed as such.

Writes docs/benchmarks/agent_results.{json,md} and docs/img/agent_results.png.

    python benchmarks/learning/agent_results.py
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from heml_gym.benchmarks.common import parse_arguments, IMAGES, RESULTS, machine_info, markdown_table, write_json

#: (results name of the sweep, config, algorithm, env, difficulty, seeds the command runs)
SWEEPS = [
    ("quick_sweep", "configs/quick.yaml", "PPO", "heml_gym/TissueRetraction-v1", 1, "0,1,2,3,4,5,6"),
    ("organ_ppo_sweep", "configs/organ_ppo.yaml", "PPO", "heml_gym/OrganRetraction-v2", 1, "0,1,2,3,4"),
    ("tissue_sac_sweep", "configs/tissue_sac.yaml", "SAC", "heml_gym/TissueRetraction-v1", 1, "0,1,2"),
    ("organ_sac_sweep", "configs/organ_sac.yaml", "SAC", "heml_gym/OrganRetraction-v2", 1, "0,1,2"),
    ("tissue_ppo_difficulty2", "configs/tissue_ppo_difficulty2.yaml", "PPO", "heml_gym/TissueRetraction-v1", 2,
     "0,1,2,3,4"),
    ("organ_ppo_difficulty2", "configs/organ_ppo_difficulty2.yaml", "PPO", "heml_gym/OrganRetraction-v2", 2,
     "0,1,2,3,4"),
    ("tissue_bc_sweep", "configs/tissue_bc.yaml", "BC", "heml_gym/TissueRetraction-v1", 1, "0,1,2,3,4"),
    ("organ_bc_sweep", "configs/organ_bc.yaml", "BC", "heml_gym/OrganRetraction-v2", 1, "0,1,2,3,4"),
    ("bimanual_bc_sweep", "configs/bimanual_bc.yaml", "BC", "heml_gym/BimanualRetraction-v0", 1, "0,1,2,3,4"),
    ("bimanual_ppo", "configs/bimanual_ppo.yaml", "PPO", "heml_gym/BimanualRetraction-v0", 1, "0,1,2,3,4"),
    ("bimanual_sac", "configs/bimanual_sac.yaml", "SAC", "heml_gym/BimanualRetraction-v0", 1, "0,1,2,3,4"),
    ("manipulation_bc_sweep", "configs/manipulation_bc.yaml", "BC", "heml_gym/TissueManipulation-v0", 1,
     "0,1,2,3,4"),
    ("manipulation_sac_her", "configs/manipulation_sac_her.yaml", "SAC+HER", "heml_gym/TissueManipulation-v0", 1,
     "0,1,2,3,4"),
    ("push_bc_sweep", "configs/push_bc.yaml", "BC", "heml_gym/PushRetraction-v0", 1, "0,1,2,3,4"),
    ("push_ppo_sweep", "configs/push_ppo.yaml", "PPO", "heml_gym/PushRetraction-v0", 1, "0,1,2,3,4"),
    ("dissection_bc_sweep", "configs/dissection_bc.yaml", "BC", "heml_gym/GallbladderDissection-v0", 1, "0,1,2,3,4"),
    ("dissection_ppo_sweep", "configs/dissection_ppo.yaml", "PPO", "heml_gym/GallbladderDissection-v0", 1, "0,1,2,3,4"),
]
#: algorithms that learn from demonstrations, without env steps (no learning curve: a line at their IQM)
OFFLINE = ("BC",)
#: line colours of the chart by (algorithm, difficulty)
COLOURS = {("PPO", 1): "tab:blue", ("SAC", 1): "tab:orange", ("SAC+HER", 1): "tab:red", ("PPO", 2): "tab:purple", ("SAC", 2): "tab:brown",
           ("BC", 1): "tab:green"}
BAR_SUCCESS = 0.9


def command(name: str, config: str, seeds: str) -> str:
    if name.endswith("_bc_sweep"):
        return f"python -m heml_gym.benchmarks.learning.bc --envs {name.split('_')[0]} --seeds {seeds}"
    if name == "quick_sweep":
        return f"python benchmarks/learning/quick_sweep.py --seeds {seeds}"
    return f"python benchmarks/learning/quick_sweep.py --config {config} --name {name} --seeds {seeds}"


def curve_iqm(seeds: list[dict], key: str, grid: np.ndarray) -> dict:
    """IQM across seeds of the success curves, each read at ``grid`` (linear between
    evaluations, not beyond a seed's last one), with 95 % bootstrap intervals."""
    from heml_gym.agents.stats import iqm, iqm_interval

    rows = []
    for s in seeds:
        xs = np.array([e[key] for e in s["evaluations"]], dtype=float)
        ys = np.array([e["success_rate"] for e in s["evaluations"]], dtype=float)
        rows.append(np.interp(grid, xs, ys, right=math.nan))
    values = np.array(rows)
    centre, lo, hi = [], [], []
    for col in values.T:
        col = col[np.isfinite(col)]
        if len(col) < 2:
            centre.append(math.nan)
            lo.append(math.nan)
            hi.append(math.nan)
            continue
        centre.append(iqm(col))
        a, b = iqm_interval(col, reps=1000)
        lo.append(a)
        hi.append(b)
    return {"x": grid.tolist(), "iqm": centre, "low": lo, "high": hi}


def collect() -> dict:
    from heml_gym.agents.stats import iqm, iqm_interval

    scripted = {}
    difficulty = RESULTS / "task_difficulty.json"
    if difficulty.is_file():
        for r in json.loads(difficulty.read_text())["rows"]:
            if r["difficulty"] == 1 and r.get("variant") is None:  # the default task
                scripted[r["env"]] = {"success_rate": r["success_rate"], "episodes": r["episodes"]}
    experts = RESULTS / "scripted_experts.json"  # every live task's expert, on held-out seeds
    if experts.is_file():
        for r in json.loads(experts.read_text())["results"]:
            scripted.setdefault(r["env"], {"success_rate": r["success_rate"], "episodes": r["episodes"]})
    groups, missing = [], []
    for name, config, algo, env, difficulty, seeds in SWEEPS:
        path = RESULTS / f"{name}.json"
        if not path.is_file():
            missing.append({"name": name, "config": config, "algorithm": algo, "env": env, "difficulty": difficulty,
                            "command": command(name, config, seeds)})
            continue
        sweep = json.loads(path.read_text())
        done = [s for s in sweep["seeds"] if s["status"] == "finished"]
        finals = [s["success_rate"] for s in done]
        group = {"name": name, "config": config, "algorithm": algo, "env": env, "difficulty": difficulty,
                 "machine": sweep["machine"],
                 "trials_at_once": sweep.get("trials_at_once"), "command": sweep.get("command"),
                 "seeds": done, "failed_seeds": [s for s in sweep["seeds"] if s["status"] != "finished"],
                 "seeds_at_90_percent": sum(f >= BAR_SUCCESS for f in finals)}
        if "demos" in sweep:
            group["demos"] = sweep["demos"]
        if finals:
            group["iqm"] = iqm(finals)
            group["iqm_ci95"] = list(iqm_interval(finals))
        if finals and algo not in OFFLINE:
            steps = np.unique([e["env_steps"] for s in done for e in s["evaluations"]])
            group["curve_steps"] = curve_iqm(done, "env_steps", steps.astype(float))
            if all("wall_s" in e for s in done for e in s["evaluations"]):
                top = max(e["wall_s"] for s in done for e in s["evaluations"])
                group["curve_wall"] = curve_iqm(done, "wall_s", np.linspace(0.0, top, 40))
        groups.append(group)
    return {"machine": machine_info(), "groups": groups, "missing": missing, "scripted": scripted}


def chart(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    order = [env for *_, env, _, _ in SWEEPS]  # the tasks in the order SWEEPS names them
    envs = sorted({g["env"] for g in results["groups"]}, key=order.index)
    if not envs:
        return
    fig, axes = plt.subplots(2, len(envs), figsize=(6.4 * len(envs), 8.4), squeeze=False)
    for col, env in enumerate(envs):
        for row, (key, curve, label, scale) in enumerate([("env_steps", "curve_steps", "env steps (thousands)", 1e3),
                                                         ("wall_s", "curve_wall", "wall time (min, one CPU per "
                                                          "trial)", 60.0)]):
            ax = axes[row, col]
            for g in [g for g in results["groups"] if g["env"] == env]:
                c = COLOURS.get((g["algorithm"], g["difficulty"]), "tab:green")
                for s in g["seeds"]:
                    if all(key in e for e in s["evaluations"]):
                        ax.plot([e[key] / scale for e in s["evaluations"]],
                                [e["success_rate"] for e in s["evaluations"]], color=c, alpha=0.3, lw=0.9)
                if g["algorithm"] in OFFLINE and "iqm" in g:
                    demos = g.get("demos", {})
                    ax.axhline(g["iqm"], color=c, lw=2.4, ls="-.",
                               label=f"{g['algorithm']} from {demos.get('episodes', '?')} {demos.get('policy', '')} "
                                     f"demos (no env steps): IQM of {len(g['seeds'])} seeds")
                if curve in g:
                    x = np.array(g[curve]["x"]) / scale
                    ax.plot(x, g[curve]["iqm"], color=c, lw=2.4,
                            label=f"{g['algorithm']}, difficulty {g['difficulty']}: IQM of {len(g['seeds'])} "
                                  "seeds (thin: each seed)")
                    ax.fill_between(x, g[curve]["low"], g[curve]["high"], color=c, alpha=0.15)
            scripted = results["scripted"].get(env)
            if scripted:
                ax.axhline(scripted["success_rate"], color="k", ls=":", lw=1.2,
                           label=f"scripted baseline, difficulty 1 ({scripted['success_rate']:.0%})")
            ax.axhline(BAR_SUCCESS, color="tab:red", ls="--", lw=1, label="90 %")
            ax.set_ylim(-0.03, 1.03)
            if not any(curve in g for g in results["groups"] if g["env"] == env):  # demonstrations only
                ax.set_xticks([])
            ax.set_xlabel(label)
            ax.set_ylabel("evaluated success rate (20 episodes)")
            ax.set_title(f"{env.split('/')[-1]}: success vs {label.split(' (')[0]}", fontsize=10)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7.5, loc="lower right")
    fig.suptitle("Learning across seeds: IQM with 95 % stratified-bootstrap band, every seed drawn", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown(results: dict) -> str:
    md = ("Written by `benchmarks/learning/agent_results.py` from the seed sweeps of the shipped configs (each "
          "`heml-gym sweep CONFIG --seeds ...` on Ray Tune, one CPU per trial). Difficulty 1 is each env's "
          "default task (expose the target and hold it exposed, below damage strain, for 2 s); difficulty 2 "
          "(not a default) draws the tissue's stiffness from a wider range and puts the target deeper under "
          "the tissue (the env docstrings' tables). Final "
          "success: 20 fresh seeded episodes, deterministic policy. IQM: interquartile mean across seeds with "
          "a 95 % stratified-bootstrap interval (Agarwal et al. 2021).\n\n")
    rows = []
    for g in results["groups"]:
        firsts = [s["first_eval_at_90_percent"] for s in g["seeds"]]
        reached = [f for f in firsts if f is not None]
        walls = [s["wall_s"] / 60 for s in g["seeds"]]
        rows.append([g["env"].split("/")[-1], g["algorithm"], g["difficulty"], f"`{g['config']}`", len(g["seeds"]),
                     f"{g['seeds_at_90_percent']} of {len(g['seeds'])}",
                     " / ".join(f"{s['success_rate']:.0%}" for s in g["seeds"]),
                     f"{g['iqm']:.0%} ({g['iqm_ci95'][0]:.0%}-{g['iqm_ci95'][1]:.0%})" if "iqm" in g else "-",
                     "- (offline)" if g["algorithm"] in OFFLINE else
                     (f"{min(reached) // 1000}-{max(reached) // 1000} k" if reached else "never")
                     + (f" ({len(firsts) - len(reached)} never)" if reached and len(reached) < len(firsts) else ""),
                     f"0 ({g['demos']['transitions']:,} demo steps)" if g["algorithm"] in OFFLINE and "demos" in g
                     else f"{max(s['env_steps'] for s in g['seeds']) // 1000} k",
                     f"{min(walls):.1f}-{max(walls):.1f}",
                     f"{g['machine']['cpu']}, {g['machine']['date']}, {g['trials_at_once']} at a time"])
    if rows:
        md += markdown_table(["env", "algorithm", "difficulty", "config", "seeds", ">= 90 %", "final success per seed",
                              "IQM (95 % interval)", "first eval >= 90 % at", "budget (env steps)",
                              "wall min per seed", "measured on"], rows)
    for env, s in results["scripted"].items():  # (difficulty 1: the default task)
        md += f"\nScripted baseline on {env.split('/')[-1]} (difficulty 1): {s['success_rate']:.0%} of {s['episodes']} episodes."
    for m in results["missing"]:
        md += (f"\n\nNot run yet: {m['algorithm']} on {m['env'].split('/')[-1]} at difficulty {m['difficulty']} "
               f"(`{m['config']}`): "
               f"`{m['command']}`.")
    md += "\n\nPer seed: " + ", ".join(f"[{g['name']}.md]({g['name']}.md)" for g in results["groups"]) + "."
    md += "\n\n![success vs env steps and wall time, every seed and the IQM](../img/agent_results.png)\n"
    return md


RENAMED = ("runs trained under the ids -v0 (2026-11-25), the tasks registered as -v1 since 2026-11-26; "
           "OrganRetraction: measured as -v1, renamed -v2 on 2026-11-26: v2 changed only the task camera's up "
           "direction (its images were turned 90 degrees), not the state observations, dynamics or rewards")


def main() -> int:
    results = collect()
    # the runs on record were trained before the tasks' ids became -v1 / -v2 (2026-11-26), on the same state tasks
    results = {"renamed": RENAMED, **results}
    write_json("agent_results.json", results)
    text = markdown(results)
    (RESULTS / "agent_results.md").write_text(text)
    IMAGES.mkdir(parents=True, exist_ok=True)
    chart(results, IMAGES / "agent_results.png")
    print(text)
    return 0


if __name__ == "__main__":
    parse_arguments(__doc__)
    raise SystemExit(main())
