"""An electrosurgical hook: it frees tissue from what it is stuck to, where it touches.

One :class:`Hook` stands for the same instrument in each of a :class:`heml_gym.World`'s N
worlds. Its action is a velocity along x, y, z in units of ``max_speed`` (or, on a port,
the port's tilt and insertion rates) and an energy command (above 0: energised). While
energised it delivers its ``power`` to the tissue within ``reach`` of its tip, shared
equally among the surface vertices there. A stuck vertex (the world's adhesion) takes
its share until it has had ``release_energy`` times its share of the surface, and is
then released (:meth:`heml_gym.World.release`): the tissue is free there. What the other
vertices take is collateral energy, harm to tissue that was not attachment. Nothing
happens in air. The hook does not push tissue. Units: m, s, W, J.
"""

from __future__ import annotations

import numpy as np

from .placing import checked_position
from .port import Port


def surface_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Each vertex's share of the surface (m^2): a third of the area of every surface
    triangle (``faces (f, 3)``) it is a corner of; 0 off the surface."""
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    out = np.zeros(len(vertices))
    for k in range(3):
        np.add.at(out, faces[:, k], area / 3.0)
    return out


class Hook:
    """An electrosurgical hook in every world of ``world``: ``scene`` (the built scene: its
    mesh's surface), ``settings`` (the task's ``max_speed``, ``control_dt``), ``spec`` (a
    ``HookSpec``), ``name`` (prefixes its ``info`` keys)."""

    kind = "hook"
    ACTION = ("velocity_x", "velocity_y", "velocity_z", "energy")
    PORT_ACTION = ("pitch_rate", "yaw_rate", "insertion_rate", "energy")
    action_size = len(ACTION)
    #: its part of the state observation, entry by entry: (name, unit)
    OBSERVATION = tuple((f"tip_{a}", "m") for a in "xyz") + (("energised", "-"),)

    def __init__(self, world, scene, settings, spec, name: str = "hook"):
        self.world, self.scene, self.settings, self.spec, self.name = world, scene, settings, spec, name
        self.port = Port.of(spec)
        if self.port is not None:
            self.ACTION = self.PORT_ACTION
        self.start_low, self.start_high = np.asarray(spec.start_low), np.asarray(spec.start_high)
        self.workspace_low, self.workspace_high = np.asarray(spec.workspace_low), np.asarray(spec.workspace_high)
        mesh = scene.mesh
        self._surface = np.unique(scene.surface_faces)
        self.area = surface_areas(mesh.vertices, scene.surface_faces)  # m^2 per vertex, at rest
        n, nv = world.n, mesh.n_vertices
        self.position = np.zeros((n, 3))
        self.energised = np.zeros(n, dtype=bool)
        self.taken = np.zeros((n, nv))  # J each stuck vertex has taken towards its release
        self.collateral = np.zeros(n)  # J into tissue that was not attachment, this step
        self.released = np.zeros(n, dtype=np.int64)  # vertices released, this step
        self.released_area = np.zeros(n)  # m^2 of attachment released this episode

    # ------------------------------------------------------------------ episode
    def reset(self, i: int, rng: np.random.Generator) -> None:
        """World ``i``'s hook off, at a start drawn from its start box."""
        self.position[i] = rng.uniform(self.start_low, self.start_high)
        self.energised[i] = False
        self.taken[i] = 0.0
        self.collateral[i] = 0.0
        self.released[i] = 0
        self.released_area[i] = 0.0

    def place(self, i: int, position) -> None:
        """World ``i``'s tip at ``position`` (m, (3,), inside the workspace)."""
        self.position[i] = checked_position(position, self.workspace_low, self.workspace_high, self.name or "hook")

    # --------------------------------------------------------------------- step
    def act(self, actions: np.ndarray) -> None:
        """Energise where the energy command (``actions[:, 3]``) is above 0, and move the tip
        by the velocity (or port) command over one control step, within the workspace."""
        st = self.settings
        self.energised = actions[:, 3] > 0.0
        if self.port is None:
            moved = self.position + actions[:, :3] * st.max_speed * st.control_dt
        else:
            moved = self.port.advance(self.position, actions[:, :3], st.max_speed, st.control_dt)
        self.position = np.clip(moved, self.workspace_low, self.workspace_high)

    def burn(self, dt: float, worlds=None) -> None:
        """Deliver ``dt`` seconds of power in the energised ``worlds`` (default all) to the
        tissue within reach of the tip where it is now; release the stuck vertices that have
        taken enough."""
        self.collateral[:] = 0.0
        self.released[:] = 0
        worlds = range(self.world.n) if worlds is None else worlds
        x, stuck, spec = self.world.state.x, self.world.stuck, self.spec
        for i in worlds:
            if not self.energised[i]:
                continue
            surface = self._surface
            near = surface[np.linalg.norm(x[i, surface] - self.position[i], axis=1) <= spec.reach]
            if near.size == 0:  # in air
                continue
            share = spec.power * dt / near.size  # J per vertex within reach
            bonded = near[stuck[i, near]]
            self.collateral[i] = share * (near.size - bonded.size)
            self.taken[i, bonded] += share
            freed = bonded[self.taken[i, bonded] >= spec.release_energy * self.area[bonded]]
            if freed.size:
                self.world.release(i, freed)
                self.released[i] = freed.size
                self.released_area[i] += self.area[freed].sum()

    # --------------------------------------------------------- what it reports
    def observation(self) -> list[np.ndarray]:
        """Its part of a state observation: tip position (m), energised (0/1)."""
        return [self.position, self.energised[:, None].astype(np.float64)]

    def info(self, worlds=None) -> dict:
        """``{name}_energised``, ``{name}_collateral_energy`` (J this step),
        ``{name}_released`` (vertices freed this step) and ``{name}_released_area`` (m^2 this
        episode) of ``worlds`` (default all)."""
        w = slice(None) if worlds is None else worlds
        return {f"{self.name}_energised": self.energised[w].copy(),
                f"{self.name}_collateral_energy": self.collateral[w].copy(),
                f"{self.name}_released": self.released[w].copy(),
                f"{self.name}_released_area": self.released_area[w].copy()}
