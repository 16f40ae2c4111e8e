"""Training and evaluation with Stable-Baselines3 on the batched retraction environments.

A run lives in one folder: ``config.yaml`` (the resolved config), ``checkpoints/``,
``tb/`` (TensorBoard), ``evaluations.json`` (success rate, exposure, strain and the
wall time so far, in seconds including evaluation, at each evaluation),
``model.zip`` (the final policy) and, when ``env.normalize_observations`` is on,
``vecnormalize.json`` (the observation statistics the policy was trained with; each
checkpoint has its own), so it can be evaluated, resumed or reproduced from the folder
alone. Loading a run executes nothing from it (:mod:`heml_gym.agents.run_files`).
"""

from __future__ import annotations

import json
import re
import shutil
import time
from pathlib import Path

import gymnasium as gym
import torch
import yaml
from stable_baselines3.common.callbacks import BaseCallback, CallbackList, CheckpointCallback
from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

from heml_gym.envs import TISSUE_RETRACTION, episode_steps  # (and registers the environments)

from .algorithms import ALGORITHMS, BACKENDS, algorithm_class, sb3_hyperparameters
from .config import ConfigError, RunConfig, load_config
from .evaluation import evaluate_policy, wilson_interval  # noqa: F401  (wilson_interval: for callers)
from .run_files import (NORMALIZER_FILE, UntrustedPickle, load_model, load_normalizer, model_record,  # noqa: F401
                        normalizer_path, save_normalizer)
from .vec_env import RetractionSb3VecEnv


# The periodic evaluations reset episodes with seeds 10,000, 10,001, ... (evaluate_policy's
# default); a run stopped early is judged on episodes from this seed on, which they never saw.
FRESH_EPISODES_SEED = 20_000


def make_vec_env(cfg: RunConfig, num_envs: int | None = None) -> VecMonitor:
    """The SB3 VecEnv of a config: one batched Numba call for all envs, with episode stats."""
    vector_env = gym.make_vec(cfg.env.id, num_envs=num_envs or cfg.env.num_envs,
                              vectorization_mode="vector_entry_point", obs_mode=cfg.env.obs_mode,
                              max_episode_steps=episode_steps(cfg.env.kwargs), **cfg.env.kwargs)
    return VecMonitor(RetractionSb3VecEnv(vector_env.unwrapped))


def make_env(cfg: RunConfig | None, env_id: str | None = None, **extra):
    """One env of a config (its id, obs mode and ``env.kwargs``), or of ``env_id`` with
    the defaults when there is no config."""
    if cfg is None:
        return gym.make(env_id or TISSUE_RETRACTION, max_episode_steps=episode_steps(extra), **extra)
    kwargs = {**cfg.env.kwargs, **extra}
    return gym.make(env_id or cfg.env.id, obs_mode=cfg.env.obs_mode, max_episode_steps=episode_steps(kwargs), **kwargs)


def model_policy(model, normalizer: VecNormalize | None = None):
    """An ``obs -> action`` callable from an SB3 model (deterministic); ``normalizer``
    (the run's VecNormalize statistics) maps raw observations to what the model saw."""
    if normalizer is None:
        return lambda obs: model.predict(obs, deterministic=True)[0]
    return lambda obs: model.predict(normalizer.normalize_obs(obs), deterministic=True)[0]


class Checkpoints(CheckpointCallback):
    """SB3's checkpoints, with the observation statistics as JSON beside each
    (:func:`~heml_gym.agents.run_files.save_normalizer`), never a pickle."""

    def __init__(self, save_freq: int, save_path: str):
        super().__init__(save_freq=save_freq, save_path=save_path, name_prefix="model", save_vecnormalize=False)

    def _on_step(self) -> bool:
        if self.n_calls % self.save_freq == 0:
            model_path = Path(self._checkpoint_path(extension="zip"))
            self.model.save(model_path)
            normalizer = self.model.get_vec_normalize_env()
            if normalizer is not None:
                save_normalizer(normalizer, normalizer_path(model_path))
        return True


class SuccessEvalCallback(BaseCallback):
    """Every ``every_steps`` env steps: evaluate the policy, log and store the success rate.
    With ``evaluation.stop_at_success`` set, training stops once ``evaluation.stop_after``
    evaluations in a row reach it (:attr:`stopped_early` is then True)."""

    def __init__(self, cfg: RunConfig, path: Path):
        super().__init__()
        self.cfg, self.path = cfg, path
        self.history = json.loads(path.read_text()) if path.exists() else []
        self._next = (self.history[-1]["timesteps"] if self.history else 0) + cfg.evaluation.every_steps
        # wall time (s) of the run so far, continued across resumes
        self._wall_before = self.history[-1].get("wall_s", 0.0) if self.history else 0.0
        self._started = time.perf_counter()
        self.stopped_early = False

    def _on_training_start(self) -> None:
        self._started = time.perf_counter()

    def _on_step(self) -> bool:
        if self.num_timesteps >= self._next:
            self._next += self.cfg.evaluation.every_steps
            self.evaluate()
            if self.learned():
                self.stopped_early = True
                return False
        return True

    def learned(self) -> bool:
        """Whether the last ``stop_after`` evaluations all reached ``stop_at_success``."""
        e = self.cfg.evaluation
        recent = self.history[-e.stop_after:]
        return (e.stop_at_success is not None and len(recent) == e.stop_after
                and all(r["success_rate"] >= e.stop_at_success for r in recent))

    def evaluate(self):
        policy = model_policy(self.model, self.model.get_vec_normalize_env())
        result = evaluate_policy(policy, self.cfg.env.id, self.cfg.evaluation.episodes,
                                 obs_mode=self.cfg.env.obs_mode, env_kwargs=self.cfg.env.kwargs)
        result["timesteps"] = int(self.num_timesteps)
        result["wall_s"] = self._wall_before + time.perf_counter() - self._started
        self.history.append(result)
        self.path.write_text(json.dumps(self.history, indent=1))
        self.logger.record("eval/success_rate", result["success_rate"])
        for key in ("mean_final_exposure", "mean_final_goal_distance"):
            if key in result:
                self.logger.record(f"eval/{key}", result[key])
        self.logger.record("eval/mean_damage", result["mean_damage"])
        return result


def _resumed_multiplier(resume, cfg: RunConfig) -> float:
    """The Lagrange multiplier to start from: the resumed run's last (its constraint.json),
    else the config's ``constraint.multiplier_init``."""
    if resume is not None:
        record = _run_folder(Path(resume)) / "constraint.json"
        if record.is_file():
            history = json.loads(record.read_text()).get("history", [])
            if history:
                return float(history[-1]["multiplier"])
    return float(cfg.constraint.multiplier_init)


def run_directory(cfg: RunConfig, root: str | Path = "runs") -> Path:
    return Path(root) / f"{cfg.name}-seed{cfg.seed}"


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The checkpoint of the run with the most steps, or None."""
    best, best_steps = None, -1
    for p in (run_dir / "checkpoints").glob("*.zip"):
        m = re.search(r"_(\d+)_steps\.zip$", p.name)
        if m and int(m.group(1)) > best_steps:
            best, best_steps = p, int(m.group(1))
    return best


def _run_folder(checkpoint: Path) -> Path:
    """The run folder of a model file: ``RUN/model.zip`` or ``RUN/checkpoints/model_N_steps.zip``."""
    return checkpoint.parent.parent if checkpoint.parent.name == "checkpoints" else checkpoint.parent


def _checkpoint_config(checkpoint: Path) -> RunConfig | None:
    """The run config beside a checkpoint (its run folder's ``config.yaml``), if any."""
    path = _run_folder(checkpoint) / "config.yaml"
    return load_config(path) if path.is_file() else None


def check_resume(cfg: RunConfig, resume: Path) -> None:
    """Refuse to resume ``resume`` under ``cfg`` when they disagree on what a policy and
    its observation statistics depend on: environment, observation mode, algorithm,
    normalisation. Raises :class:`ConfigError` naming the difference."""
    if resume.is_dir():
        raise ConfigError(f"--resume {resume} is a directory: give a checkpoint .zip (e.g. {resume}/model.zip)")
    if not resume.is_file():
        raise ConfigError(f"--resume: checkpoint not found: {resume}")
    try:
        previous = _checkpoint_config(resume)
    except ConfigError as exc:
        raise ConfigError(f"--resume: the run config beside {resume} is invalid: {exc}") from None
    if previous is not None:
        for key, old, new in (("env.id", previous.env.id, cfg.env.id),
                              ("env.obs_mode", previous.env.obs_mode, cfg.env.obs_mode),
                              ("algorithm.name", previous.algorithm.name, cfg.algorithm.name),
                              ("env.normalize_observations", previous.env.normalize_observations,
                               cfg.env.normalize_observations)):
            if old != new:
                raise ConfigError(f"--resume: {resume} was trained with {key} = {old!r}, this config has {new!r}")
    try:
        model_record(resume)  # (plain JSON; the weights are checked when they are loaded)
    except ConfigError as exc:
        raise ConfigError(f"--resume: {resume} is not a readable {cfg.algorithm.name} checkpoint ({exc})") from None


def train(cfg: RunConfig, run_dir: str | Path | None = None, resume: str | Path | None = None,
          progress_bar: bool = True, address: str | None = None, trust_pickle: bool = False) -> dict:
    """Train per ``cfg`` into ``run_dir``; ``resume`` continues from a checkpoint's step count.

    Everything that can be checked is checked before the run folder is written
    (``ConfigError`` names the problem): the resume target and its compatibility, the
    environment, the algorithm's hyperparameters (by building the model), the
    observation statistics. A start that fails leaves no new folder behind.
    ``address``: the Ray cluster of an ``RLlibPPO`` run (:mod:`heml_gym.agents.rllib_backend`).
    ``trust_pickle``: resume from a run folder whose files are pickles (statistics
    written before 2026-11-26, RLlib checkpoints): only for folders you trust.
    """
    run_dir = Path(run_dir) if run_dir is not None else run_directory(cfg)
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(f"run folder {run_dir} exists and is not a directory")
    if BACKENDS[cfg.algorithm.name] == "rllib":
        from .rllib_backend import train_rllib

        return train_rllib(cfg, run_dir, resume=resume, address=address, progress_bar=progress_bar,
                           trust_pickle=trust_pickle)
    if address is not None:
        raise ConfigError("--address is for RLlibPPO runs; spread SB3 runs over a cluster with heml-gym sweep")
    if BACKENDS[cfg.algorithm.name] == "bc":
        if resume is not None:
            raise ConfigError("--resume: a BC run is fitted in one go (train it again)")
        from .bc import train_bc

        return train_bc(cfg, run_dir, progress_bar=progress_bar)
    if resume is not None:
        resume = Path(resume)
        check_resume(cfg, resume)
    # the policies are small MLPs: one PyTorch thread is as fast as two (measured: a SAC
    # gradient step 17-20 ms on one thread, 17-31 ms on two) and leaves the cores to the
    # batched physics, which has its own Numba threads
    torch.set_num_threads(1)
    env = make_vec_env(cfg)
    env.seed(cfg.seed)
    penalty = None
    if cfg.constraint.budget is not None:  # reward - lambda cost (heml_gym.agents.constraint)
        from .constraint import CostPenalty

        env = penalty = CostPenalty(env, _resumed_multiplier(resume, cfg))
    algo = algorithm_class(cfg.algorithm.name)
    if cfg.env.normalize_observations:
        if resume is not None:  # continue with the statistics the checkpoint was trained with
            stats = normalizer_path(resume)
            try:
                normalizer = load_normalizer(stats, env, trust_pickle=trust_pickle)
            except FileNotFoundError:
                raise ConfigError(f"--resume: observation statistics of {resume} not found: {stats}") from None
            env = normalizer
            env.training = True
        else:
            env = VecNormalize(env, norm_obs=True, norm_reward=False)
    created = not run_dir.exists()
    tb = str(run_dir / "tb")
    try:
        if resume is not None:
            try:
                model = load_model(resume, cfg, env, tensorboard_log=tb)
            except ConfigError as exc:
                raise ConfigError(f"--resume: {exc}") from None
        else:
            try:
                model = algo(cfg.algorithm.policy, env, seed=cfg.seed, device="cpu", verbose=0, tensorboard_log=tb,
                             **sb3_hyperparameters(cfg.algorithm.name, cfg.algorithm.hyperparameters))
            except (AssertionError, ValueError, TypeError) as exc:
                raise ConfigError(f"config key 'algorithm.hyperparameters': {cfg.algorithm.name} rejects them: "
                                  f"{exc or type(exc).__name__}") from None
        (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
        (run_dir / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    except BaseException:
        env.close()
        if created and run_dir.exists():
            shutil.rmtree(run_dir)
        raise
    evaluator = SuccessEvalCallback(cfg, run_dir / "evaluations.json")
    callbacks = [Checkpoints(max(1, cfg.checkpoint.every_steps // cfg.env.num_envs), str(run_dir / "checkpoints")),
                 evaluator]
    if penalty is not None:
        from .constraint import MultiplierUpdate

        callbacks.append(MultiplierUpdate(penalty, cfg.constraint.budget, cfg.constraint.multiplier_lr,
                                          run_dir / "constraint.json"))
    remaining = cfg.algorithm.total_timesteps - (model.num_timesteps if resume is not None else 0)
    if remaining > 0:
        model.learn(total_timesteps=remaining, callback=CallbackList(callbacks),
                    reset_num_timesteps=resume is None, progress_bar=progress_bar,
                    tb_log_name=cfg.algorithm.name)
    model.save(run_dir / "model.zip")
    if cfg.env.normalize_observations:
        save_normalizer(env, run_dir / NORMALIZER_FILE)
    if evaluator.stopped_early:  # judged on episodes the stopping rule never saw
        final = evaluate_policy(model_policy(model, model.get_vec_normalize_env()), cfg.env.id,
                                cfg.evaluation.episodes, seed=FRESH_EPISODES_SEED, obs_mode=cfg.env.obs_mode,
                                env_kwargs=cfg.env.kwargs)
        final["timesteps"] = int(model.num_timesteps)
        final["seed"] = FRESH_EPISODES_SEED
    elif not evaluator.history or evaluator.history[-1]["timesteps"] != model.num_timesteps:
        final = evaluator.evaluate()
    else:
        final = evaluator.history[-1]
    env.close()
    return {"run_dir": str(run_dir), "timesteps": int(model.num_timesteps), "final_evaluation": final,
            "stopped_early": evaluator.stopped_early}


def load_policy(path: str | Path, trust_pickle: bool = False):
    """``(policy, model, cfg)`` from a ``.zip`` or a run folder: ``policy`` maps a raw
    observation to an action, through the run's observation statistics when it has them.

    Nothing in the folder is executed: the model is rebuilt from the run's
    ``config.yaml`` and only its weights are read, the statistics from JSON
    (:mod:`heml_gym.agents.run_files`). A model without a run config beside it, a run
    with only the former pickled statistics and an RLlib checkpoint (RLlib pickles its
    modules) are refused with :class:`~heml_gym.agents.run_files.UntrustedPickle` unless
    ``trust_pickle``: for folders you trust."""
    from .bc import is_bc_run, load_bc_policy
    from .rllib_backend import is_rllib_run, load_rllib_policy

    path = Path(path)
    if is_bc_run(path):
        cfg = load_config(path / "config.yaml")
        return load_bc_policy(path, cfg), None, cfg
    if is_rllib_run(path):
        if not trust_pickle:
            raise UntrustedPickle(f"{path} is an RLlib checkpoint, which RLlib reads by unpickling (code in it would "
                                  "run): pass --trust-pickle if you trust where this run folder came from")
        checkpoint = path / "rllib_checkpoint" if (path / "rllib_checkpoint").is_dir() else path
        run_folder = path if (path / "rllib_checkpoint").is_dir() else (
            path.parent.parent if path.parent.name == "checkpoints" else path.parent)
        cfg_path = run_folder / "config.yaml"
        cfg = load_config(cfg_path) if cfg_path.is_file() else None
        return load_rllib_policy(checkpoint), None, cfg
    model_path, cfg = _model_file(path)
    if cfg is None:
        if not trust_pickle:
            raise UntrustedPickle(f"{model_path} has no run config (config.yaml) beside it to rebuild the model from, "
                                  "and loading it whole would unpickle it: pass --trust-pickle if you trust it")
        return model_policy(algorithm_class(_algorithm_of(model_path)).load(model_path, device="cpu")), None, None
    model, normalizer = load_run(model_path, cfg, trust_pickle)
    return model_policy(model, normalizer), model, cfg


def load_run(model_path: Path, cfg: RunConfig, trust_pickle: bool = False):
    """``(model, normalizer)`` of an SB3 model file with its run config: the model rebuilt
    from the config with its weights, the observation statistics (None when the run did not
    normalise observations)."""
    model = load_model(model_path, cfg, make_env(cfg))
    if not cfg.env.normalize_observations:
        return model, None
    stats = normalizer_path(model_path)
    try:
        return model, load_normalizer(stats, trust_pickle=trust_pickle)
    except FileNotFoundError:
        raise FileNotFoundError(f"{model_path} was trained on normalised observations, but their "
                                f"statistics are missing: {stats}") from None


def model_file(path: str | Path) -> tuple[Path, RunConfig | None]:
    """The model file of a run folder, checkpoint or ``.zip``, and its run config (None
    when there is none beside it)."""
    return _model_file(Path(path))


def _model_file(path: Path) -> tuple[Path, RunConfig | None]:
    """``(model file, cfg or None)`` of a ``.zip`` or a run folder (its ``model.zip`` or
    latest checkpoint)."""
    if path.is_dir():
        candidate = path / "model.zip"
        if not candidate.is_file():
            candidate = latest_checkpoint(path)
        if candidate is None:
            raise FileNotFoundError(f"no model.zip or checkpoint in run folder {path}")
        cfg_path = path / "config.yaml"
        return candidate, load_config(cfg_path) if cfg_path.is_file() else None
    if not path.is_file():
        raise FileNotFoundError(f"model file or run folder not found: {path}")
    model_record(path)  # a zip of SB3's (else: not a PPO or SAC model)
    return path, _checkpoint_config(path)


def _algorithm_of(path: Path) -> str:
    """The SB3 algorithm of a model file (loads it whole: trusted files only)."""
    for name in (n for n in ALGORITHMS if BACKENDS[n] == "sb3"):
        try:
            algorithm_class(name).load(path, device="cpu")
            return name
        except Exception:  # noqa: BLE001 - try the next algorithm
            continue
    raise ValueError(f"{path} is not a PPO or SAC model")
