"""A grasper: jaws on a shaft that move, close on tissue, hold it and let it go.

One :class:`Grasper` stands for the same instrument in each of a :class:`heml_gym.World`'s
N worlds. It owns its slice of the action (velocity along x, y, z in units of
``max_speed``, and a grasp command), its part of the state observation (position,
grasping, the tissue's force on it) and its ``info`` entries, and drives the tissue it
holds through the world's :class:`~heml_gym.Control`. Units: m, s, N.
"""

from __future__ import annotations

import numpy as np

from heml_gym.control import rotation

from ..geometry import nearest_triangle_distance
from ..palette import JAW_HALF_SIZE, JAW_OFFSET
from ..spec import SpecError
from .placing import checked_position
from .port import Port


class Grasper:
    """Jaws that close on the tissue within reach and hold it until released.

    ``world``: the :class:`heml_gym.World`; ``scene``: the built scene (its grasp region
    and supports); ``settings``: the task's ``TaskSettings`` (``max_speed``,
    ``control_dt``, ``grasp_reach``, ``jaw_radius``, ``release_command``); ``name``:
    prefixes its ``info`` keys (None: none, for a task's only grasper); ``spec``: its
    ``GripperSpec`` (jaws, start box, workspace; None: the scene's ``gripper``);
    ``shaft_tool``: the world's rigid tool its shaft is (a port's shaft that touches
    tissue), None: none. Closing holds the grasp region's vertices within ``grasp_reach`` of the
    jaws (all of it, or what jaws of ``jaw_length`` cover, their ends by springs when
    ``jaw_ends`` is ``weighted``), or without a region the surface vertices within
    ``jaw_radius``; tissue that is stuck or held by another instrument is not taken.
    Jaws that roll (``spec.roll_speed``, on a port) lie across the shaft, turned by
    :attr:`roll` (rad) about it from the grasp region's axis, and take what lies within
    ``jaw_length / 2`` along them and ``jaw_radius`` across them.
    """

    kind = "grasper"
    #: its slice of the action, entry by entry (on a port: :data:`PORT_ACTION`)
    ACTION = ("velocity_x", "velocity_y", "velocity_z", "grasp")
    PORT_ACTION = ("pitch_rate", "yaw_rate", "insertion_rate", "grasp")
    action_size = len(ACTION)
    #: its part of the state observation, entry by entry: (name, unit)
    OBSERVATION = (tuple((f"gripper_{a}", "m") for a in "xyz") + (("grasping", "-"),)
                   + tuple((f"grasp_force_{a}", "N") for a in "xyz"))

    def __init__(self, world, scene, settings, name: str | None = None, spec=None, shaft_tool: int | None = None):
        gripper = self.spec = scene.spec.gripper if spec is None else spec
        if gripper.wrist_reach is not None and not world.solver.takes_wrist:
            raise SpecError(f"scene.gripper.wrist_reach: jaws on a free wrist are stepped by the quasi_newton "
                            f"integrator, not {scene.physics.integrator}")
        if gripper.jaw_ends == "weighted" and not world.solver.takes_hold_springs:
            raise SpecError(f"scene.gripper.jaw_ends: weighted jaws hold their end vertices by springs, which the "
                            f"{scene.physics.integrator} integrator does not step (use quasi_newton or implicit)")
        self.world, self.scene, self.settings, self.name = world, scene, settings, name
        mesh = scene.mesh
        self._graspable = np.setdiff1d(mesh.surface_vertices, scene.fixed)
        if scene.grasp_patch is not None:  # the patch's surface triangles (or its edges), for its reach
            faces = scene.surface_faces[np.isin(scene.surface_faces, scene.grasp_patch).all(axis=1)]
            if len(faces) == 0:  # a line of vertices: its edges, as degenerate triangles
                e = mesh.edges[np.isin(mesh.edges, scene.grasp_patch).all(axis=1)]
                faces = np.column_stack([e, e[:, 1]])
            self._patch_faces = faces
            rest = mesh.vertices[scene.grasp_patch]
            # the patch's long axis (unit): ``gripper.jaw_length`` is measured along it
            self._patch_axis = np.linalg.svd(rest - rest.mean(axis=0))[2][0] if len(rest) > 1 else np.zeros(3)
        self.start_low, self.start_high = np.asarray(gripper.start_low), np.asarray(gripper.start_high)
        #: the trocar its shaft passes through (None: it moves freely in x, y, z)
        self.port = Port.of(gripper)
        self.shaft_tool = shaft_tool
        self.shaft_force = np.zeros((world.n, 3))  # the shaft's push on the tissue, mean over the last step (N)
        if self.port is not None:
            self.ACTION = self.PORT_ACTION
        #: rad/s of the jaws' roll about the shaft at a command of 1 (None: they do not roll)
        self.roll_speed = gripper.roll_speed
        #: rad: the jaws' turn about the shaft from the grasp region's axis, in [-pi/2, pi/2]
        self.roll = np.zeros(world.n)
        if self.roll_speed is not None:
            if scene.grasp_patch is None:
                raise SpecError("scene.gripper.roll_speed: jaws that roll take part of a grasp region: give the "
                                "scene a grasp region (scene.grasp)")
            self.ACTION = self.PORT_ACTION + ("roll_rate",)
            self.OBSERVATION = self.OBSERVATION + (("jaw_roll", "rad"),)
            self.action_size = len(self.ACTION)
        self.workspace_low, self.workspace_high = np.asarray(gripper.workspace_low), np.asarray(gripper.workspace_high)
        n, nv = world.n, mesh.n_vertices
        self.position = np.zeros((n, 3))
        self.grasping = np.zeros(n, dtype=bool)
        self.held = np.zeros((n, nv), dtype=bool)
        #: each held vertex's share held by the jaws (1: whole; weighted jaws' ends: less)
        self.held_share = np.zeros((n, nv))
        self.offsets = np.zeros((n, nv, 3))
        self.pivot_offset = np.zeros((n, 3))  # a free wrist's pivot from the jaws (m)
        self.force = np.zeros((n, 3))  # the tissue's pull on the jaws, mean over the last step (N)
        self.grasped_once = np.zeros(n, dtype=bool)

    # ------------------------------------------------------------------ episode
    def reset(self, i: int, rng: np.random.Generator) -> None:
        """Copy ``i``'s jaws open at a start drawn from the scene's start box."""
        self.position[i] = rng.uniform(self.start_low, self.start_high)
        self.grasping[i] = False
        self.held[i] = False
        self.held_share[i] = 0.0
        self.grasped_once[i] = False
        self.force[i] = 0.0
        self.shaft_force[i] = 0.0
        self.roll[i] = 0.0
        self._pose_shaft([i])

    def place(self, i: int, position) -> None:
        """Start world ``i``'s jaws at ``position`` (m, (3,), inside the workspace)."""
        self.position[i] = checked_position(position, self.workspace_low, self.workspace_high, "gripper")
        self._pose_shaft([i])

    # --------------------------------------------------------------------- step
    def grasp(self, actions: np.ndarray) -> np.ndarray:
        """Close or open the jaws per the grasp command (``actions[:, 3]``): above 0 closes,
        below ``release_command`` opens, in between they stay. Returns which worlds grasped
        tissue for the first time in their episode."""
        st, world, x = self.settings, self.world, self.world.state.x
        first = np.zeros(world.n, dtype=bool)
        for i in range(world.n):
            close = actions[i, 3] > 0.0
            release = actions[i, 3] < st.release_command  # between it and 0 the jaws stay as they are
            if close and not self.grasping[i]:
                picked, share = self._jaw_vertices(i)
                wrist = self._wrist(i, picked) if picked.size else None
                if wrist is not None:
                    picked, share = wrist[0], np.ones(len(wrist[0]))
                if picked.size:
                    self.grasping[i] = True
                    self.held[i, picked] = True
                    self.held_share[i, picked] = share
                    self.offsets[i, picked] = x[i, picked] - self.position[i]
                    world.control.attach(i, picked, x[i], stiffness=world.hold_stiffness(i, picked, share))
                    if wrist is not None and wrist[2] is not None:
                        world.control.turn(i, picked, wrist[1], wrist[2])
                        self.pivot_offset[i] = wrist[1] - self.position[i]
                    if not self.grasped_once[i]:
                        self.grasped_once[i] = True
                        first[i] = True
            elif release and self.grasping[i]:
                self.grasping[i] = False
                world.control.detach(i, np.flatnonzero(self.held[i]))  # stuck tissue stays stuck
                self.held[i] = False
                self.held_share[i] = 0.0
        return first

    def move(self, actions: np.ndarray) -> None:
        """Move the jaws by the velocity command (``actions[:, :3]``; on a port, its tilt and
        insertion rates) over one control step, within the workspace, and drive the tissue
        they hold there (held tissue cannot be pressed below where it rests on a support)."""
        st, s, control = self.settings, self.scene, self.world.control
        if self.roll_speed is not None:  # roll first, about the shaft through the jaws
            rolled = np.clip(self.roll + actions[:, 4] * self.roll_speed * st.control_dt, -np.pi / 2, np.pi / 2)
            self._turn_held(rolled - self.roll)
            self.roll = rolled
        if self.port is None:
            moved = self.position + actions[:, :3] * st.max_speed * st.control_dt
        else:
            moved = self.port.advance(self.position, actions[:, :3], st.max_speed, st.control_dt)
        self.position = np.clip(moved, self.workspace_low, self.workspace_high)
        if s.supports:
            rest_z = s.mesh.vertices[:, 2]
            for i in np.flatnonzero(self.grasping):
                held = self.held[i]
                self.position[i, 2] = max(self.position[i, 2], (rest_z[held] - self.offsets[i, held, 2]).max())
        for i in np.flatnonzero(self.grasping):
            idx = np.flatnonzero(self.held[i])
            control.drive(i, idx, self.position[i] + self.offsets[i, idx])
            if control.turns[i].any():
                control.drive_wrist(i, self.position[i] + self.pivot_offset[i])
        self._pose_shaft(range(self.world.n))

    def shaft_directions(self) -> np.ndarray:
        """``(N, 3)`` unit: the shaft's direction from the port to the jaws (a port only)."""
        d = self.position - self.port.port
        return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)

    def jaw_axes(self) -> np.ndarray:
        """``(N, 3)`` unit: the axis of jaws that roll, across the shaft, turned by
        :attr:`roll` about it from the grasp region's axis (its part across the shaft; the
        port's first tilt direction where the region's axis runs along the shaft)."""
        u = self.shaft_directions()
        ref = self._patch_axis[None, :] - (u @ self._patch_axis)[:, None] * u
        along_shaft = np.linalg.norm(ref, axis=1) < 1e-6
        if along_shaft.any():
            e1 = self.port.e1[None, :] - (u @ self.port.e1)[:, None] * u
            ref[along_shaft] = e1[along_shaft]
        ref /= np.linalg.norm(ref, axis=1, keepdims=True)
        return np.cos(self.roll)[:, None] * ref + np.sin(self.roll)[:, None] * np.cross(u, ref)

    def jaw_frames(self) -> np.ndarray:
        """``(N, 3, 3)``: the frames of jaws that roll, columns across them, along them
        (:meth:`jaw_axes`) and back up the shaft (a drawing's box: long along the jaws)."""
        u, axis = self.shaft_directions(), self.jaw_axes()
        return np.stack([np.cross(u, axis), axis, -u], axis=2)

    def jaw_boxes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Jaws that roll as the box a drawing shows, in each world: centres ``(N, 3)`` (m),
        its half sizes ``(3,)`` (m: the drawn jaws' across and up, half the jaws' length
        along them) and turns ``(N, 3, 3)`` (:meth:`jaw_frames`); the box stands its half
        height up the shaft from the grasp point, as level jaws stand above it."""
        frames = self.jaw_frames()
        halves = np.array([JAW_HALF_SIZE[0], 0.5 * self.spec.jaw_length, JAW_HALF_SIZE[2]])
        return self.position + JAW_OFFSET[2] * frames[:, :, 2], halves, frames

    def jaw_tiles(self, half: float = 0.003) -> np.ndarray:
        """Jaws that roll, where they are now in each world, for cameras that draw boxes:
        ``(N, k, 3)`` centres (m) of cubes of half size ``half`` (m) along their axis over
        their length, one half size back up the shaft from the grasp point."""
        length = float(self.spec.jaw_length)
        t = np.linspace(-0.5, 0.5, max(2, int(np.ceil(length / half)) + 1)) * length
        centres = self.position - half * self.shaft_directions()
        return centres[:, None, :] + t[None, :, None] * self.jaw_axes()[:, None, :]

    def _turn_held(self, angles: np.ndarray) -> None:
        """Turn the tissue held in each world by ``angles`` (rad) about the shaft through
        the jaws (jaws that roll while they hold)."""
        u = self.shaft_directions()
        for i in np.flatnonzero(self.grasping & (angles != 0.0)):
            turn = rotation(u[i], float(angles[i]))
            held = self.held[i]
            self.offsets[i, held] = self.offsets[i, held] @ turn.T
            self.pivot_offset[i] = turn @ self.pivot_offset[i]

    def _pose_shaft(self, worlds) -> None:
        """Pose the shaft's rigid tool for the jaws where they are (a touching shaft only)."""
        if self.shaft_tool is None:
            return
        centres, rotations = self.port.shaft_poses(self.position[worlds])
        for k, i in enumerate(worlds):
            self.world.control.pose_tool(i, self.shaft_tool, centres[k], rotations[k])

    def shaft_tiles(self) -> tuple[np.ndarray, float] | None:
        """A touching shaft where it is now in each world, for cameras that draw boxes:
        cubes along it from its end to the port, ``(N, k, 3)`` centres (m) no further apart
        than their half size (m, the shaft's radius); None without a touching shaft."""
        if self.shaft_tool is None:
            return None
        radius = float(self.spec.shaft_radius)
        ends = self.port.shaft_ends(self.position)
        longest = float(np.linalg.norm(ends - self.port.port, axis=1).max())
        t = np.linspace(0.0, 1.0, max(2, int(np.ceil(longest / radius)) + 1))
        return ends[:, None, :] + t[None, :, None] * (self.port.port - ends)[:, None, :], radius

    def after_step(self, reaction: np.ndarray, failed: np.ndarray, tool_force: np.ndarray | None = None) -> None:
        """Take the step's outcome: where a free wrist turned the held patch, the tissue's
        pull on the jaws (the held vertices' reactions, 0 where the step failed) and, for a
        touching shaft, its push on the tissue (``tool_force``: the step's, ``(N, T, 3)``)."""
        if self.shaft_tool is not None and tool_force is not None:
            self.shaft_force = np.where(failed[:, None], 0.0, tool_force[:, self.shaft_tool])
        x, turns = self.world.state.x, self.world.control.turns
        for i in np.flatnonzero(self.grasping & turns.any(axis=1)):  # the patch has turned
            self.offsets[i, self.held[i]] = x[i, self.held[i]] - self.position[i]
        held_reaction = np.where(self.held[:, :, None], reaction, 0.0).sum(axis=1)
        self.force = np.where(failed[:, None], 0.0, -held_reaction)

    # --------------------------------------------------------- what it reports
    def observation(self) -> list[np.ndarray]:
        """Its part of the state observation: position (m), grasping (0/1), force (N), and
        for jaws that roll their roll (rad)."""
        parts = [self.position, self.grasping[:, None].astype(np.float64), self.force]
        return parts + [self.roll[:, None]] if self.roll_speed is not None else parts

    def key(self, name: str) -> str:
        return name if self.name is None else f"{self.name}_{name}"

    def info(self, worlds=None) -> dict:
        """``grasp_force`` (N, its magnitude) and ``grasping`` of ``worlds`` (default all)."""
        worlds = slice(None) if worlds is None else worlds
        out = {self.key("grasp_force"): np.linalg.norm(self.force[worlds], axis=1),
               self.key("grasping"): self.grasping[worlds].copy()}
        if self.shaft_tool is not None:  # a touching shaft's push on the tissue (N, its magnitude)
            out[self.key("shaft_force")] = np.linalg.norm(self.shaft_force[worlds], axis=1)
        return out

    def start_info(self, worlds) -> dict:
        """:meth:`info` at an episode's start: nothing held yet."""
        out = {self.key("grasp_force"): np.zeros(len(worlds)), self.key("grasping"): self.grasping[worlds].copy()}
        if self.shaft_tool is not None:
            out[self.key("shaft_force")] = np.zeros(len(worlds))
        return out

    # ---------------------------------------------------------------- the jaws
    def _jaw_vertices(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """The tissue vertices that closing the jaws of world ``i`` holds (maybe none), and
        the share of each that the jaws hold (1: whole; below 1: weighted jaws' ends)."""
        picked, share = self._reached_vertices(i)
        keep = ~self.world.control.kinematic[i, picked]  # not stuck, not held by another instrument
        return picked[keep], share[keep]

    def wrist_patch(self, i: int, picked: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray | None]:
        """What jaws on a free wrist hold when they close on ``picked`` (vertex indices) in
        world ``i``: the vertices within ``reach`` (m, at rest) of one of them, not fixed or
        stuck (indices, ascending), and the jaws' axis (unit: the longest direction of
        ``picked`` at rest, else of the patch; None when that is a single vertex, which has
        no angle). The scene's wrist (``scene.gripper.wrist_reach``) and the calibration's
        (:func:`heml_gym.envs.observations.control_log`) both take it."""
        rest = self.scene.mesh.vertices
        near = np.zeros(len(rest), dtype=bool)
        for p in rest[picked]:
            near |= np.linalg.norm(rest - p, axis=1) <= reach
        near[picked] = True
        patch = np.flatnonzero(near & ~self.world.model.fixed & ~self.world.stuck[i])
        shape = rest[picked] if len(picked) > 1 else rest[patch]
        if len(shape) < 2:
            return patch, None
        return patch, np.linalg.svd(shape - shape.mean(axis=0), full_matrices=False)[2][0]

    def _wrist(self, i: int, picked: np.ndarray):
        """``(patch, pivot, axis)`` of the scene's free wrist closing on ``picked`` in world
        ``i`` (:meth:`wrist_patch`; the pivot: the patch's middle, m), None without one."""
        reach = self.spec.wrist_reach
        if reach is None:
            return None
        patch, axis = self.wrist_patch(i, picked, reach)
        return patch, self.world.state.x[i, patch].mean(axis=0), axis

    def _reached_vertices(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        st, patch = self.settings, self.scene.grasp_patch
        x = self.world.state.x[i]
        if patch is not None:  # within reach of the patch's surface (or of its vertices)
            nearest = min(np.linalg.norm(x[patch] - self.position[i], axis=1).min(),
                          nearest_triangle_distance(self.position[i], x, self._patch_faces))
            if nearest > st.grasp_reach:
                return patch[:0], np.zeros(0)
            gripper = self.spec
            if self.roll_speed is not None:
                return self._rolled_jaw_vertices(i)
            if gripper.jaw_length is None:
                return patch, np.ones(len(patch))
            if gripper.jaw_ends == "weighted":
                share = self._jaw_shares(i, gripper.jaw_length)
                return patch[share > 0.0], share[share > 0.0]
            # the part of the patch between the jaws: within jaw_length / 2 of them along
            # the patch's long axis (at least the nearest such vertex)
            along = np.abs((x[patch] - self.position[i]) @ self._patch_axis)
            picked = patch[(along <= gripper.jaw_length / 2) | (along == along.min())]
            return picked, np.ones(len(picked))
        d = np.linalg.norm(x[self._graspable] - self.position[i], axis=1)
        held = (d <= st.jaw_radius) | (d == d.min())
        picked = self._graspable[held & (d <= st.grasp_reach)]
        return picked, np.ones(len(picked))

    def _rolled_jaw_vertices(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """What rolled jaws take of the grasp region in world ``i``: they close on the
        region's part nearest them across their axis, its vertices within ``jaw_radius``
        across of it; of those the ones within ``jaw_length / 2`` along them (weighted
        ends: by their share; at least the nearest along), and each one's share."""
        patch, gripper = self.scene.grasp_patch, self.spec
        axis = self.jaw_axes()[i]
        r = self.world.state.x[i, patch] - self.position[i]
        across = r @ np.cross(self.shaft_directions()[i], axis)
        between = np.abs(across - across[np.argmin(np.abs(across))]) <= self.settings.jaw_radius
        along = np.abs(r @ axis)
        if gripper.jaw_ends == "weighted":
            share = np.where(between, self._jaw_shares(i, gripper.jaw_length, axis), 0.0)
        else:
            share = (between & (along <= gripper.jaw_length / 2)).astype(np.float64)
        if not (share > 0).any():  # at least the vertex between the jaws nearest their middle
            share[np.flatnonzero(between)[np.argmin(along[between])]] = 1.0
        return patch[share > 0], share[share > 0]

    def _jaw_shares(self, i: int, jaw_length: float, axis: np.ndarray | None = None) -> np.ndarray:
        """Each grasp-patch vertex's share (0..1) inside jaws ``jaw_length`` (m) long centred
        on world ``i``'s jaws: the overlap of its row's span along the patch's axis (from
        midway to the previous row to midway to the next; at the patch's ends, as far out as
        in) with the jaws, over the span. Rows: the vertices' rest places along the axis,
        to 1e-6 m. ``axis``: the jaws' (unit; None: the patch's long axis)."""
        patch = self.scene.grasp_patch
        axis = self._patch_axis if axis is None else axis
        rest = self.scene.mesh.vertices[patch] @ axis
        rows, row_of = np.unique(np.round(rest, 6), return_inverse=True)
        if len(rows) == 1:
            return np.ones(len(patch))
        mids = 0.5 * (rows[1:] + rows[:-1])
        low = np.concatenate([[2 * rows[0] - mids[0]], mids])
        high = np.concatenate([mids, [2 * rows[-1] - mids[-1]]])
        # the jaws' centre along the axis, in the rest frame: their offset from the patch's
        # current centre, added to the patch's rest centre
        x = self.world.state.x[i, patch]
        centre = rest.mean() + (self.position[i] - x.mean(axis=0)) @ axis
        overlap = np.clip(np.minimum(high, centre + jaw_length / 2) - np.maximum(low, centre - jaw_length / 2), 0.0,
                          None)
        share = (overlap / (high - low))[row_of]
        if not (share > 0).any():  # (jaws between two rows' spans cannot be: the spans tile the axis)
            share[np.argmin(np.abs(rest - centre))] = 1.0
        return share
