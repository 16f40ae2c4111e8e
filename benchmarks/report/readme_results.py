"""The README's generated parts, and the list of every headline result, from the stored results.

Writes, in docs/benchmarks/ (``python benchmarks/report/update_docs.py`` then copies each
into the ``<!-- BEGIN name -->`` block of README.md or a study):

* ``readme_tasks.md``: the table of tasks, from the registry (action space, observation
  modes, success rule) and the stored results (scripted and learned success, env speed
  over the CPUs on record);
* ``readme_quickstart.md``: the main job's time as ``scripts/main.sh`` runs it, per CPU
  class on record (``main_job*.json``);
* ``readme_highlights.md``: the README's few headline results;
* ``readme_results.md``: one sentence per result with the CPU and date it was measured on
  (for docs/studies/results.md; a result that is missing is left out, and said to be).

    python benchmarks/report/readme_results.py
"""

from __future__ import annotations

import json
from heml_gym.benchmarks.common import parse_arguments, ROOT, throughput_rate, throughput_rows, vector_isa

RESULTS = ROOT / "docs" / "benchmarks"  # the checkout's stored results


def load(name: str) -> dict | None:
    path = RESULTS / f"{name}.json"
    return json.loads(path.read_text()) if path.is_file() else None


def task_versions(data: dict) -> str:
    """The tasks a stored result measured, e.g. "TissueRetraction-v1" ("" if it does not say)."""
    return " and ".join(f"{name.split('/')[-1]}-{version}" for name, version in data.get("tasks", {}).items())


def where(data: dict) -> str:
    m = data["machine"]
    isa = f", {m['vector_isa']}" if "vector_isa" in m else ""  # results stored before 2026-11-25 lack it
    return f"{m['cpu']}, {m['cores']} cores{isa}, {m['date']}"


def learning(data: dict) -> str:
    done = [s for s in data["seeds"] if s["status"] == "finished"]
    wall = sorted(s["wall_s"] / 60 for s in done)
    rates = ", ".join(f"{s['success_rate']:.0%}" for s in data["seeds"] if s["status"] == "finished")
    steps = done[0]["env_steps"] if done else 0
    firsts = [s["first_eval_at_90_percent"] for s in done if s["first_eval_at_90_percent"] is not None]
    reach = (f"; the first evaluation at >= 90 % came at {min(firsts) // 1000}-{max(firsts) // 1000} k steps"
             if firsts else "")
    return (f"**Learning.** The main job (`{data['config']}`, PPO, {steps:,} env steps) reached >= 90 % success on "
            f"20 fresh episodes for **{data['seeds_at_90_percent']} of {data['seeds_finished']} seeds** "
            f"(final success {rates}; IQM {data['iqm']:.0%}, 95 % bootstrap interval {data['iqm_ci95'][0]:.0%}-"
            f"{data['iqm_ci95'][1]:.0%}){reach}; {wall[0]:.1f}-{wall[-1]:.1f} min of training per seed with one "
            f"core each, two seeds at a time{beside_other_work(data)} ({where(data)}; [per seed](quick_sweep.md)).")


def beside_other_work(data: dict) -> str:
    """What the wall times mean when other work shared the machine (``quick_sweep.py --loaded``)."""
    return ", beside other work on the machine: a quiet one is faster" if data.get("machine_loaded") else ""


def main_job_times() -> str:
    """The main job as ``scripts/main.sh`` runs it (stopping once learned), per CPU class on
    record (``main_job*.json``: ``quick_sweep.py --name main_job --cpus-per-trial 2``): the
    median training time over the seeds, where each stopped, and how many ended >= 90 %."""
    import statistics

    lines = []
    for path in sorted(RESULTS.glob("main_job*.json")):
        data = json.loads(path.read_text())
        done = [s for s in data["seeds"] if s["status"] == "finished"]
        if not done:
            continue
        minutes = [s["wall_s"] / 60 for s in done]
        stops = [s["env_steps"] for s in done]
        m = data["machine"]
        alone = (data.get("trials_at_once") == 1 and data.get("cpus_per_trial", 1) >= 2)
        how = "alone on the machine with both cores, as `scripts/main.sh` runs it" if alone else (
            f"{data.get('trials_at_once')} at a time")
        lines.append(
            f"On a {m['cores']}-core {m['cpu']} ({m.get('vector_isa', '?')}, {m['date']}; {how}"
            f"{beside_other_work(data)}): a median of **{statistics.median(minutes):.1f} min** per seed "
            f"({min(minutes):.1f}-{max(minutes):.1f} over {len(done)} seeds, stopping at "
            f"{min(stops) // 1000}-{max(stops) // 1000} k env steps); **{data['seeds_at_90_percent']} of "
            f"{data['seeds_finished']} seeds** ended at >= 90 % on 20 fresh episodes ([per seed]({path.stem}.md)).")
    return "\n\n".join(lines)


def pixels(data: dict) -> str:
    """The pixel baseline of one env: per seed when fewer than ``SEEDS_FOR_AN_IQM`` finished (no claim), else
    how many seeds passed 80 % within the budget and the final success's IQM, every seed
    listed."""
    from heml_gym.agents.stats import SEEDS_FOR_AN_IQM

    done = [s for s in data["seeds"] if s["status"] == "finished"]
    if not done:
        return ""
    env = task_versions(data)
    per_seed, passed = [], 0
    for s in done:
        first = next((e["env_steps"] for e in s["evaluations"] if e["success_rate"] >= 0.8), None)
        passed += first is not None
        reach = f"passed 80 % at {first // 1000} k env steps" if first is not None else "never passed 80 %"
        per_seed.append(f"Seed {s['seed']} {reach}, final {s['success_rate']:.0%} at {s['env_steps'] // 1000} k "
                        f"steps in {s['wall_s'] / 60:.0f} min")
    if len(done) < SEEDS_FOR_AN_IQM:
        claim = (f"{len(done)} seed{'s' if len(done) > 1 else ''} on record, fewer than the {SEEDS_FOR_AN_IQM} a claim "
                 "needs. ")
    else:
        low, high = data["iqm_ci95"]
        claim = (f"{passed} of {len(done)} seeds passed 80 % within {max(s['env_steps'] for s in done) // 1000} k env "
                 f"steps, final success IQM {data['iqm']:.0%} (95 % CI {low:.0%}-{high:.0%}). ")
    return (f"**From pixels{f' ({env})' if env else ''}.** PPO with a CNN on the task camera's images alone "
            f"(`{data['config']}`): {claim}{'. '.join(per_seed)} ({where(data)}{beside_other_work(data)}; "
            f"[envs.md](../studies/envs.md#learning-from-pixels)).")


def rllib(data: dict) -> str:
    """RLlib PPO on either env: every seed's first evaluation at >= 90 % and final success,
    with the final success's IQM when enough seeds are on record (``SEEDS_FOR_AN_IQM``)."""
    from heml_gym.agents.stats import SEEDS_FOR_AN_IQM, iqm, iqm_interval

    seeds = data["seeds"]
    if not seeds:
        return ""
    finals = [s["final_success_rate"] for s in seeds]
    per_seed = []
    for s in seeds:
        first = s["first_eval_at_90_percent"]
        reach = f"passed 90 % at {round(first / 1000)} k env steps" if first is not None else "never reached 90 %"
        per_seed.append(f"Seed {s['seed']} {reach}, final {s['final_success_rate']:.0%} in {s['wall_s'] / 60:.0f} min")
    env = data["env"].split("/")[-1]
    claim = f"{sum(f >= 0.9 for f in finals)} of {len(seeds)} seeds ended at >= 90 %"
    if len(seeds) >= SEEDS_FOR_AN_IQM:
        low, high = iqm_interval(finals)
        claim += f" (final success IQM {iqm(finals):.0%}, 95 % CI {low:.0%}-{high:.0%})"
    return (f"**RLlib ({env}).** RLlib PPO with {data['env_runners']} env runners of {data['scenes_per_runner']} "
            f"scenes (`{data['config']}`, {max(s['env_steps'] for s in seeds) // 1000} k env steps): {claim}. "
            f"{'. '.join(per_seed)} ({where(data)}{beside_other_work(data)}; [scale_out.md](../studies/scale_out.md#measured)).")


TISSUE, ORGAN = "heml_gym/TissueRetraction-v1", "heml_gym/OrganRetraction-v2"


def _rates(data: dict):
    """``rate(env_id, env, n, threads, actions)`` (env steps/s) and ``best_vector(env_id)``
    (the fastest vector row) of a stored env_throughput run."""
    def rate(env_id, env, n, threads, actions="random"):
        return throughput_rate(data["envs"][env_id]["throughput"], env=env, actions=actions, num_envs=n,
                               threads=threads)

    def best_vector(env_id):
        return max(throughput_rows(data["envs"][env_id]["throughput"], env="vector"),
                   key=lambda r: r["median_steps_per_s"])

    return rate, best_vector


def throughput(data: dict) -> str:
    rate, best_vector = _rates(data)
    tissue, organ = TISSUE, ORGAN
    tv, ov = best_vector(tissue), best_vector(organ)
    text = (f"**Env speed** (0.1 s of tissue per step, both envs' default physics: backward Euler by L-BFGS): "
            f"TissueRetraction {rate(tissue, 'single', 1, 1):,.0f} env steps/s as a single env on one core (random "
            f"actions), {tv['median_steps_per_s']:,.0f}/s as a {tv['num_envs']}-scene vector env on {tv['threads']} "
            f"cores; OrganRetraction ({data['envs'][organ]['breakdown'][0]['n_tets']:,} tets) {rate(organ, 'single', 1, 1):,.0f}/s single with random actions and "
            f"{rate(organ, 'single', 1, 1, 'scripted'):,.0f}/s on the scripted retraction")
    explicit = [rate(organ, "single, explicit", 1, 1, a) for a in ("random", "scripted")]
    if all(explicit):
        text += (f", {rate(organ, 'single', 1, 1) / explicit[0]:.1f}x and "
                 f"{rate(organ, 'single', 1, 1, 'scripted') / explicit[1]:.1f}x its explicit path in the same run")
    text += f", {ov['median_steps_per_s']:,.0f}/s vectorised ({where(data)}; [envs.md](../studies/envs.md#measured))."
    avx2 = load("env_throughput_avx2")
    return text + (" " + throughput_avx2(avx2, data) if avx2 else "")


def throughput_avx2(data: dict, native: dict | None = None) -> str:
    """The same rates with the kernels compiled for an AVX2-only CPU (``env_throughput.py
    --avx2``); ``native``: the run above (when it ran on an AVX2 CPU itself, this one is
    the generic AVX2 code any such CPU gets)."""
    rate, best_vector = _rates(data)
    tissue, organ = TISSUE, ORGAN
    tv, ov = best_vector(tissue), best_vector(organ)
    m = data["machine"]
    target = m.get("codegen", {}).get("cpu", data.get("compiled_for", "?"))
    machine = f"{m['cpu']}, {m['cores']} cores, {m['vector_isa']}, kernels compiled for {target}, {m['date']}"
    if native is not None and native["machine"].get("vector_isa") == m.get("vector_isa"):
        lead = (f"With the kernels compiled for a generic AVX2 CPU ({target}: what any AVX2 machine gets; "
                f"{m['date']}; [env_throughput_avx2.md](env_throughput_avx2.md)): ")
    else:
        lead = f"On an AVX2-only CPU ({machine}; [env_throughput_avx2.md](env_throughput_avx2.md)): "
    return (lead
            + f"TissueRetraction {rate(tissue, 'single', 1, 1):,.0f}/s single (random actions), "
            f"{tv['median_steps_per_s']:,.0f}/s vectorised; OrganRetraction {rate(organ, 'single', 1, 1):,.0f}/s "
            f"single with random actions and {rate(organ, 'single', 1, 1, 'scripted'):,.0f}/s on the scripted "
            f"retraction, {ov['median_steps_per_s']:,.0f}/s vectorised.")


def forces(data: dict) -> str:
    laws = data.get("laws")
    if not laws:
        return ""
    nh, stvk = (laws["native"]["tets_per_s"][k] / 1e6 for k in ("HEML Neo-Hookean", "HEML StVK"))
    avx2 = laws["avx2_target"]["tets_per_s"]["HEML Neo-Hookean"] / 1e6
    place = where(data)
    if "vector_isa" not in data["machine"]:  # stored before machine_info recorded it
        place += f", {vector_isa(laws.get('cpu_avx_flags', []))}"
    processes = laws["native"].get("processes", 1)
    median = f"; medians of {processes} processes each" if processes > 1 else ""
    return (f"**Forces.** HEML equals textbook FEM to 1e-15; its Neo-Hookean kernel runs {nh:.0f} M tets/s on one core "
            f"({stvk:.0f} M for StVK; {avx2:.0f} M when compiled for a plain AVX2 CPU{median}) on a "
            f"{laws['native']['n_tets']:,}-tet box ({place}; "
            "[physics_core.md](../studies/physics_core.md#force-kernel-throughput)).")


def implicit(data: dict) -> str:
    rows = [r for r in data.get("implicit_slab", []) if r["label"] == "default"]
    if not rows:
        return ""
    r = rows[0]
    return (f"**Implicit step.** A backward-Euler 1/30 s step of a LapGym-size slab ({r['n_tets']:,} tets) takes "
            f"{r['median_step_ms']:.1f} ms on one core, {r['mean_newton_iterations']:.1f} Newton iterations on average "
            f"({where(data)}; [dynamics.md](../studies/dynamics.md#measured-speed-one-thread)).")


def agents(data: dict) -> str:
    """Every learning result but the main job's (which has its own sentence)."""
    parts = []
    for g in data["groups"]:
        if g["name"] == "quick_sweep":
            continue
        level = "" if g.get("difficulty", 1) == 1 else f" at difficulty {g['difficulty']}"
        demos = g.get("demos")
        budget = (f"from {demos['episodes']} noisy {demos['policy']} episodes, no env steps" if demos
                  else f"at {max(s['env_steps'] for s in g['seeds']) // 1000} k steps")
        parts.append(f"{g['algorithm']} on {g['env'].split('/')[-1].rsplit('-v', 1)[0]}{level}: "
                     f"{g['seeds_at_90_percent']} of {len(g['seeds'])} seeds >= 90 % {budget} (IQM {g['iqm']:.0%}, "
                     f"{g['iqm_ci95'][0]:.0%}-{g['iqm_ci95'][1]:.0%})")
    for m in data["missing"]:
        level = "" if m.get("difficulty", 1) == 1 else f" at difficulty {m['difficulty']}"
        parts.append(f"{m['algorithm']} on {m['env'].split('/')[-1].rsplit('-v', 1)[0]}{level}: not run yet")
    if not parts:
        return ""
    return (f"**Other agents** (default task, difficulty 1, unless named): {'; '.join(parts)} "
            "([agents.md](../studies/agents.md#results)).")


def convergence(data: dict) -> str:
    parts = []
    for scene, res in data["results"].items():
        default = next(r for r in res["table"] if r.get("default"))
        force = max(s["force"] for s in default["per_seed"]) * 100
        exposure = max(s["exposure"] for s in default["per_seed"])
        verdict = "meets the 5 % rule" if default["within_5pct"] else "**misses the 5 % rule**"
        if "check" in res and not res["check"]["within_5pct"]:
            verdict += " against a reference that is itself not converged"
        parts.append(f"{scene} ({default['model']}, {default['n_tets']:,} tets): force error {force:.1f} %, "
                     f"exposure error {exposure:.3f}: {verdict}")
    return (f"**Accuracy of the env scenes.** The default models against fine models of the same scene, on the "
            f"scripted baseline's path and its 2 s hold: {'; '.join(parts)} "
            f"({where(data)}; [scene_convergence.md](../studies/scene_convergence.md)).")


def speed_range(env_id: str) -> str:
    """Env steps/s of ``env_id`` over every stored env_throughput run (one per CPU class or
    codegen target): single env on one core (random actions) / best vector env, each as a
    range over the runs."""
    singles, vectors = [], []
    for path in sorted(RESULTS.glob("env_throughput*.json")):
        data = json.loads(path.read_text())
        if env_id not in data.get("envs", {}):
            continue
        rate, best_vector = _rates(data)
        single = rate(env_id, "single", 1, 1)
        if single:
            singles.append(single)
            vectors.append(best_vector(env_id)["median_steps_per_s"])
    if not singles:
        return "not measured"

    def span(values):
        low, high = min(values), max(values)
        return f"{low:,.0f}" if round(low) == round(high) else f"{low:,.0f}-{high:,.0f}"

    return f"{span(singles)} / {span(vectors)}"


def cpu_classes() -> str:
    """The CPUs (and codegen targets) of the stored env_throughput runs, in words."""
    names = []
    for path in sorted(RESULTS.glob("env_throughput*.json")):
        m = json.loads(path.read_text())["machine"]
        codegen = m.get("codegen", {})
        chosen = codegen.get("set_by", "host") != "host"  # kernels compiled for another CPU than the host
        name = (f"{m['cpu']} {m.get('vector_isa', '')}".strip()
                + (f", kernels compiled for {codegen.get('cpu')}" if chosen else ""))
        if name not in names:  # (one CPU class may have several runs: other tasks timed later)
            names.append(name)
    return "; ".join(names)


def learned(env_id: str, agents_data: dict | None) -> str:
    """Each algorithm's seeds at >= 90 % final success on ``env_id`` (difficulty 1)."""
    parts = []
    for g in (agents_data or {}).get("groups", []):
        if g["env"] == env_id and g.get("difficulty", 1) == 1:
            parts.append(f"{g['algorithm']} {g['seeds_at_90_percent']}/{len(g['seeds'])}")
    for name in ("rllib_learning", "rllib_learning_organ"):
        data = load(name)
        if data and data.get("env") == env_id and data["seeds"]:
            finals = [s["final_success_rate"] for s in data["seeds"]]
            parts.append(f"RLlib PPO {sum(f >= 0.9 for f in finals)}/{len(finals)}")
    return ", ".join(parts) or "not trained yet"


def _instruments(task) -> str:
    """A task's instruments in words: "grasper", "2 graspers (left, right)", "paddle", "grasper, hook"."""
    graspers = [g for g in task.instruments if g.kind == "grasper"]
    parts = []
    if len(graspers) == 1:
        parts.append("grasper")
    elif graspers:
        parts.append(f"{len(graspers)} graspers ({', '.join(g.name for g in graspers)})")
    parts += [g.kind for g in task.instruments if g.kind != "grasper"] + [h.kind for h in task.hooks]
    return ", ".join(parts)


def task_table() -> str:
    """The README's table of tasks: from the registry (spaces, settings) and the stored
    results (scripted and learned success, speed)."""
    import gymnasium as gym

    from heml_gym.envs import ENV_IDS, GOAL_ENV_IDS
    from heml_gym.envs.retraction_env import OBS_MODES

    agents_data = load("agent_results")
    rows = []
    for env_id in ENV_IDS:
        env = gym.make(env_id)
        u = env.unwrapped
        s = u.task.settings
        space = env.action_space
        action = f"`{type(space).__name__}({', '.join(str(n) for n in space.shape)},)`"
        if hasattr(s, "goal_tolerance"):  # a goal task
            success = f"marked point within {s.goal_tolerance * 1e3:g} mm of a goal drawn per episode"
        elif hasattr(s, "release_fraction"):  # a dissection: the critical view of safety
            success = (f"critical view: >= {s.release_fraction:.0%} of the lower third freed, both ducts exposed "
                       f">= {s.success_exposure:.0%}, held {s.hold_time:g} s, no energy near the bile duct")
        else:
            success = (f"exposure >= {s.success_exposure:.0%}, gauge strain < {s.damage_strain:g}"
                       + (f", held {s.hold_time:g} s" if s.hold_time else ""))
        scripted = (agents_data or {}).get("scripted", {}).get(env_id)
        scripted_text = (f"{scripted['success_rate']:.0%} of {scripted['episodes']}" if scripted else "not measured")
        instruments = _instruments(u.task)
        if env_id in GOAL_ENV_IDS:
            action = action + ", goal-conditioned"
        rows.append([f"`{env_id}`", instruments, action, ", ".join(OBS_MODES), success, scripted_text,
                     learned(env_id, agents_data), speed_range(env_id)])
        env.close()
    from heml_gym.benchmarks.common import markdown_table

    return (markdown_table(["task", "instruments", "action", "observations", "success", "scripted expert",
                            "learned (seeds >= 90 %)", "env steps/s: single / vector"], rows)
            + f"\nWritten by `benchmarks/report/readme_results.py` from the registry and the stored results. "
            f"Learned: seeds whose final success on 20 fresh episodes is >= 90 % ([all results](../studies/agents.md#results)). "
            f"Speed: one env on one core / the best vector env on 2 cores, the range over the CPUs on record "
            f"({cpu_classes()}; [env_throughput.md](env_throughput.md)).\n")


def highlights() -> str:
    """The README's few headline results, one short sentence each, with a link to the rest."""
    lines = []
    conv = load("scene_convergence")
    if conv:
        parts = []
        for scene, res in conv["results"].items():
            default = next(r for r in res["table"] if r.get("default"))
            parts.append(f"{scene} {max(x['force'] for x in default['per_seed']) * 100:.1f} %")
        lines.append("**Accurate where the task needs it.** Along each task's scripted solution, the default mesh's grasp "
                     f"force stays within 5 % of a fine mesh ({', '.join(parts)}; "
                     "[scene_convergence](../studies/scene_convergence.md)).")
    f = load("force_throughput")
    if f and f.get("laws"):
        nh = f["laws"]["native"]["tets_per_s"]["HEML Neo-Hookean"] / 1e6
        lines.append(f"**Fast.** HEML's forces equal textbook FEM to 1e-15, at {nh:.0f} M tets/s on one core "
                     f"({f['machine']['cpu']}, {f['machine']['date']}; [physics_core](../studies/physics_core.md)).")
    harm = [load(n) for n in ("constrained_tissue", "constrained_organ")]
    if all(harm) and all(h["verdict"]["met"] for h in harm):
        lines.append("**Harm as a cost.** Trained against a damage budget, PPO-Lagrangian lowers the final damage at "
                     f"the same success on both tasks, {min(len(h['methods']['PPO']['seeds']) for h in harm)} seeds "
                     "each ([training under a budget]"
                     "(../studies/agents.md#tissue-harm-under-a-budget)).")
    pix = [load(n) for n in ("pixel_learning", "organ_pixel_learning")]
    if all(pix):
        done = [sum(x["status"] == "finished" for x in d["seeds"]) for d in pix]
        lines.append(f"**From pixels.** PPO with a CNN learns both tasks from the task camera alone ({done[0]} and "
                     f"{done[1]} seeds; [learning from pixels](../studies/envs.md#learning-from-pixels)).")
    lines.append("Every result, its CPU and date: [results](../studies/results.md).")
    return "\n".join(f"- {line}" for line in lines) + "\n"


def main() -> int:
    (RESULTS / "readme_tasks.md").write_text(task_table())
    (RESULTS / "readme_highlights.md").write_text(highlights())
    sections = [("quick_sweep", learning), ("env_throughput", throughput), ("force_throughput", forces),
                ("simulation_speed", implicit), ("scene_convergence", convergence), ("agent_results", agents),
                ("rllib_learning", rllib), ("rllib_learning_organ", rllib), ("pixel_learning", pixels),
                ("organ_pixel_learning", pixels)]
    lines, missing, stale = [], [], []
    for name, write in sections:
        data = load(name)
        if data is None:
            missing.append(name)
            continue
        if data.get("stale"):  # set by hand when the env changed under a stored result; a re-run clears it
            stale.append(f"{name} ({data['stale']})")
            continue
        text = write(data)
        if text:
            lines.append(text)
    out = "Written by `benchmarks/report/readme_results.py` from the stored results in docs/benchmarks/.\n\n"
    out += "\n\n".join(f"- {line}" for line in lines) + "\n"
    if missing:
        out += f"\n(Not measured yet: {', '.join(missing)}.)\n"
    if stale:
        out += f"\n(Not re-run on the current defaults, so not quoted: {'; '.join(stale)}.)\n"
    (RESULTS / "readme_results.md").write_text(out)
    print(out)
    times = main_job_times()
    (RESULTS / "readme_quickstart.md").write_text(
        (times or "The main job's time with early stopping is not on record yet.") + "\n")
    return 0


if __name__ == "__main__":
    parse_arguments(__doc__)
    raise SystemExit(main())
