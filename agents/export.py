"""``heml-gym export``: a trained policy as one ONNX graph, limits included.

The graph maps the env's raw state observation (``(batch, n)`` float32: a retraction
task's state, e.g. the 24 fields of ``heml_gym.envs.STATE_SPEC``, their units in the
file's metadata; a goal task's dict concatenated in the order its ``observation_keys``
metadata names) to the action (``(batch, 4 K)`` float32 in [-1, 1] for K graspers: each
one's velocity as a fraction of the env's ``max_speed`` along x, y, z, and its grasp command): the run's observation normalisation
and clipping, the deterministic policy (PPO: the Gaussian's mean; SAC: the squashed mean),
the action box, and optionally

* a **speed limit** (m/s): the gripper's velocity components clipped to it;
* a **workspace box** (m): a velocity component that would carry the gripper further
  outside the box is zeroed (the gripper's position is the observation's first three
  fields).

It is built node by node from the policy's weights (Gemm and activation layers), so it
needs ``onnx`` only, not torch's exporter; ``onnxruntime`` runs it
(:class:`OnnxPolicy`: what ``heml-gym rollout/eval --policy policy.onnx`` use). Only MLP
policies on state observations export (pixel policies: not yet).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["export_policy", "OnnxPolicy", "ExportError", "exported_policy", "pretrained_path", "PRETRAINED"]

#: Where the shipped policies live (package data), one per env id: ``<name>-v<k>.onnx``.
PRETRAINED = Path(__file__).resolve().parent / "pretrained"


def pretrained_path(env_id: str) -> Path:
    """The shipped ONNX policy of ``env_id``'s default task, or a one-line error naming
    the envs that have one."""
    path = PRETRAINED / (env_id.split("/")[-1] + ".onnx")
    if not path.is_file():
        have = sorted("heml_gym/" + p.stem for p in PRETRAINED.glob("*.onnx"))
        raise FileNotFoundError(f"--policy pretrained: no pretrained policy for {env_id} "
                                f"(there is one for: {', '.join(have) or 'none yet'})")
    return path

#: a goal task's observation parts beside ``observation`` (its state), with their sizes
GOAL_PARTS = {"achieved_goal": 3, "desired_goal": 3}

ACTIVATIONS = {"Tanh": "Tanh", "ReLU": "Relu", "ELU": "Elu", "Sigmoid": "Sigmoid", "LeakyReLU": "LeakyRelu"}


class ExportError(ValueError):
    """A policy or option that cannot be exported."""


def _layers(module) -> list[tuple[str, object]]:
    """``[("gemm", (W, b)) | ("act", onnx op), ...]`` of a torch MLP (Sequential/Linear/activations)."""
    import torch.nn as nn

    out = []
    mods = list(module) if isinstance(module, nn.Sequential) else [module]
    for m in mods:
        if isinstance(m, nn.Sequential):
            out += _layers(m)
        elif isinstance(m, nn.Linear):
            out.append(("gemm", (m.weight.detach().cpu().numpy().astype(np.float32),
                                 m.bias.detach().cpu().numpy().astype(np.float32))))
        elif isinstance(m, nn.Identity):
            continue
        elif type(m).__name__ in ACTIVATIONS:
            out.append(("act", ACTIVATIONS[type(m).__name__]))
        else:
            raise ExportError(f"layer {type(m).__name__} has no ONNX translation here (MLP policies only)")
    return out


def policy_layers(model) -> tuple[list, bool]:
    """The deterministic policy's layers from the (normalised) observation to the action,
    and whether its output is squashed by tanh (SAC); a ``torch.nn.Sequential`` (a BC
    network, :mod:`heml_gym.agents.bc`) is its own layers."""
    import torch.nn as nn
    from stable_baselines3 import PPO, SAC

    if isinstance(model, nn.Sequential):
        return _layers(model), False

    policy = model.policy
    if isinstance(model, PPO):
        _check_flat(policy.features_extractor)
        if getattr(policy, "squash_output", False):
            raise ExportError("a squashed PPO policy does not export here")
        return _layers(policy.mlp_extractor.policy_net) + _layers(policy.action_net), False
    if isinstance(model, SAC):
        actor = policy.actor
        _check_flat(actor.features_extractor)
        return _layers(actor.latent_pi) + _layers(actor.mu), True
    raise ExportError(f"{type(model).__name__} policies do not export (PPO and SAC do)")


def _check_flat(extractor) -> None:
    """An extractor that only flattens (a state vector, or a goal task's dict of vectors
    concatenated in key order); images do not export."""
    name = type(extractor).__name__
    flat = name == "FlattenExtractor" or (
        name == "CombinedExtractor" and all(type(e).__name__ == "Flatten" for e in extractor.extractors.values()))
    if not flat:
        raise ExportError("only state-observation (MLP) policies export; this one reads images")


def observation_keys(model) -> list[str] | None:
    """The keys of a dict observation in the order the policy concatenates them (a goal
    task's: achieved_goal, desired_goal, observation), None for a vector observation."""
    from gymnasium import spaces

    space = getattr(model, "observation_space", None)
    return list(space.spaces) if isinstance(space, spaces.Dict) else None


def observation_size(model) -> int | None:
    """The length of the observation ``model`` reads (an SB3 model, or a torch MLP: its
    first layer's inputs); None for a non-vector observation."""
    import torch.nn as nn

    if isinstance(model, nn.Sequential):
        return next(m.in_features for m in model.modules() if isinstance(m, nn.Linear))
    keys = observation_keys(model)
    if keys is not None:
        spaces = model.observation_space.spaces
        if all(len(spaces[k].shape) == 1 for k in keys):
            return int(sum(spaces[k].shape[0] for k in keys))
        return None
    return int(model.observation_space.shape[0]) if model.observation_space.shape else None


def export_policy(model, normalizer, out, env_id: str, run: str = "", speed_limit: float | None = None,
                  workspace: tuple | None = None, max_speed: float = 0.05) -> Path:
    """Write ``model`` (SB3 PPO / SAC) with ``normalizer`` (the run's VecNormalize statistics,
    or None) as an ONNX graph at ``out``; ``max_speed`` (m/s) is the env's, which a
    ``speed_limit`` (m/s) is a fraction of. Returns the path."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    import gymnasium as gym

    import heml_gym.envs  # noqa: F401  (registers the environments)

    env = gym.make(env_id)
    fields = env.unwrapped.task.state_fields()
    task = env.unwrapped.task
    instruments = list(task.instruments) + list(getattr(task, "hooks", []))
    #: where each instrument's position starts in the state, in action order (graspers, paddles, hooks)
    positions = [k for k, (name, _) in enumerate(fields) if name.endswith(("gripper_x", "centre_x", "tip_x"))]
    goal = isinstance(env.observation_space, gym.spaces.Dict)
    env.close()
    keys = (observation_keys(model) or sorted([*GOAL_PARTS, "observation"])) if goal else None  # (BC: sorted, as it reads)
    # the flat input: the state (with a goal task's goals, concatenated in the policy's key order)
    sizes = {**GOAL_PARTS, "observation": len(fields)}
    expected = sum(sizes[k] for k in keys) if keys else len(fields)
    obs_dim = observation_size(model)
    if obs_dim != expected or (goal and keys is None):
        raise ExportError(f"the policy reads {getattr(model, 'observation_space', obs_dim)} observations; only "
                          f"{env_id}'s state observation ({expected} entries) exports")
    offset = 0 if not keys else sum(sizes[k] for k in keys[:keys.index("observation")])
    layers, squash = policy_layers(model)
    action_size = int(next(w for kind, (w, _) in reversed([(k, v) for k, v in layers if k == "gemm"])).shape[0])
    graspers = action_size // 4
    if not all(np.all(np.isfinite(w)) and np.all(np.isfinite(b)) for kind, (w, b) in
               ((k, v) for k, v in layers if k == "gemm")):
        raise ExportError("the policy's weights are not all finite: nothing to export")
    nodes, inits = [], []

    made = set()

    def const(name, value, dtype=np.float32):
        if name not in made:  # (one initializer per name: the graspers' limits share theirs)
            made.add(name)
            inits.append(numpy_helper.from_array(np.asarray(value, dtype=dtype), name))
        return name

    x = "observation"
    if normalizer is not None:
        rms = normalizer.obs_rms
        if keys and isinstance(rms, dict):  # per key, in the concatenation's order
            mean = np.concatenate([rms[k].mean for k in keys])
            scale = np.concatenate([1.0 / np.sqrt(rms[k].var + normalizer.epsilon) for k in keys])
        else:
            mean, scale = rms.mean, 1.0 / np.sqrt(rms.var + normalizer.epsilon)
        nodes.append(helper.make_node("Sub", [x, const("obs_mean", mean)], ["obs_centred"]))
        nodes.append(helper.make_node("Mul", ["obs_centred", const("obs_scale", scale)], ["obs_scaled"]))
        c = float(normalizer.clip_obs)
        nodes.append(helper.make_node("Clip", ["obs_scaled", const("obs_low", -c), const("obs_high", c)],
                                      ["obs_normalised"]))
        x = "obs_normalised"
    for k, (kind, value) in enumerate(layers):
        if kind == "gemm":
            W, b = value
            nodes.append(helper.make_node("Gemm", [x, const(f"W{k}", W), const(f"b{k}", b)], [f"h{k}"], transB=1))
        else:
            nodes.append(helper.make_node(value, [x], [f"h{k}"]))
        x = f"h{k}"
    if squash:
        nodes.append(helper.make_node("Tanh", [x], ["squashed"]))
        x = "squashed"
    nodes.append(helper.make_node("Clip", [x, const("act_low", -1.0), const("act_high", 1.0)], ["action_box"]))
    x = "action_box"
    state = "state: " + ", ".join(f"{name} ({unit})" for name, unit in fields)
    metadata = {"env_id": env_id, "run": run,
                "observation": state if not keys else (f"the concatenation of {', '.join(keys)}: achieved_goal and "
                                                       f"desired_goal 3-D points (m); observation the {state}"),
                "action": ("; ".join(f"{getattr(i, 'name', None) or i.kind}: {', '.join(i.ACTION)}" for i in instruments)
                           + " (velocities as a fraction of max_speed in [-1, 1]; a grasp command > 0 closes, "
                             "< release_command opens; an energy command > 0 energises)"),
                "max_speed_m_per_s": str(max_speed), "normalised_inside": str(normalizer is not None)}
    if keys:
        metadata["observation_keys"] = ",".join(keys)
    if speed_limit is not None or workspace is not None:
        if speed_limit is not None and not (np.isfinite(speed_limit) and speed_limit > 0):
            raise ExportError(f"--speed-limit: must be a positive speed in m/s, got {speed_limit}")
        if workspace is not None:
            lo, hi = (np.asarray(w, dtype=np.float32).reshape(3) for w in workspace)
            if not np.all(lo < hi):
                raise ExportError(f"--workspace: low {lo.tolist()} must lie below high {hi.tolist()} on every axis")
        axis1, zero = const("axis1", [1], np.int64), const("zero", 0.0)
        parts = []
        for g in range(graspers):  # each grasper's velocity limited, its grasp command kept
            at = lambda k: const(f"index{k}", [k], np.int64)  # noqa: E731
            nodes.append(helper.make_node("Slice", [x, at(4 * g), at(4 * g + 3), axis1], [f"velocity{g}"]))
            nodes.append(helper.make_node("Slice", [x, at(4 * g + 3), at(4 * g + 4), axis1], [f"grasp{g}"]))
            v = f"velocity{g}"
            if speed_limit is not None:
                f = min(float(speed_limit) / max_speed, 1.0)
                nodes.append(helper.make_node("Clip", [v, const("v_low", -f), const("v_high", f)],
                                              [f"velocity_limited{g}"]))
                v = f"velocity_limited{g}"
            if workspace is not None:
                p = offset + positions[g]  # the instrument's position in the flat input
                nodes.append(helper.make_node("Slice", ["observation", at(p), at(p + 3), axis1], [f"position{g}"]))
                nodes += [helper.make_node("GreaterOrEqual", [f"position{g}", const("ws_high", hi)], [f"at_high{g}"]),
                          helper.make_node("LessOrEqual", [f"position{g}", const("ws_low", lo)], [f"at_low{g}"]),
                          helper.make_node("Greater", [v, zero], [f"moving_up{g}"]),
                          helper.make_node("Less", [v, zero], [f"moving_down{g}"]),
                          helper.make_node("And", [f"at_high{g}", f"moving_up{g}"], [f"out_high{g}"]),
                          helper.make_node("And", [f"at_low{g}", f"moving_down{g}"], [f"out_low{g}"]),
                          helper.make_node("Or", [f"out_high{g}", f"out_low{g}"], [f"leaving{g}"]),
                          helper.make_node("Where", [f"leaving{g}", zero, v], [f"velocity_inside{g}"])]
                v = f"velocity_inside{g}"
            parts += [v, f"grasp{g}"]
        if speed_limit is not None:
            metadata["speed_limit_m_per_s"] = str(speed_limit)
        if workspace is not None:
            metadata["workspace_m"] = json.dumps([[float(v) for v in w] for w in workspace])
        nodes.append(helper.make_node("Concat", parts, ["limited"], axis=1))
        x = "limited"
    nodes.append(helper.make_node("Identity", [x], ["action"]))
    graph = helper.make_graph(nodes, "heml_gym_policy",
                              [helper.make_tensor_value_info("observation", TensorProto.FLOAT, ["batch", obs_dim])],
                              [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", action_size])],
                              inits)
    onnx_model = helper.make_model(graph, producer_name="heml-gym", opset_imports=[helper.make_opsetid("", 17)])
    onnx_model.ir_version = 8
    for key, value in metadata.items():
        entry = onnx_model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(onnx_model, full_check=True)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(onnx_model, out)
    return out


def exported_policy(spec: str, env_id: str | None, default_env: str):
    """The :class:`OnnxPolicy` that ``spec`` names (``"pretrained"``: the one shipped for
    ``env_id``, else ``default_env``; or a path ending in ``.onnx``), checked to be for
    ``env_id`` when one is given; None when ``spec`` names something else (a run folder, a
    model file, the scripted policy). What ``eval``, ``rollout`` and ``demos`` read. A
    policy exported for a retired version whose state task is unchanged
    (:data:`heml_gym.envs.SAME_STATE_TASK`) runs on its successor."""
    if spec == "pretrained":
        path = pretrained_path(env_id or default_env)
    elif str(spec).endswith(".onnx"):
        path = spec
    else:
        return None
    policy = OnnxPolicy(path)
    if env_id and env_id != policy.runs_on:
        raise ValueError(f"--env {env_id}: the policy was exported for {policy.env_id} (its observations and "
                         "actions are that env's); omit --env to use it there")
    return policy


class OnnxPolicy:
    """An exported policy as an ``obs -> action`` callable (onnxruntime, one thread);
    ``metadata`` holds the file's ``env_id``, observation and action descriptions, limits.
    ``env_id``: the env it was exported for; ``runs_on``: the registered env it runs on
    (the same, or the successor of a retired version with the same state task)."""

    def __init__(self, path):
        import onnxruntime as ort

        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"ONNX policy not found: {path}")
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        try:
            self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # not an ONNX file, or a broken one
            raise ExportError(f"{path}: not a loadable ONNX policy ({type(exc).__name__})") from None
        self.metadata = dict(self.session.get_modelmeta().custom_metadata_map)
        if "env_id" not in self.metadata:
            raise ExportError(f"{path}: not a heml-gym policy (no env_id in its metadata)")
        self.env_id = self.metadata["env_id"]
        from heml_gym.envs import SAME_STATE_TASK

        self.runs_on = SAME_STATE_TASK.get(self.env_id, self.env_id)

    def __call__(self, obs) -> np.ndarray:
        keys = self.metadata.get("observation_keys")
        if keys and isinstance(obs, dict):  # a goal task's dict, flattened as the policy read it
            obs = np.concatenate([np.asarray(obs[k], dtype=np.float32) for k in keys.split(",")], axis=-1)
        batch = np.asarray(obs, dtype=np.float32)
        single = batch.ndim == 1
        out = self.session.run(["action"], {"observation": batch[None] if single else batch})[0]
        return out[0] if single else out
