"""Golden trajectories: a refactoring check, bit for bit on one machine.

Steps both envs under each integrator (quasi-Newton by backward Euler and by BDF2,
Newton, explicit) for a fixed seeded stream of random actions and stores, after the
last step, the tissue's positions (m) and velocities (m/s), the last step's constraint
reactions (N), and every step's reward and grasp force (N). ``--compare`` re-runs the
same streams and reports the largest difference of each array: a change of the
kernels' plumbing (arguments, bundles, module layout) must leave every one at exactly 0.

Bit-for-bit equality only holds on one machine with one codegen target (another CPU
rounds differently): record and compare in the same session. This is why the file is
not a test (the suite asserts properties over many seeded streams instead).

    python scripts/golden_trajectories.py --record /tmp/golden.npz
    python scripts/golden_trajectories.py --compare /tmp/golden.npz
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

#: (env id, physics overrides, env steps[, vector scenes, obs mode])
CASES = [
    ("heml_gym/TissueRetraction-v1", {}, 100),
    ("heml_gym/TissueRetraction-v1", {"scheme": "bdf2"}, 100),
    ("heml_gym/TissueRetraction-v1", {"integrator": "implicit"}, 100),
    ("heml_gym/TissueRetraction-v1", {"integrator": "explicit"}, 100),
    ("heml_gym/OrganRetraction-v2", {}, 100),
    ("heml_gym/OrganRetraction-v2", {"integrator": "implicit"}, 40),
    ("heml_gym/OrganRetraction-v2", {"integrator": "explicit"}, 20),
    # vector envs: the scenes over threads (quasi-Newton), in SIMD lanes (explicit,
    # Neo-Hookean) and fused (explicit, any law); camera images (serial and parallel)
    ("heml_gym/TissueRetraction-v1", {}, 30, 4, "state"),
    ("heml_gym/TissueRetraction-v1", {"integrator": "explicit"}, 20, 6, "state"),
    ("heml_gym/TissueRetraction-v1", {"integrator": "explicit", "material": "Demiray",
                                      "material_options": {"b": 2.0}}, 20, 3, "state"),
    ("heml_gym/TissueRetraction-v1", {}, 10, 1, "rgbd"),
    ("heml_gym/OrganRetraction-v2", {}, 10, 2, "rgbd"),
    # the grasper's other jaws: shorter than the grasp region with weighted ends, on a free wrist
    ("heml_gym/TissueRetraction-v1", {}, 60, 3, "state", {"gripper": {"jaw_length": 0.04, "jaw_ends": "weighted"}}),
    ("heml_gym/TissueRetraction-v1", {}, 60, 3, "state", {"gripper": {"wrist_reach": 0.01}}),
]


def case_name(env_id: str, physics: dict, scenes: int | None = None, obs_mode: str = "state",
              scene: dict | None = None) -> str:
    short = env_id.split("/")[1].split("-")[0]
    name = short + "".join(f"_{k}={v}" for k, v in sorted(physics.items()) if k != "material_options")
    if scenes is not None:
        name += f"_vector{scenes}"
    name += "".join(f"_{k}" for k in sorted((scene or {}).get("gripper", {})))
    return name + ("" if obs_mode == "state" else f"_{obs_mode}")


def run_case(env_id: str, physics: dict, steps: int, scenes: int | None = None, obs_mode: str = "state",
             scene: dict | None = None, seed: int = 0) -> dict[str, np.ndarray]:
    """The end state of ``steps`` seeded random env steps (a vector env of ``scenes``
    scenes when given; its images when ``obs_mode`` has them; ``scene``: changes to the
    task's scene)."""
    import gymnasium as gym

    import heml_gym.envs  # noqa: F401

    rng = np.random.default_rng(seed)
    if scenes is None:
        env = gym.make(env_id, physics=physics)
        shape = (4,)
    else:
        env = gym.make_vec(env_id, num_envs=scenes, vectorization_mode="vector_entry_point", physics=physics,
                           obs_mode=obs_mode, **({"scene": scene} if scene else {}))
        shape = (scenes, 4)
    obs, _ = env.reset(seed=seed)
    rewards, forces = [], []
    for _ in range(steps):
        obs, reward, terminated, truncated, info = env.step(rng.uniform(-1, 1, shape).astype(np.float32))
        rewards.append(reward)
        forces.append(info["grasp_force"])
        if scenes is None and (terminated or truncated):
            obs, _ = env.reset()
    task = env.unwrapped.task
    out = {"x": task.state.x.copy(), "v": task.state.v.copy(), "reaction": task.reaction.copy(),
           "reward": np.array(rewards), "grasp_force": np.array(forces)}
    if isinstance(obs, dict):
        out.update({f"obs_{k}": np.asarray(v, dtype=np.float64) for k, v in obs.items()})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    group = ap.add_mutually_exclusive_group(required=True)
    group.add_argument("--record", metavar="NPZ", help="store the trajectories' end states here")
    group.add_argument("--compare", metavar="NPZ", help="re-run and compare with a stored record")
    args = ap.parse_args(argv)
    results = {}
    for env_id, physics, steps, *vector in CASES:
        name = case_name(env_id, physics, *vector)
        for key, value in run_case(env_id, physics, steps, *vector).items():
            results[f"{name}/{key}"] = value
        print(f"{name}: {steps} steps", flush=True)
    if args.record:
        np.savez(args.record, **results)
        print(f"recorded {len(results)} arrays in {args.record}")
        return 0
    stored = np.load(args.compare)
    worst = 0.0
    for key, value in results.items():
        diff = float(np.abs(value - stored[key]).max()) if value.size else 0.0
        worst = max(worst, diff)
        print(f"{key:55s} max |difference| {diff:.3g}")
    print("bit for bit" if worst == 0.0 else f"CHANGED (largest difference {worst:.3g})")
    return 0 if worst == 0.0 else 1


if __name__ == "__main__":
    sys.exit(main())
