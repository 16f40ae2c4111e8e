"""The ``heml-gym`` command line: train, eval, rollout, bench.

    heml-gym train configs/tissue_ppo.yaml [--seed 1] [--resume CHECKPOINT] [--steps N]
    heml-gym eval runs/tissue_ppo-seed0 [--episodes 50]   (or: eval scripted --env ID; eval pretrained)
    heml-gym rollout [--policy scripted|MODEL] [--env ID] [--episodes 2] [--rrd out.rrd] [--spawn]
    heml-gym scene [ENV_ID] [--out scene.yaml]
    heml-gym sweep CONFIG --seeds 0,1,2 [--set KEY=VALUE] [--grid KEY=V1,V2] [--address ADDR] [--out DIR]
    heml-gym export RUN --out policy.onnx [--speed-limit 0.02] [--workspace x0,y0,z0,x1,y1,z1]
    heml-gym demos ENV --out NAME [--policy scripted|pretrained|RUN|policy.onnx] [--episodes 20]
    heml-gym observe ENV --out obs.npz [--young-modulus E] [--points 10] [--point-noise 0.0005]
    heml-gym calibrate ENV obs.npz --out DIR [--fit young_modulus,poisson_ratio] [--regions 2x1x1]
    heml-gym bench [NAME ...] [--out DIR] [--extra ARGS]   (no name: the benchmarks by group)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

# Idle OpenMP workers (Numba's and PyTorch's) sleep instead of spinning: on a machine whose
# cores are shared, spinning workers slow down the code that runs between parallel calls.
# It has to be set before the OpenMP runtime starts, so here, before anything imports it.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


DEFAULT_ENV = "heml_gym/TissueRetraction-v1"


def _known_env(env_id: str, argument: str = "--env") -> str:
    """``env_id`` if it is a registered heml_gym environment, else a user error naming it."""
    import gymnasium as gym

    import heml_gym.envs  # noqa: F401  (registers the ids)

    if env_id not in gym.registry:
        from heml_gym.envs import unknown_env_message

        raise ValueError(f"{argument}: {unknown_env_message(env_id)}")
    return env_id


class _Parser(argparse.ArgumentParser):
    """Bad flags are user errors too: one line (with where to find the usage), exit 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (usage: {self.prog} -h)\n")


TRUST_HELP = ("read a run folder's pickles (statistics written before 2026-11-26, RLlib checkpoints): they can "
              "run code, so only for a folder you trust")


def _train(args) -> int:
    from .config import load_config
    from .train import train

    overrides = {}
    if args.seed is not None:
        overrides["seed"] = args.seed
    if args.steps is not None:
        overrides.setdefault("algorithm", {})["total_timesteps"] = args.steps
    cfg = load_config(args.config, overrides)
    if args.steps is not None and cfg.algorithm.name == "BC":
        raise ValueError("--steps: a BC run takes no env steps (it learns from its demos: demos.episodes)")
    if cfg.algorithm.name == "BC":  # its demonstrations first, if they are not recorded yet
        from .demos import record_config_demos

        record_config_demos(cfg, progress=not args.no_progress)
    result = train(cfg, run_dir=args.run_dir, resume=args.resume, progress_bar=not args.no_progress,
                   trust_pickle=args.trust_pickle,
                   address=args.address)
    ev = result["final_evaluation"]
    print(f"run folder: {result['run_dir']}  ({result['timesteps']} env steps)")
    if result.get("stopped_early"):
        e = cfg.evaluation
        print(f"  stopped early: {e.stop_after} evaluations in a row reached {e.stop_at_success:.0%} success "
              f"(cap: {cfg.algorithm.total_timesteps} env steps)")
    run_dir = Path(result["run_dir"])
    model_file = "rllib_checkpoint/" if (run_dir / "rllib_checkpoint").is_dir() else (
        "policy.pt" if (run_dir / "policy.pt").is_file() else "model.zip")
    print(f"  model:       {run_dir / model_file}")
    if (run_dir / "checkpoints").is_dir():
        print(f"  checkpoints: {run_dir / 'checkpoints'}")
    if (Path(result["run_dir"]) / "tb").is_dir():
        print(f"  tensorboard: tensorboard --logdir {Path(result['run_dir']) / 'tb'}")
    print(f"  evaluation:  success {ev['success_rate']:.0%} (95% CI {ev['success_ci95'][0]:.0%}-"
          f"{ev['success_ci95'][1]:.0%}) over {ev['episodes']} episodes")
    return 0


def _eval(args) -> int:
    from .evaluation import evaluate_policy
    from .train import load_policy

    if args.env:
        _known_env(args.env)
    policy, cfg = None, None
    if args.run_or_model == "scripted":  # the task's scripted expert
        import gymnasium as gym

        from heml_gym.envs.scripted import scripted_policy

        args.env = args.env or DEFAULT_ENV
        probe = gym.make(args.env)
        policy = scripted_policy(probe.unwrapped.scene)
        probe.close()
    elif (policy := _exported(args.run_or_model, args.env)) is not None:
        args.env = policy.runs_on
    else:
        policy, _, cfg = load_policy(args.run_or_model, trust_pickle=args.trust_pickle)
    env_id = args.env or (cfg.env.id if cfg else DEFAULT_ENV)
    obs_mode = cfg.env.obs_mode if cfg else "state"
    kwargs = cfg.env.kwargs if cfg and env_id == cfg.env.id else {}
    if args.physics:
        from heml_gym.envs import SpecError, check_env_kwargs

        from .calibrate import parse_json_mapping

        kwargs = {**kwargs, "physics": {**kwargs.get("physics", {}), **parse_json_mapping(args.physics, "--physics")}}
        try:
            check_env_kwargs(env_id, kwargs, "env")
        except SpecError as exc:
            raise ValueError(f"--physics: {exc}") from None
    result = evaluate_policy(policy, env_id, args.episodes, seed=args.seed, obs_mode=obs_mode, env_kwargs=kwargs)
    result["env"] = env_id
    if args.physics:
        result["physics"] = kwargs["physics"]
    print(json.dumps(result, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=1))
    return 0


def _rollout(args) -> int:
    import gymnasium as gym

    import heml_gym.envs  # noqa: F401

    from .recording import record_rollouts

    if args.env:
        _known_env(args.env)
    if not args.rrd and not args.spawn:
        raise ValueError("nothing to record to: give --rrd FILE.rrd and/or --spawn (a viewer)")
    if args.policy == "scripted":
        from heml_gym.envs.scripted import scripted_policy

        env = gym.make(args.env or DEFAULT_ENV)
        policy = scripted_policy(env.unwrapped.scene)
    elif (exported := _exported(args.policy, args.env)) is not None:
        policy, env = exported, gym.make(exported.runs_on)
    else:
        from .train import load_policy, make_env

        policy, _, cfg = load_policy(args.policy, trust_pickle=args.trust_pickle)
        if cfg and args.env and args.env != cfg.env.id:
            raise ValueError(f"--env {args.env}: the policy was trained on {cfg.env.id} (its observations and "
                             "actions are that env's); omit --env to roll it out there")
        env = make_env(cfg, None if cfg else (args.env or DEFAULT_ENV))
    summary = record_rollouts(env, policy, path=args.rrd, episodes=args.episodes, seed=args.seed,
                              spawn=args.spawn)
    print(json.dumps(summary, indent=1, default=str))
    if args.rrd:
        print(f"recording: {args.rrd}  (open with: rerun {args.rrd})")
    return 0


def _exported(spec: str, env_id: str | None):
    from .export import exported_policy

    return exported_policy(spec, env_id, DEFAULT_ENV)


def _scene(args) -> int:
    import yaml

    import heml_gym.envs  # noqa: F401
    from heml_gym.envs import check_env_kwargs

    _known_env(args.env, "env")
    scene = check_env_kwargs(args.env, {}, "scene")
    text = f"# the default scene of {args.env} (heml_gym.envs.Scene); pass an edited copy as\n" \
           f"# gym.make({args.env!r}, scene='this.yaml') or a run config's env.kwargs.scene\n" \
           + yaml.safe_dump(scene.to_dict(), sort_keys=False, default_flow_style=None)
    if args.out:
        Path(args.out).write_text(text)
        print(f"scene written to {args.out}")
    else:
        print(text, end="")
    return 0


def _sweep(args) -> int:
    from .sweep import parse_assignments, parse_grid, plan_sweep, run_sweep

    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError:
        raise ValueError(f"--seeds must be comma-separated integers, got {args.seeds!r}") from None
    out = Path(args.out) if args.out else Path("runs") / f"sweep-{Path(args.config).stem}"
    if not (args.cpus_per_trial > 0):
        raise ValueError(f"--cpus-per-trial must be > 0, got {args.cpus_per_trial}")
    trials = plan_sweep(args.config, seeds, parse_assignments(args.set), parse_grid(args.grid), out)
    if trials[0].config.algorithm.name == "BC":  # its demonstrations once, before the trials read them
        from .demos import record_config_demos

        for cfg in {t.config.demos.dataset: t.config for t in trials}.values():
            record_config_demos(cfg, progress=not args.quiet)
    summary = run_sweep(trials, out, address=args.address, cpus_per_trial=args.cpus_per_trial,
                        verbose=not args.quiet)
    for row in summary["trials"]:
        if row["status"] == "finished":
            lo, hi = row["success_ci95"]
            print(f"  {row['name']}: success {row['success_rate']:.0%} ({lo:.0%}-{hi:.0%}), "
                  f"{row['env_steps']} env steps, {row['wall_s']:.0f} s on {row['hostname']} ({row['node_id'][:8]})")
        else:
            print(f"  {row['name']}: {row['status'].upper()}: {row.get('error', '')}")
    for point in summary["grid_points"]:
        if "iqm" in point:
            print(f"  {point['grid_point'] or 'all'}: IQM success {point['iqm']:.0%} "
                  f"(95% CI {point['iqm_ci95'][0]:.0%}-{point['iqm_ci95'][1]:.0%}) over seeds {point['seeds']}")
    print(f"summary: {out / 'summary.json'}, chart: {out / 'summary.png'}")
    return 0 if summary["failed"] == 0 else 1


def _observe(args) -> int:
    from .calibrate import observe

    _known_env(args.env, "ENV")
    out = Path(args.out)
    if out.exists():
        raise ValueError(f"--out {out}: exists (give a new file)")
    summary = observe(args.env, args.out, seed=args.seed, steps=args.steps, points=args.points,
                      point_noise=args.point_noise, force_noise=args.force_noise, young_modulus=args.young_modulus,
                      poisson=args.poisson, law=args.law, env_kwargs=args.env_kwargs, depth=args.depth,
                      depth_noise=args.depth_noise, force=not args.no_force, wrist_reach=args.wrist_reach)
    print(json.dumps(summary, indent=1))
    return 0


def _calibrate(args) -> int:
    from .calibrate import calibrate

    if args.env != "-":
        _known_env(args.env, "ENV")
    names = tuple(n.strip() for n in args.fit.split(",") if n.strip())
    record = calibrate(None if args.env == "-" else args.env, args.observation, args.out, names, law=args.law,
                       env_kwargs=args.env_kwargs, starts=args.starts, point_scale=args.point_scale,
                       force_scale=args.force_scale, progress=not args.no_progress, wrist_reach=args.wrist_reach,
                       regions=args.regions, use=args.use, mesh_correction=not args.no_mesh_correction,
                       jobs=args.jobs)
    settings = record["settings"]
    left = [q for q in settings["in_the_file"] if q not in settings["observed"]]
    print(f"fitted on {settings['model']}, to the {', '.join(settings['observed'])}"
          + (f" (not the file's {', '.join(left)}: --use to choose)" if left and args.use is None else ""))
    for caveat in record["caveats"]:
        print(f"warning: {caveat}", file=sys.stderr)
    correction = record["mesh_correction"]
    if correction and "skipped" in correction:
        print(f"warning: no mesh correction: {correction['skipped']}", file=sys.stderr)
    elif correction and "error" in correction:
        print(f"warning: no mesh correction (the fit on {settings['model']} is reported as it is): {correction['error']}",
              file=sys.stderr)
    elif correction:
        print(f"corrected for the mesh against {correction['reference']} (its fit of that model's replay: "
              + ", ".join(f"{n} {raw:.4g} -> {refit:.4g}" for n, raw, refit in
                          zip(record["parameters"], correction["raw"], correction["refit"])) + ")")
        if not correction["converged"]:
            print("warning: the mesh correction's refit did not converge", file=sys.stderr)
    for name, p in record["parameters"].items():
        std = f"{p['std']:.2g}" if p["std"] is not None else "? (not determined by the data)"
        print(f"{name}: {p['value']:.6g} ± {std} {p['unit']}".rstrip())
    print("residual RMS: " + ", ".join(f"{k} {v:.3g}" for k, v in record["residual_rms"].items()))
    if record["loosely_determined"]:
        print(f"warning: the data determine {', '.join(record['loosely_determined'])} only loosely (standard error "
              "above 10 % of the value; nu's above 0.02): more or other observations (points and force, a longer or "
              "larger retraction) would pin them down", file=sys.stderr)
    for found in record["disagreements"]:
        unit = record["parameters"][found["constant"]]["unit"]
        print(f"warning: the observed quantities disagree on {found['constant']} (each alone, one Gauss-Newton step "
              "from the joint fit: " + ", ".join(
            f"{q} {v:.4g} {unit}".rstrip() for q, v in found["estimates"].items()) + "), more than their noise "
            "allows: one of them carries a model error the joint fit averages in (--use keeps the one you trust)",
            file=sys.stderr)
    if record["law_selection"]:
        print(f"law: {record['law']} (held-out RMS: " + ", ".join(
            f"{r['law']} {r['heldout_rms_m'] * 1e3:.3f} mm" if "heldout_rms_m" in r else f"{r['law']} failed"
            for r in record["law_selection"]) + ")")
        tie = record["law_ambiguity"]
        if tie:
            spans = "; ".join(f"{name} {lo:.4g} to {hi:.4g} {record['parameters'][name]['unit']}".rstrip()
                              for name, (lo, hi) in tie["ranges"].items())
            print(f"warning: the data do not tell {', '.join(tie['laws'])} apart (each one's held-out RMS is within "
                  f"the 95 % interval of {record['law']}'s); fitted with them: {spans}. The constants hold for the "
                  "law assumed: give --law if you know it", file=sys.stderr)
    written = [Path(args.out) / name for name in ("fit.json", "fit.png", "fit.rrd") if (Path(args.out) / name).is_file()]
    print("written: " + ", ".join(str(p) for p in written)
          + (f"  (open the recording with: rerun {Path(args.out) / 'fit.rrd'})" if Path(args.out, "fit.rrd").is_file()
             else ""))
    if not record["converged"]:
        print(f"the fit did NOT converge: {record['message']}", file=sys.stderr)
        return 1
    return 0


def _export(args) -> int:
    from .export import ExportError, export_policy
    from .train import load_run, make_env, model_file

    out = Path(args.out)
    if out.suffix != ".onnx":
        raise ValueError(f"--out: an ONNX policy file ends in .onnx, got {args.out!r}")
    workspace = None
    if args.workspace:
        try:
            values = [float(v) for v in args.workspace.split(",")]
        except ValueError:
            raise ValueError(f"--workspace: six numbers (m), x0,y0,z0,x1,y1,z1, got {args.workspace!r}") from None
        if len(values) != 6:
            raise ValueError(f"--workspace: six numbers (m), x0,y0,z0,x1,y1,z1, got {len(values)}")
        workspace = (values[:3], values[3:])
    from .bc import is_bc_run, load_bc_run

    if is_bc_run(Path(args.run)):  # behaviour cloning: its network and statistics, read without unpickling
        from .config import load_config

        path = Path(args.run)
        cfg = load_config(path / "config.yaml")
        model, normalizer = load_bc_run(path, cfg)
    else:
        path, cfg = model_file(args.run)
        if cfg is None:
            raise ExportError(f"{path}: no run config beside it (export reads a run folder or a checkpoint of one)")
        if cfg.env.obs_mode != "state":
            raise ExportError(f"{args.run}: trained on {cfg.env.obs_mode!r} observations; only state policies export")
        model, normalizer = load_run(path, cfg, trust_pickle=args.trust_pickle)
    max_speed = make_env(cfg).unwrapped.task.settings.max_speed
    export_policy(model, normalizer, out, cfg.env.id, run=str(path), speed_limit=args.speed_limit,
                  workspace=workspace, max_speed=max_speed)
    print(f"written: {out}  (heml-gym rollout --policy {out} --rrd r.rrd)")
    return 0


def _demos(args) -> int:
    from .demos import collect_demos

    _known_env(args.env, "ENV")
    summary = collect_demos(args.env, args.policy, args.episodes, args.out, seed=args.seed, root=args.root,
                            reference_episodes=args.reference_episodes, action_noise=args.action_noise)
    print(json.dumps(summary, indent=1))
    return 0


def _bench(args) -> int:
    from heml_gym import benchmarks

    if not args.names:
        print(benchmarks.listing())
        return 0
    known = benchmarks.studies()
    for name in args.names:  # every name checked before anything runs
        if name not in known:
            raise ValueError(f"unknown benchmark {name!r} (known: {', '.join(known)}; `heml-gym bench` lists them)")
    for name in args.names:
        print(f"== {name}", flush=True)
        code = benchmarks.run(name, args.extra, out=args.out)
        if code:
            return code
    return 0


def main(argv=None) -> int:
    ap = _Parser(prog="heml-gym", description="Train, evaluate and record agents on HEML tissue.")
    sub = ap.add_subparsers(dest="command", required=True)

    t = sub.add_parser("train", help="train an agent from a YAML config")
    t.add_argument("config")
    t.add_argument("--seed", type=int)
    t.add_argument("--steps", type=int, help="override algorithm.total_timesteps")
    t.add_argument("--resume", help="checkpoint .zip to continue from (keeps its step count)")
    t.add_argument("--run-dir", help="run folder (default runs/<config name>-seed<seed>)")
    t.add_argument("--no-progress", action="store_true", help="no progress bar")
    t.add_argument("--address", help="Ray cluster for an RLlibPPO run ('auto', HOST:PORT; default: local Ray)")
    t.add_argument("--trust-pickle", action="store_true", help=TRUST_HELP)
    t.set_defaults(func=_train)

    e = sub.add_parser("eval", help="success rate of a trained model or run folder")
    e.add_argument("run_or_model", help="a run folder, a model .zip, an exported .onnx policy, 'pretrained' or "
                   "'scripted' (the task's scripted expert; --env picks the task)")
    e.add_argument("--episodes", type=int, default=50)
    e.add_argument("--seed", type=int, default=10_000)
    e.add_argument("--env", help="environment id (default: the run's)")
    e.add_argument("--out", help="write the result as JSON here")
    e.add_argument("--physics", help="JSON physics= changes for the evaluation episodes, over the run's: e.g. a "
                   "held-out stiffness range '{\"young_modulus\": [8000, 16000]}', or '{\"fit\": \"fit/\"}'")
    e.add_argument("--trust-pickle", action="store_true", help=TRUST_HELP)
    e.set_defaults(func=_eval)

    r = sub.add_parser("rollout", help="roll a policy out and record it to rerun")
    r.add_argument("--policy", default="scripted", help="'scripted', 'pretrained' (shipped with the package), a "
                                                        "model .zip, a run folder or an exported .onnx")
    r.add_argument("--env", help=f"environment id (default: the run's; {DEFAULT_ENV} for 'scripted')")
    r.add_argument("--episodes", type=int, default=2)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--rrd", help="write the recording to this .rrd file")
    r.add_argument("--spawn", action="store_true", help="open the rerun viewer")
    r.add_argument("--trust-pickle", action="store_true", help=TRUST_HELP)
    r.set_defaults(func=_rollout)

    w = sub.add_parser("sweep", help="seed / hyperparameter sweep on Ray Tune (local or a cluster)")
    w.add_argument("config")
    w.add_argument("--seeds", default="0", help="comma-separated seeds (default 0)")
    w.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key for every trial (dotted, e.g. algorithm.total_timesteps=2048)")
    w.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2",
                   help="a config key to sweep over (dotted; one trial per value and seed)")
    w.add_argument("--address", help="Ray cluster address ('auto', HOST:PORT); default: a local Ray instance")
    w.add_argument("--out", help="sweep folder (default runs/sweep-<config name>)")
    w.add_argument("--cpus-per-trial", type=float, default=1.0, help="CPUs Ray reserves per trial (default 1)")
    w.add_argument("--quiet", action="store_true", help="no Ray / Tune progress output")
    w.set_defaults(func=_sweep)

    s = sub.add_parser("scene", help="print (or write) an environment's default scene as YAML")
    s.add_argument("env", nargs="?", default=DEFAULT_ENV)
    s.add_argument("--out", help="write it to this file")
    s.set_defaults(func=_scene)

    x = sub.add_parser("export", help="a trained policy as one ONNX graph (normalisation and limits inside)")
    x.add_argument("run", help="a run folder, its model.zip or a checkpoint")
    x.add_argument("--out", required=True, help="the .onnx file to write")
    x.add_argument("--speed-limit", type=float, help="the gripper's speed at most, m/s (clipped in the graph)")
    x.add_argument("--workspace", help="x0,y0,z0,x1,y1,z1 (m): no velocity that leaves this box")
    x.add_argument("--trust-pickle", action="store_true", help=TRUST_HELP)
    x.set_defaults(func=_export)

    d = sub.add_parser("demos", help="demonstrations as a Minari dataset (minari.load_dataset(NAME))")
    d.add_argument("env", metavar="ENV", help="environment id")
    d.add_argument("--policy", default="scripted", help="'scripted', 'pretrained', a run folder or a .onnx")
    d.add_argument("--episodes", type=int, default=20)
    d.add_argument("--out", required=True, help="the dataset id, e.g. heml-gym/tissue-retraction/scripted-v0")
    d.add_argument("--seed", type=int, default=0, help="episode k is reset with seed + k")
    d.add_argument("--root", help="the Minari datasets folder (default: MINARI_DATASETS_PATH or ~/.minari/datasets)")
    d.add_argument("--reference-episodes", type=int, default=5, help="random episodes for Minari's ref_min_score")
    d.add_argument("--action-noise", type=float, default=0.0,
                   help="std of Gaussian noise on the executed velocity commands (the policy's own action is kept in "
                        "infos['expert_action']: demonstrations that show recovery, for behaviour cloning)")
    d.set_defaults(func=_demos)

    o = sub.add_parser("observe", help="record an observation file (.npz) from a simulated scripted retraction")
    o.add_argument("env", metavar="ENV", help="environment id")
    o.add_argument("--out", required=True, help="the .npz file to write")
    o.add_argument("--seed", type=int, default=0, help="the episode's seed, and the noise's and the tracked points' draw")
    o.add_argument("--steps", type=int, default=30, help="env steps (default 30: 3 s)")
    o.add_argument("--points", type=int, default=10, help="tracked points on the upper surface (default 10)")
    o.add_argument("--point-noise", type=float, default=0.0, help="Gaussian noise per coordinate, m")
    o.add_argument("--force-noise", type=float, default=0.0, help="Gaussian noise per force component, N")
    o.add_argument("--young-modulus", type=float, help="the tissue's E, Pa (default: drawn as the scene draws it)")
    o.add_argument("--poisson", type=float, help="the tissue's Poisson ratio (default: the scene's)")
    o.add_argument("--law", help="the tissue's law (a heml_gym.materials class name; default: the scene's)")
    o.add_argument("--env-kwargs", help="JSON gym.make keyword arguments (e.g. a finer mesh)")
    o.add_argument("--depth", help="also record the task camera's depth image, HxW pixels (e.g. 84x84)")
    o.add_argument("--depth-noise", type=float, default=0.0, help="Gaussian noise per depth pixel, m")
    o.add_argument("--no-force", action="store_true", help="no jaw force in the file (no force sensor)")
    o.add_argument("--wrist-reach", type=float, default=None,
                   help="the jaws hold the tissue within this distance (m) of what the scene's jaws take on a free "
                        "wrist (stepped by the calibration's replay; no --depth; a scene with gripper.wrist_reach in "
                        "--env-kwargs has the envs' own wrist, depth included)")
    o.set_defaults(func=_observe)

    c = sub.add_parser("calibrate", help="fit a scene's tissue to an observation file")
    c.add_argument("env", metavar="ENV", help="environment id whose scene is fitted ('-': the observation's)")
    c.add_argument("observation", help="the .npz observation file")
    c.add_argument("--out", required=True, help="folder for fit.json and fit.png (new or empty)")
    c.add_argument("--fit", default="young_modulus,poisson_ratio",
                   help="constants to fit, comma-separated: young_modulus, poisson_ratio, density, damping, "
                        "c01_fraction (MooneyRivlin), b (Demiray)")
    c.add_argument("--law", help="the law to fit (a heml_gym.materials class name; default: the scene's), or "
                                 "'auto': the one that predicts held-out tracked points best")
    c.add_argument("--env-kwargs", help="JSON gym.make keyword arguments of the fitted model (default: the task's "
                                        "calibration model, heml_gym.envs.calibration_models: the lobe on a 7 mm "
                                        "mesh; '{}': the env's own)")
    c.add_argument("--starts", type=int, default=1, help="L-BFGS starts (the scene's values, then random ones)")
    c.add_argument("--jobs", type=int, default=1,
                   help="with --law auto: fit the laws in this many worker processes at once; else with --starts "
                        "N: the starts (each worker about 1.5 GB; the cores shared among them), default 1")
    c.add_argument("--point-scale", type=float, default=None,
                   help="tracked points' residual scale (their noise), m; neither scale given: 1 mm and 0.05 N to "
                        "start, then points and force each weighed by their own residual")
    c.add_argument("--force-scale", type=float, default=None, help="force residual scale (its noise), N")
    c.add_argument("--wrist-reach", type=float, default=None,
                   help="the jaws hold the tissue within this distance (m) of what the scene's jaws take, rigidly, "
                        "on a free wrist (it turns about the jaws' axis); default: the scene's grasp")
    c.add_argument("--regions", default=None,
                   help="fit Young's modulus in each box of an NXxNYxNZ grid over the tissue's rest bounding box "
                        "(e.g. 2x1x1: two halves along x); default: one E for the whole tissue")
    c.add_argument("--use", default=None,
                   help="the observed quantities to fit, comma-separated: points, force, depth (default: all the "
                        "file has, but on the lobe its tracked points alone when it has them: its force carries "
                        "the larger model error)")
    c.add_argument("--no-mesh-correction", action="store_true",
                   help="report the fit on the calibration model as it is (by default the lobe's is corrected for "
                        "its mesh's stiffness against a 5 mm lobe: one replay of that and one more fit)")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")
    c.set_defaults(func=_calibrate)

    b = sub.add_parser("bench", help="run benchmarks (no name: list them by group)")
    b.add_argument("names", nargs="*", help="benchmarks to run, in order (`heml-gym bench` lists them)")
    b.add_argument("--out", help="folder for the results (default: the checkout's docs/, "
                                 "else ./heml-gym-results)")
    b.add_argument("--extra", nargs=argparse.REMAINDER, default=[], help="arguments for the scripts")
    b.set_defaults(func=_bench)

    args = ap.parse_args(argv)
    try:
        return args.func(args)
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError, ValueError, ImportError) as exc:
        # user errors (ConfigError and SpecError are ValueErrors): one line, no traceback
        message = " ".join(str(exc).split())
        print(f"heml-gym {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"heml-gym {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
