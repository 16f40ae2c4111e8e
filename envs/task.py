"""What every tissue task shares: a world, its instruments, the episode's draws, the step.

:class:`TissueTask` runs N independent episodes on one scene: a :class:`heml_gym.World`
(the tissue's physics) and the scene's instruments (graspers,
:class:`~heml_gym.envs.instruments.Grasper`). It draws each episode's tissue stiffness,
instrument starts and adhesion, steps the instruments and the world, and measures the
tissue's gauge strain and harm. A task (retraction, manipulation to a goal) adds what it
observes, rewards, succeeds and fails on top: the :meth:`_draw`, :meth:`_measure_start`
and :meth:`step` hooks. Units: m, s, N, Pa.
"""

from __future__ import annotations

import math

import numpy as np

from heml_gym.tools import Capsule
from heml_gym.world import World

from .instruments import Grasper, Hook, Paddle
from .instruments.port import SHAFT_HALF_LENGTH
from .measures import finite
from .scene import BuiltScene, GripperSpec
from .spec import SpecError
from .strain_gauges import StrainGauges

STRAIN_BOUND = 5.0  # gauge strain reported for tissue whose strain is not finite


def _wrist(instrument):
    """An instrument's free wrist's reach (m), None without one (paddles have none)."""
    return getattr(instrument.spec, "wrist_reach", None)


class StepOutcome:
    """What :meth:`TissueTask.advance` did: ``parts`` (each instrument's slice of the
    action, ``(N, 4)``), ``first_grasps`` (per instrument: worlds that first held tissue),
    ``stats`` (the world's step statistics), ``failed`` (diverged or not converged)."""

    def __init__(self, parts, first_grasps, stats, failed):
        self.parts, self.first_grasps, self.stats, self.failed = parts, first_grasps, stats, failed


class TissueTask:
    """N episodes of one scene: a world, its graspers, the draws of each episode.

    ``grippers``: the graspers by name, in action order (a mapping of name to
    ``GripperSpec``); None: the scene's (``scene.graspers``, or its one ``gripper``, whose
    ``info`` keys carry no name). The action is each grasper's 4 entries in turn. The first
    grasper is the one the attributes ``gripper``, ``grasping``, ... name.
    """

    #: What :meth:`set_episode` can set, with its unit.
    EPISODE_OPTIONS = {"young_modulus": "Pa", "gripper": "m, (3,)", "adhesion_width": "m"}

    def __init__(self, scene: BuiltScene, n_worlds: int, settings, grippers: dict | None = None):
        if not isinstance(scene, BuiltScene):
            raise TypeError(f"scene must be a BuiltScene (heml_gym.envs.scene.build_scene), got {type(scene).__name__}")
        self.scene = scene
        self.n = n = int(n_worlds)
        self.settings = settings
        dt = settings.control_dt
        if grippers is None:
            specs = [(name, spec) for name, spec in scene.graspers]
        else:
            if (not isinstance(grippers, dict) or not grippers
                    or not all(isinstance(spec, GripperSpec) for spec in grippers.values())):
                raise SpecError(f"grippers: must map each grasper's name to its GripperSpec, got {grippers!r}")
            specs = [(str(name), spec) for name, spec in grippers.items()]
        # the world's rigid tools: the shafts that touch tissue, in the graspers' order, then the paddles
        shafts = [spec.shaft_radius for _, spec in specs if spec.shaft_radius is not None]
        tools = [Capsule(r, SHAFT_HALF_LENGTH) for r in shafts] + [Paddle.blade(spec) for _, spec in scene.paddles]
        self.world = World.from_physics(scene.mesh, scene.physics, n, dt, fixed=scene.fixed, supports=scene.supports,
                                        tools=tools)
        if self.world.substeps > 1_000_000:
            raise SpecError(f"settings.control_dt: {dt} s needs {self.world.substeps} explicit sub-steps per env "
                            "step; use a shorter control_dt or the implicit integrator")
        tool_of = iter(range(len(tools)))
        self.instruments = [Grasper(self.world, scene, settings, name=name, spec=spec,
                                    shaft_tool=next(tool_of) if spec.shaft_radius is not None else None)
                            for name, spec in specs]
        #: the scene's paddle retractors, after the graspers (instruments too: they move and push)
        self.instruments += [Paddle(self.world, scene, settings, spec, name=name, tool=len(shafts) + k)
                             for k, (name, spec) in enumerate(scene.paddles)]
        if sum(_wrist(g) is not None for g in self.instruments) > 1:
            raise SpecError("grippers: at most one grasper may be on a free wrist (wrist_reach): a world has "
                            "one wrist")
        self.grasper = self.instruments[0]
        #: the scene's electrosurgical hooks, after the graspers in the action
        self.hooks = [Hook(self.world, scene, settings, spec, name=name) for name, spec in scene.hooks]
        self.action_size = sum(g.action_size for g in self.instruments) + sum(h.action_size for h in self.hooks)
        self.gauges = StrainGauges(scene.mesh, scene.strain_gauge)
        self.adhesion_width = np.zeros(n)
        self.max_strain = np.zeros(n)
        self.damage = np.zeros(n)  # strain x s: the episode's summed info["cost"]
        self.young_modulus = np.full(n, scene.physics.young_modulus[1])
        self.stuck_at_start = np.zeros((n, scene.mesh.n_vertices), dtype=bool)  # the episode's adhesion
        self.steps = np.zeros(n, dtype=np.int64)
        self.rngs = [np.random.default_rng() for _ in range(n)]

    # the world's and the first grasper's parts, under the names the envs and tools read
    model = property(lambda self: self.world.model)
    solver = property(lambda self: self.world.solver)
    state = property(lambda self: self.world.state)
    control = property(lambda self: self.world.control)
    reaction = property(lambda self: self.world.reaction)
    substeps = property(lambda self: self.world.substeps, lambda self, n: setattr(self.world, "substeps", int(n)))
    adhered = property(lambda self: self.world.stuck)
    grasping = property(lambda self: self.grasper.grasping)
    held = property(lambda self: self.grasper.held)
    held_share = property(lambda self: self.grasper.held_share)
    offsets = property(lambda self: self.grasper.offsets)
    grasp_force = property(lambda self: self.grasper.force)
    grasped_once = property(lambda self: self.grasper.grasped_once)
    gripper = property(lambda self: self.grasper.position,
                       lambda self, value: setattr(self.grasper, "position", value))

    @property
    def x(self) -> np.ndarray:
        """Tissue vertex positions of every world, ``(N, n, 3)`` m (the state's)."""
        return self.world.state.x

    @property
    def grippers(self) -> np.ndarray:
        """Every grasper's jaws, ``(N, K, 3)`` m (K instruments, in action order)."""
        return np.stack([g.position for g in self.instruments], axis=1)

    @property
    def released(self) -> np.ndarray:
        """``(N, n)`` bool: tissue stuck at the episode's start that a hook has freed."""
        return self.stuck_at_start & ~self.world.stuck

    @property
    def hook_tips(self) -> np.ndarray:
        """Every hook's tip, ``(N, H, 3)`` m."""
        return np.stack([h.position for h in self.hooks], axis=1) if self.hooks else np.zeros((self.n, 0, 3))

    @property
    def hooks_energised(self) -> np.ndarray:
        """Whether each hook is energised, ``(N, H)`` bool."""
        return (np.stack([h.energised for h in self.hooks], axis=1) if self.hooks
                else np.zeros((self.n, 0), dtype=bool))

    @property
    def grasping_all(self) -> np.ndarray:
        """Whether each grasper holds tissue, ``(N, K)`` bool."""
        return np.stack([g.grasping for g in self.instruments], axis=1)

    def wrist_patch(self, i: int, picked: np.ndarray, reach: float):
        """The first grasper's :meth:`~heml_gym.envs.instruments.Grasper.wrist_patch`."""
        return self.grasper.wrist_patch(i, picked, reach)

    # ------------------------------------------------------------------ reset
    def reset(self, worlds, seeds=None) -> None:
        """Start new episodes in ``worlds`` (indices), reseeding them from ``seeds`` if given.
        Each draws, in order: the tissue's E, the task's own draws (:meth:`_draw`), each
        instrument's start, then the adhesion width."""
        s = self.scene
        for k, i in enumerate(np.atleast_1d(worlds)):
            if seeds is not None and seeds[k] is not None:
                self.rngs[i] = np.random.default_rng(seeds[k])
            rng = self.rngs[i]
            self.world.reset(i)
            E = rng.uniform(*s.physics.young_modulus)
            self.young_modulus[i] = E
            self.model.set_material(i, s.physics.material_for(E))
            self._draw(i, rng)
            for g in self.instruments:
                g.reset(i, rng)
            for h in self.hooks:
                h.reset(i, rng)
            self.steps[i] = 0
            self.damage[i] = 0.0
            if s.adhesion_vertices is not None:  # drawn last: the other draws stay as without adhesion
                self._stick(i, rng.uniform(*s.spec.adhesion.width))
            self.stuck_at_start[i] = self.world.stuck[i]
        self._measure_start(np.atleast_1d(worlds))

    def _draw(self, i: int, rng: np.random.Generator) -> None:
        """The task's own draws for world ``i``'s new episode (after E, before the instruments)."""

    def _measure_start(self, idx: np.ndarray) -> None:
        """Measure worlds ``idx`` at their episodes' start."""
        self.solver.forget(idx)  # the same seed gives the same episode, whatever came before
        self.max_strain[idx] = self.measure_strain(idx)

    def set_episode(self, i: int, young_modulus: float | None = None, gripper=None,
                    adhesion_width: float | None = None) -> None:
        """Set what :meth:`reset` drew for world ``i``'s episode (before its first step): the
        tissue's ``young_modulus`` (Pa), the first grasper's start (``gripper``, m, inside its
        workspace) and how far out the underside is stuck (``adhesion_width``, m; the scene
        must have adhesion). A replay of a recorded episode (an observation file) starts
        this way."""
        s = self.scene
        if young_modulus is not None:
            E = float(young_modulus)
            if not (math.isfinite(E) and E > 0):
                raise SpecError(f"young_modulus: must be a positive number of pascals, got {young_modulus!r}")
            self.young_modulus[i] = E
            self.model.set_material(i, s.physics.material_for(E))
        if gripper is not None:
            self.grasper.place(i, gripper)
        if adhesion_width is not None:
            if s.adhesion_vertices is None:
                raise SpecError("adhesion_width: this scene has no adhesion (scene.adhesion is null)")
            w = float(adhesion_width)
            if not (math.isfinite(w) and w >= 0):
                raise SpecError(f"adhesion_width: must be a distance >= 0 (m), got {adhesion_width!r}")
            self.world.unstick(i)
            self._stick(i, w)
            self.stuck_at_start[i] = self.world.stuck[i]
        self._measure_start(np.array([i]))

    def _stick(self, i: int, width: float) -> None:
        """Hold world ``i``'s underside where it rests, out to ``width`` (m) from the attachment."""
        s = self.scene
        self.adhesion_width[i] = width
        self.world.stick(i, s.adhesion_vertices[s.adhesion_distance <= width + 1e-9])

    # ------------------------------------------------------------------- step
    def advance(self, actions: np.ndarray, active: np.ndarray | None = None) -> StepOutcome:
        """Apply ``actions`` (N, action_size; clipped to [-1, 1]) to the instruments and step
        the world one control step (worlds outside ``active`` are not simulated); then
        measure the gauge strain. The task turns the outcome into its reward."""
        a = np.asarray(actions, dtype=np.float64)
        if a.size != self.n * self.action_size:
            raise ValueError(f"actions: must have shape ({self.n}, {self.action_size}) (each world's "
                             f"{len(self.instruments)} instrument(s) in turn), got {a.shape}")
        a = np.clip(a.reshape(self.n, self.action_size), -1.0, 1.0)
        sizes = [g.action_size for g in self.instruments] + [h.action_size for h in self.hooks]
        parts = np.split(a, np.cumsum(sizes)[:-1], axis=1)
        parts, hook_parts = parts[:len(self.instruments)], parts[len(self.instruments):]
        first = [g.grasp(part) for g, part in zip(self.instruments, parts)]
        for g, part in zip(self.instruments, parts):
            g.move(part)
        for h, part in zip(self.hooks, hook_parts):
            h.act(part)
        stats = self.world.step(self.settings.control_dt, active=active)
        failed = stats.diverged | ~stats.converged
        for g in self.instruments:
            g.after_step(stats.reaction, failed, stats.tool_force)
        for h in self.hooks:  # on the tissue where the step left it; what it frees moves from the next step
            h.burn(self.settings.control_dt, np.flatnonzero(~failed if active is None else active & ~failed))
        self.steps += 1
        return StepOutcome(parts, first, stats, failed)

    def harm(self, failed: np.ndarray) -> np.ndarray:
        """This step's cost (Safety-Gymnasium's convention: a per-step cost beside the
        reward): ``control_dt`` times the gauge strain's excess over the safe strain
        (strain x s; 0 where the step failed), added to the episode's ``damage``."""
        st = self.settings
        cost = np.where(failed, 0.0, st.control_dt * np.maximum(0.0, self.max_strain - st.safe_strain))
        self.damage = self.damage + cost
        return cost

    def solver_info(self, stats) -> dict:
        """What ``info`` says of the solver's step: diverged, converged, its iterations, its
        sub-step refinement and whether it fell back to Newton's method."""
        return {"simulation_diverged": stats.diverged.copy(), "solver_converged": stats.converged.copy(),
                "newton_iterations": stats.newton_iterations.copy(), "substep_refinement": stats.refinement.copy(),
                "solver_fallback": stats.fallback.copy()}

    def solver_start_info(self, k: int) -> dict:
        """:meth:`solver_info` at the start of ``k`` episodes: nothing failed, at rest."""
        no = np.zeros(k, dtype=bool)
        return {"simulation_diverged": no.copy(), "solver_converged": ~no, "newton_iterations": np.zeros(k, dtype=np.int64),
                "substep_refinement": np.ones(k, dtype=np.int64), "solver_fallback": no.copy()}

    def episode_info(self, worlds) -> dict:
        """What ``info`` says of the episode itself (drawn at its reset): the tissue's
        ``young_modulus`` (Pa) and, with adhesion, its ``adhesion_width`` (m)."""
        info = {"young_modulus": self.young_modulus[worlds].copy()}
        if self.scene.adhesion_vertices is not None:
            info["adhesion_width"] = self.adhesion_width[worlds].copy()
        return info

    def instrument_info(self, worlds=None, start: bool = False) -> dict:
        """Each instrument's ``info`` entries; unless the only instrument is an unnamed
        grasper (whose entries are these), also ``grasp_force`` (the graspers' forces'
        magnitudes summed, N; 0 without graspers) and ``grasping`` (any holds tissue)."""
        parts = [g.start_info(worlds) if start else g.info(worlds) for g in self.instruments]
        info = {k: v for part in parts for k, v in part.items()}
        graspers = [(g, part) for g, part in zip(self.instruments, parts) if g.kind == "grasper"]
        if len(self.instruments) > 1 or not graspers or graspers[0][0].name is not None:  # (paddles alone: 0 N)
            k = self.n if worlds is None else len(np.atleast_1d(worlds))
            info["grasp_force"] = sum((part[g.key("grasp_force")] for g, part in graspers), np.zeros(k))
            info["grasping"] = np.any([part[g.key("grasping")] for g, part in graspers] or [np.zeros(k, dtype=bool)],
                                      axis=0)
        for h in self.hooks:
            info.update(h.info(worlds))
        return info

    def hook_observation(self) -> list[np.ndarray]:
        """The hooks' part of the state observation (each: tip position, m; energised, 0/1)."""
        return [part for h in self.hooks for part in h.observation()]

    def hook_fields(self) -> list[tuple[str, str]]:
        """``(name, unit)`` of the hooks' state entries."""
        return [(f"{h.name}_{entry}", unit) for h in self.hooks for entry, unit in Hook.OBSERVATION]

    def wrist_info(self, worlds) -> dict:
        """``wrist_angle`` (rad): how far the jaws on a free wrist have turned since they
        closed (0 when open), where the scene has them."""
        if all(_wrist(g) is None for g in self.instruments):
            return {}
        turned = self.control.turns[worlds].any(axis=1)
        return {"wrist_angle": np.where(turned, self.control.wrist_angle[worlds], 0.0)}

    # ----------------------------------------------------------- measurements
    def measure_strain(self, worlds) -> np.ndarray:
        """Largest engineering strain ``|l / L - 1|`` of the tissue's strain gauges, per world."""
        worlds = np.atleast_1d(worlds)
        x = self.x if np.array_equal(worlds, np.arange(self.n)) else self.x[worlds]
        return finite(self.gauges.max_strain(x), nan=STRAIN_BOUND)

    def instrument_fields(self) -> list[tuple[str, str]]:
        """``(name, unit)`` of each grasper's state entries, in order (a named grasper's
        prefixed by its name)."""
        return [((f"{g.name}_" if g.name else "") + name, unit) for g in self.instruments for name, unit in g.OBSERVATION]

    def instrument_observation(self) -> list[np.ndarray]:
        """Each grasper's part of the state observation, in action order."""
        return [part for g in self.instruments for part in g.observation()]
