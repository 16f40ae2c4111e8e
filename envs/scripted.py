"""Scripted baseline for the retraction tasks: grasp the free edge, fold the tissue back,
hold it there.

The policy reads only the state observation (gripper position, grasp flag, exposure). It
closes the gripper where it starts (next to the free edge), or, with jaws shorter than
the grasp region, first moves to the region's middle (``grasp_point``); once holding
tissue it moves
the gripper along a circular arc about the attached edge (the hinge), keeping its
distance to the hinge so the tissue is folded rather than stretched, until the target is
exposed (``hold_exposure``) or the arc reaches ``max_angle``, and holds the gripper still
there (folding on if the exposure drops again).
"""

from __future__ import annotations

import math

import numpy as np

from .core import GRASPER_SIZE, STATE_FIELDS
from .instruments.port import Port

EXPOSURE = STATE_FIELDS.index("exposure")  # its entry in the state observation
ALIGNED = 0.001  # m: close enough to ``grasp_point`` to close the jaws
GRASP_INSET = 0.008  # m: the jaws close this far inside a grasp region's x (a free edge), to be within reach


class FoldBackPolicy:
    """Grasp, then fold the tissue about the hinge line ``x = hinge[0], z = hinge[1]``.

    ``direction`` is +1 when the tissue extends from the hinge towards +x, -1 towards -x.
    ``step_angle``: radians added to the arc angle per step; ``max_angle``: where to stop at
    the latest (past vertical, so the tissue lies back over its attachment);
    ``hold_exposure``: the exposure (0..1) at which to stop folding and hold (None: fold
    to ``max_angle``); ``max_speed`` and ``control_dt`` convert a displacement (m) into a
    velocity command; ``grasp_point`` (m): ``(x, y)`` where to close the jaws, either may
    be None (None: where the gripper starts); ``radius_scale``: the arc's radius as a
    fraction of the grasp's distance from the hinge (below 1 the fold carries the grasped
    edge back over the hinge with some slack instead of pulling it taut).
    """

    def __init__(self, hinge=(0.0, 0.008), step_angle=0.06, max_angle=1.9, max_speed=0.05,
                 control_dt=0.1, direction=1.0, hold_exposure: float | None = 0.95, grasp_point=None,
                 radius_scale: float = 1.0):
        self.radius_scale = float(radius_scale)
        self.grasp_point = None if grasp_point is None else np.array(
            [np.nan if v is None else float(v) for v in grasp_point])
        self.hinge = np.asarray(hinge, dtype=np.float64)
        self.direction = 1.0 if direction >= 0 else -1.0  # -1: the tissue extends towards -x
        self.step_angle = float(step_angle)
        self.max_angle = float(max_angle)
        self.hold_exposure = None if hold_exposure is None else float(hold_exposure)
        self.scale = 1.0 / (max_speed * control_dt)
        self.radius = None

    def reset(self):
        self.radius = None

    def __call__(self, obs) -> np.ndarray:
        state = obs["state"] if isinstance(obs, dict) else obs
        gripper, grasping = np.asarray(state[0:3], dtype=np.float64), state[3] > 0.5
        if not grasping:
            self.radius = None
            if self.grasp_point is not None:  # move to the grasp point first (the jaws stay open)
                move = np.nan_to_num(self.grasp_point - gripper[:2])
                if np.abs(move).max() > ALIGNED:
                    return np.concatenate([np.clip(move * self.scale, -1.0, 1.0), [0.0, 0.0]]).astype(np.float32)
            return np.array([0.0, 0.0, 0.0, 1.0], dtype=np.float32)
        sign = self.direction
        rel = np.array([sign * (gripper[0] - self.hinge[0]), gripper[2] - self.hinge[1]])
        if self.radius is None:
            self.radius = self.radius_scale * float(np.hypot(*rel))
        exposed = self.hold_exposure is not None and state[EXPOSURE] >= self.hold_exposure
        angle = min(math.atan2(rel[1], rel[0]) + (0.0 if exposed else self.step_angle), self.max_angle)
        target = self.radius * np.array([math.cos(angle), math.sin(angle)])
        move = np.array([self.hinge[0] + sign * target[0] - gripper[0], 0.0,
                         self.hinge[1] + target[1] - gripper[2]]) * self.scale
        return np.concatenate([np.clip(move, -1.0, 1.0), [1.0]]).astype(np.float32)


#: How far (rad above the free direction) each scene family is folded: the flap back
#: past vertical over its attachment, the lobe's thin edge up about its base.
MAX_FOLD_ANGLE = {"TissueRetraction": 1.9, "OrganRetraction": 1.2, "BimanualRetraction": 1.9}
#: With jaws shorter than the grasp region, the fold's arc radius as a fraction of the
#: grasp's distance from the hinge: on the flap 0.9 (held by 40 mm jaws, a taut fold
#: strains soft tissue beyond damage at the jaws' ends); 1 otherwise
PARTIAL_JAWS_RADIUS_SCALE = {"TissueRetraction": 0.9, "BimanualRetraction": 0.9}


class PushPolicy:
    """Scripted expert of a paddle task (PushRetraction): slide the level blade in along x at
    floor level to ``under_x`` (m; its centre), then lift it at ``lift_speed`` (m/s) until
    the exposure reaches ``hold_exposure`` and hold it there (lifting on if the exposure
    drops below it again, never above ``max_height``, m). Reads the state observation:
    the blade's centre (entries 0-2), its tilt (3) and the exposure."""

    def __init__(self, under_x: float = -0.035, lift_speed: float = 0.03, hold_exposure: float = 0.85,
                 max_height: float = 0.07, max_speed: float = 0.03, angular_speed: float = 0.5,
                 control_dt: float = 0.1):
        self.under_x, self.hold_exposure, self.max_height = float(under_x), float(hold_exposure), float(max_height)
        self.lift = float(lift_speed) / max_speed
        self.scale = 1.0 / (max_speed * control_dt)
        self.tilt_scale = 1.0 / (angular_speed * control_dt)

    def reset(self):
        pass

    def __call__(self, obs) -> np.ndarray:
        state = np.asarray(obs["state"] if isinstance(obs, dict) else obs, dtype=np.float64)
        centre, tilt = state[0:3], state[3]
        action = np.zeros(4)
        action[3] = np.clip(-tilt * self.tilt_scale, -1.0, 1.0)  # keep the blade level
        if centre[0] < self.under_x - ALIGNED:  # slide in under the lobe
            action[0] = np.clip((self.under_x - centre[0]) * self.scale, -1.0, 1.0)
            return action.astype(np.float32)
        if state[EXPOSURE] < self.hold_exposure and centre[2] < self.max_height:
            action[2] = self.lift
        return action.astype(np.float32)


class DissectionPolicy:
    """Scripted expert of GallbladderDissection: the grasper closes on the fundus and lifts
    it to ``lift_height`` (m); the hook, energised inside the lower third, sweeps the stuck
    strip in two lanes (y = +-``lane`` m, ``sweep_height`` m above the bed: towards the
    neck in the +y lane to ``neck_x``, back in the -y lane to ``far_x``) at ``sweep_speed``
    (m/s) until ``done_fraction`` of the lower third is released; then the hook switches
    off and rises, and the grasper folds the sac back about its neck (``step_angle`` rad
    per step, on an arc ``radius_scale`` of the jaws' distance from the neck: with slack)
    until both ducts show (``hold_exposure``) and holds there. Reads the state
    observation only (its entries by name: :class:`~heml_gym.envs.gallbladder_dissection.BatchedDissection`)."""

    GRASPER, GRASPING, EXPOSURE, RELEASED, HOOK = slice(0, 3), 3, 23, 24, slice(25, 28)

    def __init__(self, lift_height: float = 0.032, lane: float = 0.0045, sweep_height: float = 0.0005,
                 neck_x: float = 0.003, far_x: float = 0.030, sweep_speed: float = 0.005, done_fraction: float = 0.97,
                 step_angle: float = 0.04, max_angle: float = 1.3, hold_exposure: float = 0.9, radius_scale: float = 1.0,
                 max_speed: float = 0.05, control_dt: float = 0.1):
        self.lift_height, self.lane, self.sweep_height = lift_height, lane, sweep_height
        self.neck_x, self.far_x, self.done_fraction = neck_x, far_x, done_fraction
        self.sweep = sweep_speed / max_speed
        self.step_angle, self.max_angle, self.hold_exposure = step_angle, max_angle, hold_exposure
        self.radius_scale = radius_scale
        self.scale = 1.0 / (max_speed * control_dt)
        self.radius = None

    def reset(self):
        self.radius = None

    def __call__(self, obs) -> np.ndarray:
        state = np.asarray(obs["state"] if isinstance(obs, dict) else obs, dtype=np.float64)
        done = state[self.RELEASED] >= self.done_fraction
        return np.concatenate([self._grasper(state, done), self._hook(state, done)]).astype(np.float32)

    def _grasper(self, state, done) -> np.ndarray:
        jaws = state[self.GRASPER]
        if state[self.GRASPING] < 0.5:
            self.radius = None
            return np.array([0.0, 0.0, 0.0, 1.0])
        if not done:  # lift the fundus while the hook frees the neck
            return np.array([0.0, 0.0, np.clip((self.lift_height - jaws[2]) * self.scale, -1.0, 1.0), 1.0])
        if self.radius is None:
            self.radius = self.radius_scale * float(np.hypot(jaws[0], jaws[2]))
        angle = math.atan2(jaws[2], jaws[0])
        if state[self.EXPOSURE] < self.hold_exposure:
            angle = min(angle + self.step_angle, self.max_angle)
        goal = self.radius * np.array([math.cos(angle), 0.0, math.sin(angle)])
        return np.concatenate([np.clip((goal - jaws) * self.scale, -1.0, 1.0), [1.0]])

    def _hook(self, state, done) -> np.ndarray:
        tip = state[self.HOOK]
        if done:  # off, up and away from the tissue
            return np.array([0.0, 0.0, 1.0 if tip[2] < 0.04 else 0.0, -1.0])
        move = np.zeros(3)
        move[2] = np.clip((self.sweep_height - tip[2]) * self.scale, -1.0, 1.0)
        if tip[1] > 0.0:  # the +y lane, towards the neck, then across
            move[1] = np.clip((self.lane - tip[1]) * self.scale, -1.0, 1.0)
            if tip[0] > self.neck_x:
                move[0] = -self.sweep
            else:
                move[1] = -1.0
        else:  # the -y lane, away from the neck, then across
            move[1] = np.clip((-self.lane - tip[1]) * self.scale, -1.0, 1.0)
            if tip[0] < self.far_x:
                move[0] = self.sweep
            else:
                move[1] = 1.0
        energy = 1.0 if tip[0] <= self.far_x + 0.002 else -1.0  # on only over the stuck strip
        return np.concatenate([move, [energy]])


class SeveralGraspersPolicy:
    """One policy per grasper of a task with several (``policies``, in action order), each
    run on its own view of the state observation: its grasper's 7 entries and the task's
    17 (as a one-grasper task's 24). The action is theirs in turn."""

    def __init__(self, policies):
        self.policies = list(policies)

    def reset(self):
        for p in self.policies:
            p.reset()

    def __call__(self, obs) -> np.ndarray:
        state = np.asarray(obs["state"] if isinstance(obs, dict) else obs)
        k, g = len(self.policies), GRASPER_SIZE
        task = state[g * k:]
        return np.concatenate([p(np.concatenate([state[g * j:g * (j + 1)], task]))
                               for j, p in enumerate(self.policies)]).astype(np.float32)


class ReachGoalPolicy:
    """Scripted expert of a goal-conditioned task (``GoalEnv`` observations): move the open
    jaws towards the marked point (the achieved goal) and close them (they close as soon
    as it is within reach), then move them by the marked point's offset from the desired
    goal each step (``gain`` times it, as a velocity command in units of ``max_speed``)."""

    def __init__(self, max_speed=0.05, control_dt=0.1, gain: float = 1.0):
        self.scale = float(gain) / (max_speed * control_dt)

    def reset(self):
        pass

    def __call__(self, obs) -> np.ndarray:
        state = np.asarray(obs["observation"], dtype=np.float64)
        achieved = np.asarray(obs["achieved_goal"], dtype=np.float64)
        jaws, grasping = state[0:3], state[3] > 0.5
        target = achieved if not grasping else jaws + (np.asarray(obs["desired_goal"], dtype=np.float64) - achieved)
        move = np.clip((target - jaws) * self.scale, -1.0, 1.0)
        return np.concatenate([move, [1.0]]).astype(np.float32)


class PortCommands:
    """A scripted policy that thinks in Cartesian velocities, driving graspers on ports:
    each such grasper's velocity command (its first 3 entries, in units of ``max_speed``)
    becomes the port's tilt and insertion commands that move its tip so to first order
    (:meth:`~heml_gym.envs.instruments.port.Port.commands_for`; ``ports``: one
    :class:`~heml_gym.envs.instruments.port.Port` or None per grasper, in action order).
    Jaws that roll (``rolls``: a flag per grasper) keep their roll: ``policy`` sees the
    state without their ``jaw_roll`` entries, and their roll rate is 0."""

    def __init__(self, policy, ports, max_speed: float = 0.05, rolls=None):
        self.policy, self.ports, self.max_speed = policy, list(ports), float(max_speed)
        self.rolls = [False] * len(self.ports) if rolls is None else [bool(r) for r in rolls]
        # each grasper's first state entry in the full state; the roll entries the policy does not see
        starts = np.cumsum([0] + [GRASPER_SIZE + r for r in self.rolls])
        self._starts = starts[:-1]
        self._rolls_at = [int(start + GRASPER_SIZE) for start, r in zip(self._starts, self.rolls) if r]

    def reset(self):
        self.policy.reset()

    def __call__(self, obs) -> np.ndarray:
        key = ("observation" if "observation" in obs else "state") if isinstance(obs, dict) else None
        state = np.asarray(obs[key] if key else obs, dtype=np.float64)
        if self._rolls_at:  # the state as a grasper that does not roll gives it
            seen = np.delete(state, self._rolls_at).astype(np.float32)
            obs = {**obs, key: seen} if key else seen
        action = np.array(self.policy(obs), dtype=np.float32)
        for k, port in enumerate(self.ports):
            if port is not None:
                tip = state[self._starts[k]:self._starts[k] + 3]
                velocity = action[4 * k:4 * k + 3] * self.max_speed
                action[4 * k:4 * k + 3] = port.commands_for(tip, velocity, self.max_speed)[0]
        for k in reversed(range(len(self.ports))):  # a roll rate of 0 after each rolling grasper's grasp entry
            if self.rolls[k]:
                action = np.insert(action, 4 * k + 4, 0.0)
        return action.astype(np.float32)


class HooksIdle:
    """A scripted policy for the graspers of a scene with hooks: its action, then each
    hook's switched off and still (``hooks``: how many)."""

    def __init__(self, policy, hooks: int):
        self.policy, self.idle = policy, np.tile(np.array([0.0, 0.0, 0.0, -1.0], dtype=np.float32), hooks)

    def reset(self):
        self.policy.reset()

    def __call__(self, obs) -> np.ndarray:
        return np.concatenate([np.asarray(self.policy(obs), dtype=np.float32), self.idle])


def scripted_policy(scene):
    """The scripted baseline of a scene (a :class:`~heml_gym.envs.scene.Scene`: its fold
    hinge and direction are used) or of a scene family by name ("TissueRetraction",
    "OrganRetraction", "BimanualRetraction", "TissueManipulation" or "PushRetraction",
    their default scenes). A scene of paddles alone is pushed (:class:`PushPolicy`). With several graspers, each folds from the middle of its start box
    (:class:`SeveralGraspersPolicy`); a scene with a marked point is a goal task
    (:class:`ReachGoalPolicy`); graspers on ports take its commands through
    :class:`PortCommands`."""
    if isinstance(scene, str):
        from . import bimanual_retraction, organ_retraction, tissue_retraction

        from .gallbladder_dissection import dissection_scene
        from .push_retraction import push_scene
        from .tissue_manipulation import manipulation_scene

        defaults = {"TissueRetraction": tissue_retraction.tissue_scene, "OrganRetraction": organ_retraction.organ_scene,
                    "BimanualRetraction": bimanual_retraction.bimanual_scene, "TissueManipulation": manipulation_scene,
                    "PushRetraction": push_scene, "GallbladderDissection": dissection_scene}
        if scene not in defaults:
            raise ValueError(f"no scripted policy for scene {scene!r} (known: {', '.join(defaults)})")
        scene = defaults[scene]()
    if getattr(scene, "critical", None) is not None and getattr(scene, "hooks", None):  # a dissection
        return DissectionPolicy()
    if getattr(scene, "paddles", None) and not scene.graspers:  # a paddle task
        spec = next(iter(scene.paddles.values()))
        return PushPolicy(max_speed=spec.max_speed, angular_speed=spec.angular_speed)
    specs = [scene.gripper] if scene.graspers is None else list(scene.graspers.values())
    if scene.marker is not None:  # a goal-conditioned task
        policy = ReachGoalPolicy()
    elif len(specs) > 1:
        policy = SeveralGraspersPolicy([_fold_policy(scene, spec, at_start=True) for spec in specs])
    else:
        policy = _fold_policy(scene, specs[0])
    ports = [Port.of(spec) for spec in specs]
    rolls = [spec.roll_speed is not None for spec in specs]
    policy = policy if all(p is None for p in ports) else PortCommands(policy, ports, rolls=rolls)
    return HooksIdle(policy, len(scene.hooks)) if getattr(scene, "hooks", None) else policy


def _fold_policy(scene, gripper, at_start: bool = False) -> FoldBackPolicy:
    """The fold of one grasper (``gripper``: its spec); ``at_start``: jaws shorter than the
    grasp region close at the middle of the grasper's start box in y, not of the region."""
    max_angle = MAX_FOLD_ANGLE.get(scene.name, 1.9)
    partial = gripper.jaw_length is not None  # jaws shorter than the grasp region
    point = None
    if partial:
        point = grasp_point(scene)
        if at_start:
            point = (point[0], 0.5 * (gripper.start_low[1] + gripper.start_high[1]))
    return FoldBackPolicy(hinge=scene.fold.hinge, direction=scene.fold.direction, max_angle=max_angle,
                          radius_scale=PARTIAL_JAWS_RADIUS_SCALE.get(scene.name, 1.0) if partial else 1.0,
                          grasp_point=point)


def grasp_point(scene) -> tuple[float | None, float | None]:
    """Where (m; x, y) to close jaws that hold only part of ``scene``'s grasp region:
    ``GRASP_INSET`` inside its x (towards the hinge) where it fixes x, and the middle of its
    y extent where it bounds y, else of a box tissue's (None where neither says)."""
    region = scene.grasp
    low = region.low if region is not None and region.low is not None else (None, None, None)
    high = region.high if region is not None and region.high is not None else (None, None, None)
    x = None
    if low[0] is not None and low[0] == high[0]:
        x = low[0] - scene.fold.direction * GRASP_INSET
    if low[1] is not None and high[1] is not None:
        y = 0.5 * (low[1] + high[1])
    elif scene.tissue.kind == "box":
        y = scene.tissue.origin[1] + 0.5 * scene.tissue.size[1]
    else:
        y = None
    return x, y


def run_episodes(env, policy, episodes: int, seed: int = 0) -> dict:
    """Roll ``policy`` out for ``episodes`` seeded episodes (seeds ``seed``, ``seed + 1``, ...):
    success rate and means, and every episode's length (steps) and success."""
    successes, exposures, strains, lengths = [], [], [], []
    for k in range(episodes):
        obs, info = env.reset(seed=seed + k)
        policy.reset()
        done = False
        steps = 0
        max_strain = 0.0
        while not done:
            obs, reward, terminated, truncated, info = env.step(policy(obs))
            done = terminated or truncated
            steps += 1
            max_strain = max(max_strain, info["max_strain"])
        successes.append(bool(info["is_success"]))
        exposures.append(info.get("exposure", np.nan))  # (a goal task has none)
        strains.append(max_strain)
        lengths.append(steps)
    return {"episodes": episodes, "success_rate": float(np.mean(successes)),
            "mean_final_exposure": float(np.mean(exposures)) if not np.isnan(exposures).any() else None, "mean_max_strain": float(np.mean(strains)),
            "mean_length": float(np.mean(lengths)), "lengths": lengths, "successes": successes}
