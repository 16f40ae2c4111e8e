"""The README's "Results" and its quick-start sentence, written from the stored results.

Reads docs/benchmarks/{quick_sweep,env_throughput,force_throughput,simulation_speed,
scene_convergence,agent_results,rllib_learning,rllib_learning_organ,pixel_learning,
organ_pixel_learning}.json
and writes docs/benchmarks/readme_results.md, one sentence per result with the CPU and
date it was measured on (a result that is missing is left out, and said to be), and docs/benchmarks/readme_quickstart.md (what the main job
gives across seeds). ``python benchmarks/report/update_docs.py`` then copies them into README.md.

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


def quickstart(data: dict) -> str:
    """The quick-start sentence: what the main job gives a fresh clone, across seeds."""
    done = [s for s in data["seeds"] if s["status"] == "finished"]
    wall = sorted(s["wall_s"] / 60 for s in done)
    misses = [f"seed {s['seed']}: {s['success_rate']:.0%}" for s in done if s["success_rate"] < 0.9]
    m = data["machine"]
    isa = f", {m['vector_isa']}" if "vector_isa" in m else ""
    text = (f"Measured on a {m['cores']}-core {m['cpu']} ({m['date']}{isa}), {len(done)} seeds: training took "
            f"{wall[0]:.1f}-{wall[-1]:.1f} min per seed (one core each, two seeds at a time"
            f"{beside_other_work(data)}), and "
            f"**{data['seeds_at_90_percent']} of {data['seeds_finished']} seeds** reached >= 90 % success on 20 fresh "
            "evaluation episodes")
    text += f" (below it: {', '.join(misses)})." if misses else "."
    return text + " [Per seed](quick_sweep.md)."


def quickstart_elsewhere(data: dict) -> str:
    """The same job re-run with other seeds on another machine (``quick_sweep_avx2``)."""
    done = [s for s in data["seeds"] if s["status"] == "finished"]
    if not done:
        return ""
    wall = sorted(s["wall_s"] / 60 for s in done)
    ended = ", ".join(f"seed {s['seed']} at {s['success_rate']:.0%}" for s in done)
    took = f"{wall[0]:.1f} min" if len(wall) == 1 else f"{wall[0]:.1f}-{wall[-1]:.1f} min per seed"
    if data.get("trials_at_once", 1) == 1 and data.get("cpus_per_trial", 1) >= 2 and not data.get("machine_loaded"):
        how = "alone on the machine with both cores, as `scripts/main.sh` runs it"
    else:
        how = f"{data.get('trials_at_once', 1)} at a time{beside_other_work(data)}"
    task = task_versions(data)
    seeds = "a seed" if len(done) == 1 else "seeds"
    return (f" On an AVX2-only machine ({where(data)}{f'; {task}' if task else ''}) with {seeds} no config was tuned "
            f"on, training took {took} ({how}) and ended with {ended} ([per seed](quick_sweep_avx2.md)).")


def quickstart_quiet(data: dict) -> str:
    """The same job alone on the machine with both cores, as ``scripts/main.sh`` runs it
    (``quick_sweep_quiet``: ``quick_sweep.py --seeds 7 --cpus-per-trial 2 --name quick_sweep_quiet``)."""
    done = [s for s in data["seeds"] if s["status"] == "finished"]
    if not done or data.get("machine_loaded"):
        return ""
    runs = ", ".join(f"seed {s['seed']} took {s['wall_s'] / 60:.1f} min and ended at {s['success_rate']:.0%}"
                     for s in done)
    isa = data["machine"].get("vector_isa")
    on = f" (the same {isa} machine type)" if isa else ""
    return (f" Alone on the machine with both cores, as `scripts/main.sh` runs it{on}, {runs} "
            f"([quiet run](quick_sweep_quiet.md)).{avx2_slowdown()}")


def avx2_slowdown() -> str:
    """How much slower the main job's env (16 flap scenes, 2 threads) steps on an AVX2-only
    CPU than in the AVX-512 run, from the two stored env_throughput runs ("" without both)."""
    native, avx2 = load("env_throughput"), load("env_throughput_avx2")
    if not (native and avx2) or native["machine"].get("vector_isa") != "AVX-512":
        return ""
    rates = [_rates(d)[0](TISSUE, "vector", 16, 2) for d in (native, avx2)]
    if None in rates:
        return ""
    return (f" On an AVX2-only CPU the main job's 16 flap scenes step {rates[0] / rates[1]:.1f}x slower "
            f"({rates[1]:,.0f} against {rates[0]:,.0f} env steps/s, Results); PPO's own updates run slower "
            "there too, and the main job's wall time on such a machine is not on record for today's code.")


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
        per_seed.append(f"seed {s['seed']} {reach}, final {s['success_rate']:.0%} at {s['env_steps'] // 1000} k "
                        f"steps in {s['wall_s'] / 60:.0f} min")
    if len(done) < SEEDS_FOR_AN_IQM:
        claim = (f"{len(done)} seed{'s' if len(done) > 1 else ''} on record, fewer than the {SEEDS_FOR_AN_IQM} a claim "
                 "needs: ")
    else:
        low, high = data["iqm_ci95"]
        claim = (f"{passed} of {len(done)} seeds passed 80 % within {max(s['env_steps'] for s in done) // 1000} k env "
                 f"steps, final success IQM {data['iqm']:.0%} (95 % CI {low:.0%}-{high:.0%}): ")
    return (f"**From pixels{f' ({env})' if env else ''}.** PPO with a CNN on the task camera's images alone "
            f"(`{data['config']}`), {claim}{'; '.join(per_seed)} ({where(data)}{beside_other_work(data)}; "
            f"[envs.md](../envs.md#learning-from-pixels)).")


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
        per_seed.append(f"seed {s['seed']} {reach}, final {s['final_success_rate']:.0%} in {s['wall_s'] / 60:.0f} min")
    env = data["env"].split("/")[-1]
    claim = f"{sum(f >= 0.9 for f in finals)} of {len(seeds)} seeds ended at >= 90 %"
    if len(seeds) >= SEEDS_FOR_AN_IQM:
        low, high = iqm_interval(finals)
        claim += f" (final success IQM {iqm(finals):.0%}, 95 % CI {low:.0%}-{high:.0%})"
    return (f"**RLlib ({env}).** RLlib PPO with {data['env_runners']} env runners of {data['scenes_per_runner']} "
            f"scenes (`{data['config']}`, {max(s['env_steps'] for s in seeds) // 1000} k env steps): {claim}: "
            f"{'; '.join(per_seed)} ({where(data)}{beside_other_work(data)}; [scale_out.md](../scale_out.md#measured)).")


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
    text += f", {ov['median_steps_per_s']:,.0f}/s vectorised ({where(data)}; [envs.md](../envs.md#measured))."
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
            "[physics_core.md](../physics_core.md#force-kernel-throughput)).")


def implicit(data: dict) -> str:
    rows = [r for r in data.get("implicit_slab", []) if r["label"] == "default"]
    if not rows:
        return ""
    r = rows[0]
    return (f"**Implicit step.** A backward-Euler 1/30 s step of a LapGym-size slab ({r['n_tets']:,} tets) takes "
            f"{r['median_step_ms']:.1f} ms on one core, {r['mean_newton_iterations']:.1f} Newton iterations on average "
            f"({where(data)}; [dynamics.md](../dynamics.md#measured-speed-one-thread)).")


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
            "([agents.md](../agents.md#results)).")


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
            f"({where(data)}; [scene_convergence.md](../scene_convergence.md)).")


def main() -> int:
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
    sweep = load("quick_sweep")
    if sweep is not None:
        elsewhere, quiet = load("quick_sweep_avx2"), load("quick_sweep_quiet")
        text = (quickstart(sweep) + (quickstart_quiet(quiet) if quiet else "")
                + (quickstart_elsewhere(elsewhere) if elsewhere else ""))
        (RESULTS / "readme_quickstart.md").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    parse_arguments(__doc__)
    raise SystemExit(main())
