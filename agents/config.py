"""Run configurations: YAML files validated before anything trains.

A config names the environment, the algorithm and its hyperparameters, and the
evaluation / checkpoint schedule::

    env:
      id: heml_gym/TissueRetraction-v1
      num_envs: 8
      obs_mode: state
      normalize_observations: true   # VecNormalize statistics saved beside the model
      kwargs:                        # passed to gym.make / gym.make_vec (validated)
        physics: {material: StVenantKirchhoff, integrator: implicit}
        settings: {max_steps: 100}   # the episode length lives here (TaskSettings)
    algorithm:
      name: PPO
      policy: MlpPolicy
      total_timesteps: 300000
      hyperparameters: {n_steps: 128, batch_size: 256}
    evaluation: {every_steps: 20000, episodes: 20}
    checkpoint: {every_steps: 50000}
    seed: 0

Behaviour cloning (``algorithm.name: BC``) learns from demonstrations instead, named in a
``demos`` section (:class:`DemosConfig`, :mod:`heml_gym.agents.bc`).

A config may start from another: ``base: quick.yaml`` (a path relative to the config's own
folder) reads that config first and lays this one's keys over it (nested mappings merge,
anything else replaces), so an ablation names only what it changes::

    base: quick.yaml
    env:
      kwargs:
        weights: {lift: 5.0}

Unknown keys, wrong types and missing files raise :class:`ConfigError` naming the key;
``env.kwargs`` is checked against the environment's arguments and its scene, physics,
settings and weights against their fields, and ``algorithm.hyperparameters`` against the
algorithm's constructor, all before anything is written.
"""

from __future__ import annotations

import inspect
import math
import types
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, get_type_hints

import yaml

from heml_gym.envs.retraction_env import OBS_MODES

from .algorithms import ALGORITHMS, BACKENDS, algorithm_class


class ConfigError(ValueError):
    """An invalid run configuration; the message names the offending key or file."""


@dataclass
class EnvConfig:
    id: str = "heml_gym/TissueRetraction-v1"
    num_envs: int = 8
    obs_mode: str = "state"
    normalize_observations: bool = True  # running mean/std of observations (SB3 VecNormalize)
    kwargs: dict = field(default_factory=dict)  # gym.make / gym.make_vec keyword arguments


@dataclass
class AlgorithmConfig:
    name: str = "PPO"
    policy: str = "MlpPolicy"
    total_timesteps: int = 100_000
    hyperparameters: dict = field(default_factory=dict)


@dataclass
class EvaluationConfig:
    """Every ``every_steps`` env steps, ``episodes`` fresh episodes with the deterministic
    policy. ``stop_at_success`` (a fraction in (0, 1]; None: never) ends training early once
    ``stop_after`` evaluations in a row reach it; ``algorithm.total_timesteps`` stays the cap."""

    every_steps: int = 20_000
    episodes: int = 20
    stop_at_success: float | None = None
    stop_after: int = 2


@dataclass
class CheckpointConfig:
    every_steps: int = 50_000


@dataclass
class ConstraintConfig:
    """A damage budget (strain x s per episode: the summed ``info["cost"]``); None: no
    constraint. See :mod:`heml_gym.agents.constraint`."""

    budget: float | None = None
    multiplier_lr: float = 0.05
    multiplier_init: float = 0.0


@dataclass
class DemosConfig:
    """The demonstrations of a BC run (:mod:`heml_gym.agents.bc`): the local Minari dataset
    ``dataset``, recorded first (``policy`` for ``episodes`` episodes seeded from ``seed``)
    when it is not in ``root`` (None: ``MINARI_DATASETS_PATH``, else ``~/.minari/datasets``),
    its velocity commands executed with Gaussian noise of standard deviation ``action_noise``
    (:mod:`heml_gym.agents.demos`)."""

    dataset: str | None = None
    policy: str = "scripted"
    episodes: int = 100
    seed: int = 0
    root: str | None = None
    action_noise: float = 0.0


@dataclass
class RunConfig:
    env: EnvConfig = field(default_factory=EnvConfig)
    algorithm: AlgorithmConfig = field(default_factory=AlgorithmConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    constraint: ConstraintConfig = field(default_factory=ConstraintConfig)
    demos: DemosConfig = field(default_factory=DemosConfig)
    seed: int = 0
    name: str = "run"

    def to_dict(self) -> dict:
        return _to_dict(self)


def _to_dict(obj) -> dict:
    return {f.name: (_to_dict(getattr(obj, f.name)) if is_dataclass(getattr(obj, f.name))
                     else getattr(obj, f.name)) for f in fields(obj)}


def _build(cls, data: Any, path: str):
    if not isinstance(data, dict):
        raise ConfigError(f"config key '{path or '<top>'}' must be a mapping, got {type(data).__name__}")
    hints = get_type_hints(cls)
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        where = f"{path}." if path else ""
        hint = ""
        if f"{where}{unknown[0]}" == "env.max_episode_steps":
            hint = "; the episode length is env.kwargs.settings.max_steps"
        raise ConfigError(f"unknown config key '{where}{unknown[0]}' (known: {', '.join(sorted(known))}){hint}")
    kwargs = {}
    for name, value in data.items():
        key = f"{path}.{name}" if path else name
        expected = hints[name]
        if is_dataclass(expected):
            kwargs[name] = _build(expected, value, key)
            continue
        if isinstance(expected, types.UnionType):  # "X | None": None, or an X
            if value is None:
                kwargs[name] = None
                continue
            expected = next(t for t in expected.__args__ if t is not type(None))
        if expected is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if expected is int and isinstance(value, float) and value.is_integer():
            value = int(value)  # YAML writes 1e5 as a float
        if expected is dict and value is None:
            value = {}
        if not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
            hint = ""
            if expected is float and isinstance(value, str):
                try:
                    float(value)
                    hint = " (YAML reads 1e-3 as text: write 1.0e-3 or 0.001)"
                except ValueError:
                    pass
            raise ConfigError(f"config key '{key}' must be {expected.__name__}{hint}, "
                              f"got {type(value).__name__} ({value!r})")
        kwargs[name] = value
    return cls(**kwargs)


def validate(cfg: RunConfig) -> RunConfig:
    """Check values beyond types; raises :class:`ConfigError` naming the key."""
    if cfg.algorithm.name not in ALGORITHMS:
        raise ConfigError(f"config key 'algorithm.name' must be one of {tuple(ALGORITHMS)}, got {cfg.algorithm.name!r}")
    c = cfg.constraint
    if c.budget is not None:
        if BACKENDS[cfg.algorithm.name] != "sb3":
            raise ConfigError(f"config key 'constraint.budget': constrained training runs on PPO or SAC, "
                              f"not {cfg.algorithm.name}")
        for key, value, low in (("budget", c.budget, 0.0), ("multiplier_lr", c.multiplier_lr, None),
                                ("multiplier_init", c.multiplier_init, 0.0)):
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and (
                value >= low if low is not None else value > 0)
            if not ok:
                raise ConfigError(f"config key 'constraint.{key}' must be a finite number "
                                  f"{'>= 0' if low is not None else '> 0'}, got {value!r}")
    _check_demos(cfg)
    stop = cfg.evaluation.stop_at_success
    if stop is not None and not (isinstance(stop, (int, float)) and not isinstance(stop, bool) and 0 < stop <= 1):
        raise ConfigError(f"config key 'evaluation.stop_at_success' must be a success rate in (0, 1] or null, "
                          f"got {stop!r}")
    if cfg.env.obs_mode not in OBS_MODES:
        raise ConfigError(f"config key 'env.obs_mode' must be one of {OBS_MODES}, got {cfg.env.obs_mode!r}")
    for key, value in [("env.num_envs", cfg.env.num_envs),
                       ("algorithm.total_timesteps", cfg.algorithm.total_timesteps),
                       ("evaluation.every_steps", cfg.evaluation.every_steps),
                       ("evaluation.episodes", cfg.evaluation.episodes),
                       ("evaluation.stop_after", cfg.evaluation.stop_after),
                       ("checkpoint.every_steps", cfg.checkpoint.every_steps)]:
        if value < 1:
            raise ConfigError(f"config key '{key}' must be >= 1, got {value}")
    import gymnasium as gym

    import heml_gym.envs  # noqa: F401  (registers the ids)

    from heml_gym.envs import SpecError, check_env_kwargs, unknown_env_message

    if cfg.env.id not in gym.registry:
        raise ConfigError(f"config key 'env.id': {unknown_env_message(cfg.env.id)}")

    try:
        check_env_kwargs(cfg.env.id, cfg.env.kwargs, "env.kwargs")
    except SpecError as exc:
        raise ConfigError(f"config key {exc}") from None
    _check_hyperparameters(cfg)
    return cfg


def _check_demos(cfg: RunConfig) -> None:
    """A BC run names its demonstrations and reads state observations; no other run has demos."""
    d = cfg.demos
    if BACKENDS[cfg.algorithm.name] != "bc":
        if d != DemosConfig():
            raise ConfigError(f"config key 'demos': only BC runs read demonstrations, not {cfg.algorithm.name}")
        return
    if not d.dataset or not d.dataset.strip():
        raise ConfigError("config key 'demos.dataset': name the Minari dataset to learn from (e.g. "
                          "heml-gym/tissue-retraction-scripted-100-v0; recorded first when it is not there)")
    from .dataset_ids import check_dataset_id, check_root

    try:
        check_dataset_id(d.dataset, "config key 'demos.dataset'")
        if d.root is not None:
            check_root(d.root, "config key 'demos.root'")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    if d.episodes < 1:
        raise ConfigError(f"config key 'demos.episodes' must be >= 1, got {d.episodes}")
    if d.seed < 0:
        raise ConfigError(f"config key 'demos.seed' must be >= 0 (episode seeds), got {d.seed}")
    if not (math.isfinite(d.action_noise) and d.action_noise >= 0):
        raise ConfigError(f"config key 'demos.action_noise' must be a finite number >= 0, got {d.action_noise}")
    if cfg.env.obs_mode != "state":
        raise ConfigError(f"config key 'env.obs_mode': BC reads the state observation, got {cfg.env.obs_mode!r}")
    from .bc_hyperparameters import BehaviourCloning

    try:
        BehaviourCloning(**{k: v for k, v in cfg.algorithm.hyperparameters.items()
                            if k in inspect.signature(BehaviourCloning).parameters})
    except ValueError as exc:
        raise ConfigError(f"config key 'algorithm.hyperparameters.{exc}'") from None


#: hyperparameters of the RLlib path that are not PPOConfig.training arguments
RLLIB_OPTIONS = ("num_env_runners", "num_cpus_per_env_runner", "fcnet_hiddens")


def import_rllib():
    """``(ray, PPOConfig)``, or an ImportError that says how to install them."""
    try:
        import ray
        from ray.rllib.algorithms.ppo import PPOConfig
    except ImportError:
        raise ImportError("RLlibPPO runs on Ray RLlib: pip install -e '.[ray]'") from None
    return ray, PPOConfig


def check_rllib_hyperparameters(cfg: RunConfig) -> None:
    """Every hyperparameter is an RLlib option or a ``PPOConfig.training`` argument."""
    _, PPOConfig = import_rllib()
    accepted = set(RLLIB_OPTIONS)
    for klass in PPOConfig.__mro__:  # PPOConfig.training passes **kwargs on to its bases'
        if "training" in vars(klass):
            accepted |= set(inspect.signature(vars(klass)["training"]).parameters) - {"self", "kwargs"}
    for key, value in cfg.algorithm.hyperparameters.items():
        if key not in accepted:
            raise ConfigError(f"config key 'algorithm.hyperparameters.{key}': not an RLlibPPO argument "
                              f"(known: {', '.join(sorted(accepted))})")
        if key in ("num_env_runners",) and (not isinstance(value, int) or isinstance(value, bool) or value < 0):
            raise ConfigError(f"config key 'algorithm.hyperparameters.{key}' must be an integer >= 0, got {value!r}")


def _check_hyperparameters(cfg: RunConfig) -> None:
    """Every hyperparameter must be an argument of the algorithm's constructor."""
    import inspect

    if BACKENDS[cfg.algorithm.name] == "rllib":
        check_rllib_hyperparameters(cfg)
        return
    cls = algorithm_class(cfg.algorithm.name)
    accepted = set(inspect.signature(cls.__init__).parameters) - {"self", "policy", "env"}
    for key in cfg.algorithm.hyperparameters:
        if key not in accepted:
            raise ConfigError(f"config key 'algorithm.hyperparameters.{key}': not a {cfg.algorithm.name} argument "
                              f"(known: {', '.join(sorted(accepted))})")
    if BACKENDS[cfg.algorithm.name] == "sb3":
        from .algorithms import sb3_hyperparameters

        try:
            sb3_hyperparameters(cfg.algorithm.name, cfg.algorithm.hyperparameters)
        except ValueError as exc:
            raise ConfigError(f"config key 'algorithm.hyperparameters.{exc}'") from None


def load_config(path: str | Path, overrides: dict | None = None) -> RunConfig:
    """Read, type-check and validate a YAML run config; ``overrides`` (nested dict) win."""
    path = Path(path)
    data = _read_with_bases(path, ())
    if overrides:
        data = _merge(data, overrides)
    data.setdefault("name", path.stem)
    return validate(_build(RunConfig, data, ""))


def _read_with_bases(path: Path, chain: tuple) -> dict:
    """The mapping in ``path`` laid over its ``base`` (and that one's, ...); ``chain``: the
    configs that include this one, to refuse a cycle."""
    data = _read_mapping(path)
    if "base" not in data:
        return data
    base = data.pop("base")
    if not isinstance(base, str) or not base.strip():
        raise ConfigError(f"config key 'base' in {path}: must be the path of another run config (relative to "
                          f"{path.parent}), got {base!r}")
    base_path = (path.parent / Path(base.strip()).expanduser()).resolve()
    if not base_path.is_file():
        raise ConfigError(f"config key 'base' in {path}: config file not found: {base_path}")
    if base_path in chain or base_path == path.resolve():
        raise ConfigError(f"config key 'base' in {path}: {base_path} includes itself "
                          f"({' -> '.join(str(p) for p in (*chain, path.resolve(), base_path))})")
    parent = _read_with_bases(base_path, (*chain, path.resolve()))
    parent.pop("name", None)  # a config's name is its own (by default its file name)
    return _merge(parent, data)


def _read_mapping(path: Path) -> dict:
    if path.is_dir():
        raise ConfigError(f"config file {path} is a directory, not a YAML file")
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        at = f" (line {where.line + 1})" if where is not None else ""
        raise ConfigError(f"config file {path} is not valid YAML{at}: {getattr(exc, 'problem', exc)}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"config file {path} is not a text file") from None
    if data is None:
        raise ConfigError(f"config file {path} is empty: give at least env and algorithm (see configs/quick.yaml)")
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping of keys (env, algorithm, evaluation, "
                          f"checkpoint, seed), got a {type(data).__name__}")
    return data


def config_from_dict(data: dict) -> RunConfig:
    return validate(_build(RunConfig, data, ""))


def _merge(base: dict, extra: dict) -> dict:
    out = dict(base)
    for k, v in extra.items():
        out[k] = _merge(out.get(k, {}), v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out
