"""The retraction task on N worlds at once: gripper, grasp, observations, reward.

A :class:`~heml_gym.envs.scene.Scene` describes one scene (tissue mesh, physics,
attachment, target placement, camera, gripper start); :class:`BatchedRetraction` runs N
independent copies of it on one :class:`heml_gym.Model` (one material per world, drawn
per episode) stepped by the scene's solver. The single-environment classes (N = 1) and
the vectorised ones share this code. Units: m, s, N, Pa.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from .instruments import Grasper
from .measures import Exposure, FoldLift, finite
from .scene import BuiltScene
from .spec import SpecError, from_mapping
from .task import STRAIN_BOUND, TissueTask

POSITION_BOUND = 0.5  # m: |positions| in observations are clipped to this
FORCE_BOUND = 20.0  # N

#: The state observation, entry by entry: (name, low, high, unit). The bounds of the
#: observation space and the clipping of every entry come from this table.
#: the bounds of a grasper's entries by their unit: positions (m), the grasping flag (-), forces (N)
_BOUNDS_BY_UNIT = {"m": (-POSITION_BOUND, POSITION_BOUND), "-": (0.0, 1.0), "N": (-FORCE_BOUND, FORCE_BOUND),
                   "rad": (-math.pi, math.pi)}
STATE_SPEC = (
    [(name, *_BOUNDS_BY_UNIT[unit], unit) for name, unit in Grasper.OBSERVATION]  # the grasper's part
    + [(f"target_{a}", -POSITION_BOUND, POSITION_BOUND, "m") for a in "xyz"]
    + [(f"tracked_{i}_{a}", -POSITION_BOUND, POSITION_BOUND, "m") for i in range(4) for a in "xyz"]
    + [("max_strain", 0.0, STRAIN_BOUND, "-"), ("exposure", 0.0, 1.0, "-")]
)
#: Names and order of the state-observation entries (see the env docstrings).
STATE_FIELDS = [name for name, *_ in STATE_SPEC]
STATE_SIZE = len(STATE_FIELDS)
STATE_LOW = np.array([lo for _, lo, _, _ in STATE_SPEC], dtype=np.float32)
STATE_HIGH = np.array([hi for _, _, hi, _ in STATE_SPEC], dtype=np.float32)
#: the state entries of one grasper (position, grasping, force), first in :data:`STATE_SPEC`
GRASPER_SIZE = len(Grasper.OBSERVATION)


def bounds_by_unit(fields) -> tuple[np.ndarray, np.ndarray]:
    """``(low, high)`` float32 of state entries ``fields`` (``(name, unit)``), by unit."""
    return (np.array([_BOUNDS_BY_UNIT[unit][0] for _, unit in fields], dtype=np.float32),
            np.array([_BOUNDS_BY_UNIT[unit][1] for _, unit in fields], dtype=np.float32))


def _positive(obj, name, value, allow_zero=False):
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and (
        value >= 0 if allow_zero else value > 0)
    if not ok:
        raise SpecError(f"{type(obj).__name__}.{name}: must be a finite number {'>=' if allow_zero else '>'} 0, "
                        f"got {value!r}")


@dataclass(frozen=True)
class RewardWeights:
    """Weights of the reward terms (each term is reported in ``info`` under its name);
    every weight a finite number >= 0."""

    exposure: float = 10.0  # times the change of exposure (0..1) this step
    lift: float = 20.0  # times the change of lift progress (0..1) this step (shaping; 5 left PPO stalled short of exposure)
    grasp: float = 0.5  # once per episode, when a grasp first holds tissue
    strain: float = 5.0  # times the strain above the damage threshold
    stretch: float = 5.0  # times the rise of the largest gauge strain this step, as a cost (shaping: fold, don't stretch)
    effort: float = 0.01  # times |gripper velocity command|^2
    success: float = 5.0  # once, on success
    hold: float = 1.0  # per second of simulated time the success condition is held before success (hold_time > 0)

    def __post_init__(self):
        for f in fields(self):
            _positive(self, f.name, getattr(self, f.name), allow_zero=True)


@dataclass(frozen=True)
class TaskSettings:
    """Task constants: control step, gripper, thresholds, episode length. Every value is
    checked: the error names the setting and what it allows."""

    control_dt: float = 0.1  # s simulated per env step, in (0, 10]
    max_speed: float = 0.05  # m/s of the gripper at action 1
    grasp_reach: float = 0.012  # m: closing grasps tissue only if the grasp patch (or a surface vertex) is this close
    jaw_radius: float = 0.005  # m: the jaws hold every surface vertex this close (at least the nearest)
    damage_strain: float = 0.5  # gauge strain above which the strain penalty applies
    #: gauge strain above which info["cost"] counts harm: 0.18, the lower end (mean - 1 SD)
    #: of the ultimate local strain of human liver capsule in uniaxial tension, 0.47 +- 0.29
    #: (Brunon, Bruyere-Garnier and Coret, J Biomech 43(11), 2010, 2221-2227)
    safe_strain: float = 0.18
    tear_strain: float = 1.0  # gauge strain that ends the episode (tissue torn)
    success_exposure: float = 0.8  # fraction of the target visible for success
    hold_time: float = 0.0  # s the success condition must hold, continuously, before success (0: at once)
    release_command: float = -0.5  # grasp command below which closed jaws open (> 0 closes), in [-1, 0]
    max_steps: int = 100  # steps before truncation
    exposure_samples: int = 256  # points on the target sphere for exposure

    def __post_init__(self):
        for name in ("control_dt", "max_speed", "grasp_reach", "jaw_radius", "damage_strain", "tear_strain"):
            _positive(self, name, getattr(self, name))
        if self.control_dt > 10.0:
            raise SpecError(f"TaskSettings.control_dt: must be at most 10 s, got {self.control_dt}")
        s = self.safe_strain
        if isinstance(s, bool) or not isinstance(s, (int, float)) or not (0.0 <= s < math.inf):
            raise SpecError(f"TaskSettings.safe_strain: must be a finite number >= 0, got {s!r}")
        if not self.tear_strain > self.damage_strain:
            raise SpecError(f"TaskSettings.tear_strain: must exceed damage_strain ({self.damage_strain}), "
                            f"got {self.tear_strain}")
        if not (isinstance(self.success_exposure, (int, float)) and 0 < self.success_exposure <= 1):
            raise SpecError(f"TaskSettings.success_exposure: must lie in (0, 1], got {self.success_exposure!r}")
        _positive(self, "hold_time", self.hold_time, allow_zero=True)
        r = self.release_command
        if not (isinstance(r, (int, float)) and not isinstance(r, bool) and -1.0 <= r <= 0.0):
            raise SpecError(f"TaskSettings.release_command: must be a number in [-1, 0], got {r!r}")
        for name in ("max_steps", "exposure_samples"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise SpecError(f"TaskSettings.{name}: must be an integer >= 1, got {value!r}")


def as_settings(value, cls, name: str):
    """``value`` (None, a ``cls`` or a mapping of its fields) as a ``cls``; errors name ``name``."""
    if value is None:
        return cls()
    if isinstance(value, cls):
        return value
    if isinstance(value, dict):
        return from_mapping(cls, value, name)
    raise SpecError(f"{name}: must be a {cls.__name__} or a mapping of its fields, got {type(value).__name__}")


class BatchedRetraction(TissueTask):
    """N independent retraction episodes on one scene: the shared world, graspers and
    draws of a :class:`~heml_gym.envs.task.TissueTask`, and the retraction task: what is
    measured (exposure of a hidden target, lift of the flap, gauge strain), rewarded,
    succeeded, failed and costed.

    ``grippers``: the graspers by name, in action order (a mapping of name to
    ``GripperSpec``); None: the scene's. The action is each grasper's 4 entries in turn,
    and the state observation each one's 7 (position, grasping, force) before the task's
    17. The first grasper is the one the attributes ``gripper``, ``grasping``, ... name."""

    #: a task's own state entries after the exposure (``(name, unit)``; its values:
    #: :meth:`extra_state_observation`, bounded by their units)
    EXTRA_STATE: tuple = ()

    def __init__(self, scene: BuiltScene, n_worlds: int, settings: TaskSettings | None = None,
                 weights: RewardWeights | None = None, grippers: dict | None = None):
        super().__init__(scene, n_worlds, as_settings(settings, TaskSettings, "settings"), grippers)
        self.weights = as_settings(weights, RewardWeights, "weights")
        n = self.n
        # the state's bounds: each instrument's entries by their units, the task's, a task's own, the hooks'
        low, high = bounds_by_unit(self.instrument_fields())
        extra_low, extra_high = bounds_by_unit(self.EXTRA_STATE)
        hook_low, hook_high = bounds_by_unit(self.hook_fields())
        self._state_low = np.concatenate([low, STATE_LOW[GRASPER_SIZE:], extra_low, hook_low])
        self._state_high = np.concatenate([high, STATE_HIGH[GRASPER_SIZE:], extra_high, hook_high])
        self._exposure = Exposure(scene, self.settings.exposure_samples)
        self._fold = FoldLift(scene)
        self.target = np.zeros((n, 3))
        self.exposure = np.zeros(n)
        self.lift = np.zeros(n)
        # env steps the success condition has held in a row; success once it has held hold_time
        self.held_steps = np.zeros(n, dtype=np.int64)
        self.steps_to_hold = math.ceil(self.settings.hold_time / self.settings.control_dt - 1e-9)

    # ------------------------------------------------------------------ reset
    def _draw(self, i: int, rng: np.random.Generator) -> None:
        s = self.scene
        self.target[i] = rng.uniform(s.target_low, s.target_high)
        self.held_steps[i] = 0

    def _measure_start(self, idx: np.ndarray) -> None:
        super()._measure_start(idx)
        self.exposure[idx] = self.measure_exposure(idx)
        self.lift[idx] = self._lift(idx)

    # ------------------------------------------------------------------- step
    def step(self, actions: np.ndarray, active: np.ndarray | None = None):
        """Apply ``actions`` (N, action_size) in [-1, 1] to every world; returns reward, terminated,
        truncated and a dict of per-world arrays (the info).

        Worlds outside the ``active`` mask (default: all) are not simulated (their results
        are meaningless; the vector env resets them right after)."""
        st, w = self.settings, self.weights
        prev_exposure, prev_lift, prev_strain = self.exposure.copy(), self.lift.copy(), self.max_strain.copy()
        out = self.advance(actions, active)
        parts, failed, stats = out.parts, out.failed, out.stats
        diverged = stats.diverged
        grasp_bonus = sum(np.where(first, w.grasp, 0.0) for first in out.first_grasps)
        all_worlds = np.arange(self.n)
        self.exposure = self.measure_exposure(all_worlds)
        self.lift = self._lift(all_worlds)
        self.max_strain = self.measure_strain(all_worlds)
        terms = {
            "reward_exposure": w.exposure * (self.exposure - prev_exposure),
            "reward_lift": w.lift * (self.lift - prev_lift),
            "reward_grasp": grasp_bonus,
            "reward_strain": -w.strain * np.maximum(0.0, self.max_strain - st.damage_strain),
            "reward_stretch": -w.stretch * (self.max_strain - prev_strain),
            "reward_effort": -w.effort * sum((part[:, :3] ** 2).sum(axis=1) for part in parts),
        }
        # success: the target exposed with the tissue below damage strain, held for hold_time
        # (the condition first met counts as 0 s; each further step in a row adds control_dt)
        meets = (self.exposure >= st.success_exposure) & (self.max_strain < st.damage_strain) & ~failed
        meets &= self._also_needed()
        self.held_steps = np.where(meets, self.held_steps + 1, 0)
        success = meets & (self.held_steps > self.steps_to_hold)
        terms["reward_hold"] = np.where(meets & ~success, w.hold * st.control_dt, 0.0)
        terms["reward_success"] = np.where(success, w.success, 0.0)
        # a failed world earns nothing: every term is zeroed, so they still add up
        if failed.any():
            terms = {k: np.where(failed, 0.0, v) for k, v in terms.items()}
        reward = sum(terms.values())
        torn = (self.max_strain >= st.tear_strain) & ~failed
        terminated = success | torn | failed
        truncated = (self.steps >= st.max_steps) & ~terminated
        cost = self.harm(failed)
        info = {**terms, "cost": cost, "damage": self.damage.copy(), "exposure": self.exposure.copy(),
                "lift": self.lift.copy(), "max_strain": self.max_strain.copy(), **self.instrument_info(),
                "is_success": success, "hold_time": np.maximum(self.held_steps - 1, 0) * st.control_dt,
                "tissue_torn": torn, **self.solver_info(stats), **self.wrist_info(all_worlds),
                **self.episode_info(all_worlds)}
        return reward, terminated, truncated, info

    def _also_needed(self) -> np.ndarray:
        """What a task adds to the success condition, per world (here: nothing more)."""
        return np.ones(self.n, dtype=bool)

    def start_info(self, worlds) -> dict:
        """The ``info`` of ``worlds`` (indices) at the start of their episodes (after
        :meth:`reset`), with the keys and dtypes of :meth:`step`'s: every reward term 0,
        nothing held, succeeded, torn or failed, the solver's counters at rest, and the
        episode's measurements and draws. Single envs return it at reset, vector envs
        for the worlds they start afresh."""
        worlds = np.atleast_1d(np.asarray(worlds, dtype=np.int64))
        k = len(worlds)
        zero, no = np.zeros(k), np.zeros(k, dtype=bool)
        return {**{f"reward_{term.name}": zero.copy() for term in fields(RewardWeights)},
                "exposure": self.exposure[worlds].copy(), "lift": self.lift[worlds].copy(),
                "max_strain": self.max_strain[worlds].copy(), **self.instrument_info(worlds, start=True),
                "cost": zero.copy(), "damage": zero.copy(), "is_success": no.copy(), "hold_time": zero.copy(),
                "tissue_torn": no.copy(), **self.solver_start_info(k), **self.wrist_info(worlds),
                **self.episode_info(worlds)}

    # ----------------------------------------------------------- measurements
    def measure_exposure(self, worlds) -> np.ndarray:
        """Fraction of the camera-facing target surface samples the tissue does not hide, in
        each of ``worlds`` (indices), from the current state (the observation's exposure)."""
        worlds = np.atleast_1d(worlds)
        return self._exposure(self.x[worlds], self.target[worlds])

    def _lift(self, worlds) -> np.ndarray:
        """Lift progress in [0, 1] (:class:`~heml_gym.envs.measures.FoldLift`)."""
        return self._fold(self.x[np.atleast_1d(worlds)[:, None], self._fold.edge])

    # ------------------------------------------------------------ observation
    def state_observation(self) -> np.ndarray:
        """The state vector of every world, ``(N, STATE_SIZE)`` float32, clipped to its bounds."""
        tracked = self.x[:, self.scene.tracked].reshape(self.n, -1)
        obs = np.concatenate([*self.instrument_observation(), self.target, tracked, self.max_strain[:, None],
                              self.exposure[:, None], *self.extra_state_observation(), *self.hook_observation()],
                             axis=1)
        obs = np.clip(finite(obs, nan=0.0), self._state_low, self._state_high)
        return obs.astype(np.float32)

    def extra_state_observation(self) -> list[np.ndarray]:
        """A task's own state entries (:attr:`EXTRA_STATE`), each ``(N, 1)``; none here."""
        return []

    def state_fields(self) -> list[tuple[str, str]]:
        """``(name, unit)`` of each state entry (:data:`STATE_SPEC`'s, a grasper's once per
        instrument, then a task's own and the hooks')."""
        return (self.instrument_fields() + [(name, unit) for name, _, _, unit in STATE_SPEC[GRASPER_SIZE:]]
                + list(self.EXTRA_STATE) + self.hook_fields())

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` of the state observation (from :data:`STATE_SPEC`, its grasper's
        entries once per instrument)."""
        return self._state_low.copy(), self._state_high.copy()


def settings_with(settings: TaskSettings, **changes) -> TaskSettings:
    """A copy of ``settings`` with ``changes`` (the caller's object is never modified)."""
    return replace(settings, **changes)
