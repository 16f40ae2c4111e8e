"""A paddle retractor: a rigid blade that pushes and lifts tissue and holds none.

One :class:`Paddle` stands for the same instrument in each of a :class:`heml_gym.World`'s
N worlds. It is one of the world's rigid tools (:class:`heml_gym.Box`, thin along its
local z), posed each step where its action takes it. Its action is a velocity along x,
y, z in units of its ``max_speed`` and a tilt rate about its local y in units of its
``angular_speed``. Its part of the state observation is its centre, its tilt and the
force it exerts on the tissue (mean over the step). Where it presses, it also reports
the contact pressure: its push over the area of tissue it touches. Units: m, s, rad, N, Pa.

To the solver the blade is solid to :data:`BACKING` (30 mm) below its face. Contact is on
the tissue's vertices, and a blade thinner than the mesh's cells moved sideways under
tissue would otherwise catch vertices deeper than half its thickness and push them out
through its underside (the lobe then falls through the blade). A paddle lifts from
below, so no tissue belongs under its face; the backing changes nothing else.
"""

from __future__ import annotations

import numpy as np

from heml_gym.tools import Box

from .placing import checked_position

#: m: the depth below the blade's face that is solid to the solver (at least the blade's thickness)
BACKING = 0.03
#: m: tissue this close to the blade touches it (the penalty of the implicit solvers lets it in
#: a little; explicit sub-steps put it on the surface)
TOUCH = 1e-6


def tilt_rotation(angle: float) -> np.ndarray:
    """The rotation (3, 3) that pitches the blade by ``angle`` (rad) about y: its local z
    (the blade's normal) turns from +z towards +x."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


class Paddle:
    """A paddle retractor in every world of ``world``: ``scene`` (the built scene),
    ``settings`` (the task's ``control_dt``), ``spec`` (a ``PaddleSpec``), ``name``
    (prefixes its ``info`` keys), ``tool`` (its index among the world's rigid tools).

    It has a grasper's attributes where a task reads them (``position``, ``force``,
    ``grasping`` and ``held``: always empty), so that a task treats every instrument
    alike."""

    kind = "paddle"
    ACTION = ("velocity_x", "velocity_y", "velocity_z", "tilt_rate")
    action_size = len(ACTION)
    #: its part of the state observation, entry by entry: (name, unit)
    OBSERVATION = (tuple((f"centre_{a}", "m") for a in "xyz") + (("tilt", "rad"),)
                   + tuple((f"push_force_{a}", "N") for a in "xyz"))

    @staticmethod
    def blade(spec) -> Box:
        """The rigid tool a paddle of ``spec`` is to the solver: its blade, extended
        :data:`BACKING` below its face (see the module docstring)."""
        hx, hy, hz = spec.half_extents
        return Box((hx, hy, max(hz, BACKING / 2)))

    def _centre_offset(self) -> float:
        """How far (m) the solver's box's centre lies below the blade's centre, along the blade's normal."""
        hz = self.spec.half_extents[2]
        return max(hz, BACKING / 2) - hz

    def __init__(self, world, scene, settings, spec, name: str = "paddle", tool: int = 0):
        self.world, self.scene, self.settings, self.spec, self.name, self.tool = world, scene, settings, spec, name, tool
        self.start_low, self.start_high = np.asarray(spec.start_low), np.asarray(spec.start_high)
        self.workspace_low, self.workspace_high = np.asarray(spec.workspace_low), np.asarray(spec.workspace_high)
        mesh = scene.mesh
        free = np.ones(mesh.n_vertices, dtype=bool)
        free[scene.fixed] = False
        surface = np.zeros(mesh.n_vertices, dtype=bool)
        surface[np.unique(scene.surface_faces)] = True
        self._surface = np.flatnonzero(surface & free)  # the vertices that can feel its pressure
        n, nv = world.n, mesh.n_vertices
        self.position = np.zeros((n, 3))
        self.tilt = np.zeros(n)
        self.force = np.zeros((n, 3))  # its push on the tissue, mean over the last step (N)
        self.pressure = np.zeros(n)  # contact pressure at the step's end (Pa)
        self.grasping = np.zeros(n, dtype=bool)  # (a paddle holds nothing)
        self.grasped_once = np.zeros(n, dtype=bool)
        self.held = np.zeros((n, nv), dtype=bool)
        self.held_share = np.zeros((n, nv))
        self.offsets = np.zeros((n, nv, 3))
        self.shaft_force = np.zeros((n, 3))

    def key(self, entry: str) -> str:
        """The ``info`` key of ``entry`` for this paddle (its name first)."""
        return f"{self.name}_{entry}"

    # ------------------------------------------------------------------ episode
    def reset(self, i: int, rng: np.random.Generator) -> None:
        """World ``i``'s blade level, at a start drawn from its start box."""
        self.position[i] = rng.uniform(self.start_low, self.start_high)
        self.tilt[i] = 0.0
        self.force[i] = 0.0
        self.pressure[i] = 0.0
        self._pose([i])

    def place(self, i: int, position) -> None:
        """Start world ``i``'s blade centre at ``position`` (m, (3,), inside the workspace)."""
        self.position[i] = checked_position(position, self.workspace_low, self.workspace_high, "gripper")
        self._pose([i])

    def _pose(self, worlds) -> None:
        below = self._centre_offset()
        for i in worlds:
            rotation = tilt_rotation(self.tilt[i])
            self.world.control.pose_tool(i, self.tool, self.position[i] - below * rotation[:, 2], rotation)

    # --------------------------------------------------------------------- step
    def grasp(self, actions: np.ndarray) -> np.ndarray:
        """A paddle grasps nothing: no world grasps for the first time."""
        return np.zeros(self.world.n, dtype=bool)

    def move(self, actions: np.ndarray) -> None:
        """Move the blade by the velocity command (``actions[:, :3]``, in units of
        ``max_speed``) and tilt it by the tilt command (``actions[:, 3]``, in units of
        ``angular_speed``) over one control step, within the workspace and ``max_tilt``."""
        sp, dt = self.spec, self.settings.control_dt
        self.position = np.clip(self.position + actions[:, :3] * sp.max_speed * dt, self.workspace_low,
                                self.workspace_high)
        self.tilt = np.clip(self.tilt + actions[:, 3] * sp.angular_speed * dt, -sp.max_tilt, sp.max_tilt)
        self._pose(range(self.world.n))

    def after_step(self, reaction, failed, tool_force) -> None:
        """Read the blade's push (the step's mean) and its contact pressure at the step's
        end; 0 where the step failed."""
        self.force = np.where(failed[:, None], 0.0, tool_force[:, self.tool])
        self.pressure = np.where(failed, 0.0, self.contact_pressure())

    def contact_pressure(self, worlds=None) -> np.ndarray:
        """Contact pressure (Pa) per world: the blade's push (its force on the tissue, the
        step's mean) over the area of tissue it touches at the step's end (each surface
        vertex within :data:`TOUCH` of the blade or inside it, a third of each of its surface
        triangles, projected on the blade's face there); 0 where it touches nothing. This
        mean over the contact converges as the mesh refines; a vertex's own force over its
        area would not (the blade's edges load single vertices)."""
        worlds = range(self.world.n) if worlds is None else worlds
        tools = self.world.model.tools
        faces = self.scene.surface_faces
        out = np.zeros(len(worlds))
        for k, i in enumerate(worlds):
            x = self.world.state.x[i]
            d, normal = tools.each_distance(x[self._surface], self.world.control.tool_pose[i])
            touching = d[self.tool] < TOUCH
            if not touching.any():
                continue
            inside = np.zeros(len(x), dtype=bool)
            inside[self._surface[touching]] = True
            blade_normal = np.zeros((len(x), 3))
            blade_normal[self._surface] = normal[self.tool]
            a, b, c = x[faces[:, 0]], x[faces[:, 1]], x[faces[:, 2]]
            area_vector = 0.5 * np.cross(b - a, c - a)  # (f, 3): area (m^2) times the unit normal
            area = 0.0
            for corner in range(3):  # each touching corner's third, projected on the blade's face
                v = faces[:, corner]
                on = inside[v]
                area += np.abs(np.einsum("fa,fa->f", area_vector[on], blade_normal[v[on]])).sum() / 3.0
            out[k] = float(np.linalg.norm(self.force[i])) / area if area > 0 else 0.0
        return np.nan_to_num(out, nan=0.0, posinf=0.0)

    def blade_tiles(self, nx: int = 4, ny: int = 8) -> tuple[np.ndarray, tuple]:
        """The blade cut into ``nx`` x ``ny`` tiles where it is now in each world: their
        centres ``(N, nx ny, 3)`` (m) and half sizes (m), for cameras that draw boxes (a
        tilted blade's tiles stay level: a drawing, not the contact shape)."""
        hx, hy, hz = self.spec.half_extents
        u, v = np.meshgrid((np.arange(nx) + 0.5) / nx * 2 * hx - hx, (np.arange(ny) + 0.5) / ny * 2 * hy - hy,
                           indexing="ij")
        local = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], axis=1)  # (m, 3) in the blade's frame
        rotations = np.stack([tilt_rotation(a) for a in self.tilt])  # (N, 3, 3)
        return self.position[:, None, :] + np.einsum("nab,mb->nma", rotations, local), (hx / nx, hy / ny, hz)

    # --------------------------------------------------------- what it reports
    def observation(self) -> list[np.ndarray]:
        """Its part of a state observation: centre (m), tilt (rad), push force (N)."""
        return [self.position, self.tilt[:, None], self.force]

    def info(self, worlds=None) -> dict:
        """``{name}_push_force`` (N, its magnitude), ``{name}_contact_pressure`` (Pa) and
        ``{name}_tilt`` (rad) of ``worlds`` (default all)."""
        w = slice(None) if worlds is None else worlds
        return {self.key("push_force"): np.linalg.norm(self.force[w], axis=1), self.key("contact_pressure"): self.pressure[w].copy(),
                self.key("tilt"): self.tilt[w].copy()}

    def start_info(self, worlds=None) -> dict:
        """:meth:`info` at an episode's start (before any step)."""
        return self.info(worlds)
