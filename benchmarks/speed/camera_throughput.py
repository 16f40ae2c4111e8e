"""Camera observations: what rendering costs next to the physics, on both envs.

1. Frames per second of the batched rasteriser alone (``CameraRenderer.render``) on one
   thread, 84 x 84 and 128 x 128 RGB-D, each env's default scenes in the middle of its
   scripted fold (grasped, folding: a deformed tissue in view).
2. A 16-scene vector env with ``obs_mode="rgbd"`` (84 x 84) against the same env with state
   observations, random actions, all Numba threads, in interleaved blocks of the same run
   (so both see the same machine load): median env steps per second and their ratio.

Writes docs/benchmarks/camera_throughput.{json,md}.

    python -m heml_gym.benchmarks.speed.camera_throughput [--blocks 7] [--steps 40] [--from-json]
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numba
import numpy as np
from tqdm import tqdm

from heml_gym.benchmarks.common import command_line, generated_by, machine_info, markdown_table, store_and_report
from heml_gym.envs import ENV_IDS
from heml_gym.envs.scripted import scripted_policy

SCENES = 16
SIZES = (84, 128)
FOLD_STEPS = 8  # scripted steps before timing: grasped and folding


def render_rate(env_id: str, size: int, reps: int = 40) -> float:
    """RGB-D frames per second (one per scene) of the rasteriser alone, one thread."""
    numba.set_num_threads(1)
    try:
        vec = gym.make_vec(env_id, num_envs=SCENES, vectorization_mode="vector_entry_point", obs_mode="rgbd",
                           camera={"size": size})
        vec.reset(seed=0)
        policy = scripted_policy(vec.unwrapped.scene)
        for _ in range(FOLD_STEPS):
            states = vec.unwrapped.task.state_observation()
            vec.step(np.stack([policy(s) for s in states]))
        camera = vec.unwrapped.camera_renderer
        camera.render()
        times = []
        for _ in range(reps):
            t0 = time.perf_counter()
            camera.render()
            times.append(time.perf_counter() - t0)
        vec.close()
    finally:
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    return SCENES / float(np.median(times))


def env_rates(env_id: str, blocks: int, steps: int, bar) -> dict:
    """Env steps per second of the 16-scene vector env with state and with rgbd observations,
    in ``blocks`` interleaved blocks of ``steps`` vector steps (random actions, all threads)."""
    envs = {mode: gym.make_vec(env_id, num_envs=SCENES, vectorization_mode="vector_entry_point", obs_mode=mode)
            for mode in ("state", "rgbd")}
    rng = np.random.default_rng(0)
    action_size = envs["state"].single_action_space.shape[0]
    rates = {mode: [] for mode in envs}
    for env in envs.values():  # compile and settle before timing
        env.reset(seed=0)
        env.step(rng.uniform(-1, 1, (SCENES, action_size)).astype(np.float32))
    for _ in range(blocks):
        for mode, env in envs.items():
            actions = rng.uniform(-1, 1, (steps, SCENES, action_size)).astype(np.float32)
            t0 = time.perf_counter()
            for a in actions:
                env.step(a)
            rates[mode].append(steps * SCENES / (time.perf_counter() - t0))
            bar.update()
    for env in envs.values():
        env.close()
    return {"state": float(np.median(rates["state"])), "rgbd": float(np.median(rates["rgbd"])), "blocks": rates}


def report(data: dict) -> str:
    head = (f"{generated_by(data)}. Rasteriser: {data['scenes']} scenes grasped and folding (the scripted fold's first "
            f"{data['fold_steps']} steps), medians of 40 renders on one thread. Vector env: {data['scenes']} scenes, "
            f"random actions, all threads, medians of {data['blocks']} interleaved blocks of {data['steps']} "
            f"vector steps.\n\n")
    rows = []
    for env_id, r in data["envs"].items():
        rows.append([env_id.split("/")[-1]] + [f"{r['render_frames_per_s_one_thread'][str(s)]:,.0f}" for s in SIZES]
                    + [f"{r['vector_env']['state']:,.0f}", f"{r['vector_env']['rgbd']:,.0f}",
                       f"{r['vector_env']['rgbd'] / r['vector_env']['state']:.2f}"])
    return head + markdown_table(["env", "84 x 84 RGB-D frames/s, rasteriser, one thread",
                                  "128 x 128 frames/s", "env steps/s, state", "env steps/s, rgbd 84 x 84",
                                  "rgbd / state"], rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--blocks", type=int, default=7, help="interleaved timing blocks per observation mode")
    ap.add_argument("--steps", type=int, default=40, help="vector steps per block")
    ap.add_argument("--from-json", action="store_true", help="only rebuild the table from the stored result")
    args = ap.parse_args(argv)
    if args.from_json:
        store_and_report("camera_throughput", None, report)
        return 0
    data = {"machine": machine_info(), "command": command_line("heml_gym.benchmarks.speed.camera_throughput", ap, args),
            "scenes": SCENES, "fold_steps": FOLD_STEPS, "blocks": args.blocks, "steps": args.steps, "envs": {}}
    with tqdm(total=len(ENV_IDS) * 2 * args.blocks, desc="timing blocks") as bar:
        for env_id in ENV_IDS:
            frames = {str(size): render_rate(env_id, size) for size in SIZES}
            data["envs"][env_id] = {"render_frames_per_s_one_thread": frames,
                                    "vector_env": env_rates(env_id, args.blocks, args.steps, bar)}
    store_and_report("camera_throughput", data, report, envs=ENV_IDS)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
