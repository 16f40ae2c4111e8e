"""A run folder's model and observation statistics, read without executing code from them.

SB3 saves a model as a zip whose ``data`` entry holds some objects as base64 cloudpickle
(the policy class, the spaces, the schedules) and whose ``*.pth`` entries hold the
weights; ``VecNormalize.save`` pickles the whole wrapper. Unpickling a file runs
whatever code its author put in it, so opening a run folder someone shared must not
unpickle anything. Here:

* observation statistics are written as JSON (:func:`save_normalizer`: the running mean,
  variance and count of each normalised observation key, the clip and epsilon) beside
  the model (``vecnormalize.json``) and every checkpoint
  (``model_vecnormalize_<N>_steps.json``), and read back into a frozen or a training
  ``VecNormalize`` (:func:`load_normalizer`);
* a model is rebuilt from the run's ``config.yaml`` (algorithm, policy, hyperparameters,
  environment) and only its weights are read from the zip, by ``torch.load(...,
  weights_only=True)`` (:func:`load_model`); the step count comes from the zip's plain
  JSON.

Run folders written before 2026-11-26 hold ``vecnormalize.pkl``: they are refused with a
one-line error, unless the caller trusts the folder (``trust_pickle``, the CLI's
``--trust-pickle``), which reads the pickle once and writes the JSON beside it.
"""

from __future__ import annotations

import json
import pickle
import re
import zipfile
from pathlib import Path

import numpy as np
from stable_baselines3.common.save_util import load_from_zip_file, recursive_setattr
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from .algorithms import algorithm_class
from .config import ConfigError, RunConfig

NORMALIZER_FILE = "vecnormalize.json"
PICKLED_NORMALIZER_FILE = "vecnormalize.pkl"  # written by runs before 2026-11-26
FORMAT = "heml-gym observation statistics 1"


class UntrustedPickle(ConfigError):
    """A run file that only a pickle holds (refused unless the folder is trusted)."""


# ------------------------------------------------------------------ statistics
def normalizer_path(model_path: Path) -> Path:
    """Where the observation statistics of a model file are: a checkpoint's own
    ``model_vecnormalize_<N>_steps.json``, else ``vecnormalize.json`` beside the model."""
    m = re.fullmatch(r"(.*)_(\d+)_steps\.zip", model_path.name)
    if m:
        return model_path.with_name(f"{m.group(1)}_vecnormalize_{m.group(2)}_steps.json")
    return model_path.with_name(NORMALIZER_FILE)


def save_normalizer(normalizer: VecNormalize, path: Path) -> Path:
    """Write ``normalizer``'s observation statistics to ``path`` as JSON."""
    rms = normalizer.obs_rms
    keys = None if not isinstance(rms, dict) else sorted(rms)
    entries = {"": rms} if keys is None else rms
    data = {"format": FORMAT, "keys": keys, "clip_obs": float(normalizer.clip_obs),
            "epsilon": float(normalizer.epsilon),
            "stats": {k: {"mean": np.asarray(r.mean, dtype=np.float64).tolist(),
                          "var": np.asarray(r.var, dtype=np.float64).tolist(), "count": float(r.count)}
                      for k, r in entries.items()}}
    Path(path).write_text(json.dumps(data))
    return Path(path)


def _read_stats(path: Path) -> dict:
    try:
        data = json.loads(Path(path).read_text())
        if data.get("format") != FORMAT:
            raise ValueError(f"format {data.get('format')!r}, expected {FORMAT!r}")
        stats = {}
        for key, s in data["stats"].items():
            mean, var = np.asarray(s["mean"], dtype=np.float64), np.asarray(s["var"], dtype=np.float64)
            count = float(s["count"])
            if mean.shape != var.shape or not (np.all(np.isfinite(mean)) and np.all(var >= 0) and count > 0):
                raise ValueError(f"statistics of {key or 'the observation'} are not finite means and variances")
            stats[key] = (mean, var, count)
        keys = data["keys"]
        if (keys is None) != (list(stats) == [""]) or (keys is not None and sorted(stats) != sorted(keys)):
            raise ValueError("keys do not match the statistics")
        return {"keys": keys, "clip_obs": float(data["clip_obs"]), "epsilon": float(data["epsilon"]),
                "stats": stats}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"observation statistics {path} cannot be read ({exc})") from None


def load_normalizer(path: Path, venv: VecEnv | None = None, trust_pickle: bool = False) -> VecNormalize:
    """The observation statistics at ``path`` (:func:`normalizer_path`'s JSON) as a
    ``VecNormalize`` around ``venv`` (None: a stand-in of the statistics' shapes, for
    ``normalize_obs`` only); frozen (``training = False``). A folder that has only the
    former pickle is refused (:class:`UntrustedPickle`) unless ``trust_pickle``: then the
    pickle is read and its JSON written beside it."""
    path = Path(path)
    if not path.is_file():
        pickled = path.with_suffix(".pkl")
        if pickled.is_file():
            if not trust_pickle:
                raise UntrustedPickle(
                    f"{pickled} is a pickle (runs before 2026-11-26), and reading it would run any code it holds: "
                    "if you trust where this run folder came from, pass --trust-pickle once (it writes "
                    f"{path.name} beside it)")
            save_normalizer(_unpickle_normalizer(pickled), path)
        else:
            raise FileNotFoundError(f"observation statistics not found: {path}")
    data = _read_stats(path)
    if venv is None:
        venv = _StatsVecEnv(data)
    try:
        normalizer = VecNormalize(venv, training=False, norm_obs=True, norm_reward=False, clip_obs=data["clip_obs"],
                                  epsilon=data["epsilon"], norm_obs_keys=data["keys"])
    except (KeyError, ValueError, AssertionError) as exc:
        raise ConfigError(f"observation statistics {path} do not fit this environment's observations "
                          f"({type(exc).__name__}: {exc})") from None
    for key, (mean, var, count) in data["stats"].items():
        rms = normalizer.obs_rms if key == "" else normalizer.obs_rms[key]
        if rms.mean.shape != mean.shape:
            raise ConfigError(f"observation statistics {path} are of observations shaped {mean.shape}, this "
                              f"environment's{' ' + key if key else ''} are {rms.mean.shape}")
        rms.mean, rms.var, rms.count = mean, var, count
    return normalizer


def _unpickle_normalizer(path: Path) -> VecNormalize:
    """The former ``vecnormalize.pkl`` (only for a folder the user trusts)."""
    try:
        with open(path, "rb") as f:
            normalizer = pickle.load(f)  # noqa: S301 - the caller trusts this folder (--trust-pickle)
    except (pickle.UnpicklingError, EOFError, AttributeError, ImportError, IndexError, TypeError, ValueError) as exc:
        raise ConfigError(f"observation statistics {path} cannot be read ({type(exc).__name__}: {exc})") from None
    if not isinstance(normalizer, VecNormalize):
        raise ConfigError(f"{path} does not hold VecNormalize statistics")
    return normalizer


class _StatsVecEnv(VecEnv):
    """The observation space of stored statistics, for a VecNormalize that only normalises."""

    def __init__(self, data: dict):
        from gymnasium import spaces

        def box(mean):
            return spaces.Box(-np.inf, np.inf, mean.shape, dtype=np.float32)

        stats = data["stats"]
        space = box(stats[""][0]) if data["keys"] is None else spaces.Dict({k: box(s[0]) for k, s in stats.items()})
        super().__init__(1, space, spaces.Box(-1.0, 1.0, (1,), dtype=np.float32))

    def reset(self):  # pragma: no cover - never stepped
        raise NotImplementedError

    def step_async(self, actions):  # pragma: no cover
        raise NotImplementedError

    def step_wait(self):  # pragma: no cover
        raise NotImplementedError

    def close(self):
        pass

    def get_attr(self, attr_name, indices=None):
        return [None]  # (VecEnv asks for render_mode: none)

    def set_attr(self, attr_name, value, indices=None):  # pragma: no cover
        raise NotImplementedError

    def env_method(self, method_name, *method_args, indices=None, **method_kwargs):  # pragma: no cover
        raise NotImplementedError

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False]


# ----------------------------------------------------------------------- model
def model_record(path: Path) -> dict:
    """The plain-JSON entries of an SB3 zip's ``data`` (step count, update count, ...),
    read without deserialising its pickled ones."""
    try:
        with zipfile.ZipFile(path) as archive:
            data = json.loads(archive.read("data").decode())
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
        raise ConfigError(f"{path} is not a PPO or SAC model ({type(exc).__name__}: {exc})") from None
    return {k: v for k, v in data.items() if not (isinstance(v, dict) and ":serialized:" in v)}


def load_model(path: Path, cfg: RunConfig, env, **model_args):
    """The SB3 model of ``cfg`` (its algorithm, policy and hyperparameters) on ``env`` with
    the weights of the zip at ``path``, read by ``torch.load(weights_only=True)``: nothing
    in the file is unpickled. Keeps the zip's step count. ``ConfigError`` when the weights
    do not fit the config (another network, another environment)."""
    record = model_record(path)
    algo = algorithm_class(cfg.algorithm.name)
    try:
        model = algo(cfg.algorithm.policy, env, device="cpu", verbose=0, seed=cfg.seed, **model_args,
                     **cfg.algorithm.hyperparameters)
    except (AssertionError, ValueError, TypeError) as exc:
        raise ConfigError(f"the run config's algorithm cannot be built: {exc}") from None
    try:
        model.set_parameters(str(path), exact_match=True, device="cpu")
        _, _, variables = load_from_zip_file(path, load_data=False, device="cpu")
    except (RuntimeError, ValueError, KeyError, OSError, zipfile.BadZipFile) as exc:
        raise ConfigError(f"{path} does not hold {cfg.algorithm.name} weights for this run's config and "
                          f"environment ({type(exc).__name__}: {str(exc).splitlines()[0]})") from None
    for name, value in (variables or {}).items():  # e.g. SAC's entropy coefficient
        recursive_setattr(model, f"{name}.data", value.data)
    model.num_timesteps = int(record.get("num_timesteps", 0))
    return model


__all__ = ["NORMALIZER_FILE", "PICKLED_NORMALIZER_FILE", "UntrustedPickle", "load_model", "load_normalizer",
           "model_record", "normalizer_path", "save_normalizer"]
