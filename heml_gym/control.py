"""The control: what the user drives each step, for N worlds at once."""

from __future__ import annotations

import numpy as np

from .tools import PARKED

__all__ = ["Control", "rotation"]


def rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """The (3, 3) rotation by ``angle`` (rad) about the unit vector ``axis`` (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


class Control:
    """Held (kinematic) vertices, where they go, and external forces, per world.

    Attributes
    ----------
    kinematic : (N, n) bool
        Vertices held by a gripper: they follow :attr:`targets` exactly, or, where
        :attr:`hold_stiffness` is positive, through a spring.
    targets : (N, n, 3) float, m
        Where the kinematic vertices (or their springs' anchors) are at the end of the next
        step; they move there along a straight line at constant speed during the step.
    hold_stiffness : (N, n) float, N/m
        0: a kinematic vertex is held exactly; positive: it is held by a spring of that
        stiffness to its anchor (a vertex the jaws hold only in part). Every solver
        steps it (the explicit one with a critical step shortened for the springs).
    anchors : (N, n, 3) float, m
        Where each spring's anchor is (the solver moves it towards :attr:`targets`).
    external_forces : (N, n, 3) float, N
        Applied to every vertex every step (a tip load, a probe).
    turns : (N, n) bool
        Held vertices on a free wrist (:meth:`turn`): a patch the jaws hold rigidly but
        that turns about the jaws' axis to where the tissue's torque on it vanishes. They
        are at ``pivot + R(angle) arms`` (their :attr:`targets` are not read), and the
        quasi-Newton solver finds the angle in every sub-step; the other solvers refuse them.
    arms : (N, n, 3) float, m
        Each wrist vertex's place relative to the pivot at angle 0.
    wrist_axis : (N, 3) float
        The jaws' axis (unit), which the patch turns about.
    pivot : (N, 3) float, m
        The point on the axis the patch turns about, where it is now (the solver moves
        it to :attr:`pivot_target` along a straight line during a step).
    pivot_target : (N, 3) float, m
        Where the pivot is at the end of the next step.
    wrist_angle : (N,) float, rad
        The patch's angle about the axis since the jaws took it (the solver's).
    wrist_stiffness : (N,) float, N/m
        The solver's latest estimate of ``d^2 Phi / ds^2`` (``s`` = angle times the patch's
        radius about the axis): its warm start, 0 when none.
    tool_pose : (N, T, 12) float
        Each rigid tool's pose (:mod:`heml_gym.tools`) at the end of the next step: its
        centre (m), then its rotation matrix row by row (its columns: the tool's axes);
        until posed, a tool waits far away (:data:`heml_gym.tools.PARKED`).
    """

    def __init__(self, n_worlds: int, n_vertices: int, n_tools: int = 0):
        self.kinematic = np.zeros((n_worlds, n_vertices), dtype=bool)
        self.targets = np.zeros((n_worlds, n_vertices, 3))
        self.external_forces = np.zeros((n_worlds, n_vertices, 3))
        self.hold_stiffness = np.zeros((n_worlds, n_vertices))
        self.anchors = np.zeros((n_worlds, n_vertices, 3))
        self.turns = np.zeros((n_worlds, n_vertices), dtype=bool)
        self.arms = np.zeros((n_worlds, n_vertices, 3))
        self.wrist_axis = np.zeros((n_worlds, 3))
        self.pivot = np.zeros((n_worlds, 3))
        self.pivot_target = np.zeros((n_worlds, 3))
        self.wrist_angle = np.zeros(n_worlds)
        self.wrist_stiffness = np.zeros(n_worlds)
        self.tool_pose = np.zeros((n_worlds, n_tools, 12))
        self.tool_pose[:, :, :3] = PARKED
        self.tool_pose[:, :, 3:] = np.eye(3).ravel()

    def pose_tool(self, world: int, tool: int, position, rotation=None) -> None:
        """Pose rigid tool ``tool`` of world ``world`` for the next step: its centre at
        ``position`` (m, (3,)), turned by ``rotation`` ((3, 3), orthonormal; None: as
        built)."""
        if not 0 <= tool < self.tool_pose.shape[1]:
            raise ValueError(f"tool must be in [0, {self.tool_pose.shape[1]}) (the model's tools), got {tool}")
        p = np.asarray(position, dtype=np.float64)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"position must be 3 finite coordinates (m), got {position!r}")
        r = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        if r.shape != (3, 3) or not np.all(np.isfinite(r)) or not np.allclose(r @ r.T, np.eye(3), atol=1e-9) \
                or np.linalg.det(r) < 0:
            raise ValueError("rotation must be a (3, 3) rotation matrix (orthonormal, determinant +1)")
        self.tool_pose[world, tool, :3] = p
        self.tool_pose[world, tool, 3:] = r.ravel()

    @property
    def n_worlds(self) -> int:
        return self.kinematic.shape[0]

    def indices(self, vertices) -> np.ndarray:
        """Vertex indices from indices or an ``(n,)`` bool mask, checked against ``[0, n)``."""
        n = self.kinematic.shape[1]
        arr = np.asarray(vertices)
        if arr.dtype == bool:
            if arr.shape != (n,):
                raise ValueError(f"vertex mask must have shape ({n},), got {arr.shape}")
            return np.flatnonzero(arr)
        if arr.size and not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"vertices must be integer indices or a bool mask, got {arr.dtype}")
        idx = arr.astype(np.int64).ravel()
        if idx.size and (idx.min() < 0 or idx.max() >= n):
            raise ValueError(f"vertex indices must lie in [0, {n})")
        return idx

    def attach(self, world: int, vertices, positions, stiffness=None) -> None:
        """Hold ``vertices`` of ``world`` where they are (``positions``: their current
        positions, m, ``(k, 3)`` or the world's whole ``(n, 3)`` array): exactly, or, with
        ``stiffness`` (N/m, one number or one per vertex; 0: exactly), each by a spring to
        an anchor placed there."""
        idx = self.indices(vertices)
        positions = np.asarray(positions, dtype=np.float64)
        here = positions[idx] if positions.shape == (self.kinematic.shape[1], 3) else positions.reshape(len(idx), 3)
        k = np.zeros(len(idx)) if stiffness is None else np.broadcast_to(np.asarray(stiffness, dtype=np.float64),
                                                                        (len(idx),))
        if not np.all(np.isfinite(k) & (k >= 0.0)):
            raise ValueError("attach: stiffness must be finite and >= 0 N/m (0: held exactly)")
        self.kinematic[world, idx] = True
        self.targets[world, idx] = here
        self.hold_stiffness[world, idx] = k
        self.anchors[world, idx] = here

    def drive(self, world: int, vertices, targets) -> None:
        """Kinematic ``vertices`` of ``world`` reach ``targets`` (m, ``(k, 3)``) at the end of
        the next step."""
        idx = self.indices(vertices)
        targets = np.asarray(targets, dtype=np.float64).reshape(len(idx), 3)
        if not np.all(self.kinematic[world, idx]):
            raise ValueError("drive() needs attached (kinematic) vertices: attach them first")
        if not np.all(np.isfinite(targets)):
            raise ValueError("kinematic targets must be finite")
        self.targets[world, idx] = targets

    def turn(self, world: int, vertices, pivot, axis) -> None:
        """Put held ``vertices`` of ``world`` on a free wrist: from now on they keep their
        places relative to each other and to the ``pivot`` (m, (3,)), which follows
        :meth:`drive_wrist`, and turn about ``axis`` (3,) through it to where the tissue's
        torque about the axis vanishes (the wrist is massless: the patch's inertia and
        weight are the jaws'). One patch per world: a second call replaces the first."""
        idx = self.indices(vertices)
        pivot = np.asarray(pivot, dtype=np.float64).reshape(-1)
        axis = np.asarray(axis, dtype=np.float64).reshape(-1)
        if not idx.size:
            raise ValueError("turn: give at least one vertex")
        if not np.all(self.kinematic[world, idx] & (self.hold_stiffness[world, idx] == 0.0)):
            raise ValueError("turn: the wrist's vertices must be held exactly (attach them first, no springs)")
        if pivot.shape != (3,) or not np.all(np.isfinite(pivot)):
            raise ValueError(f"turn: pivot must be 3 finite coordinates (m), got {pivot.tolist()}")
        norm = float(np.linalg.norm(axis)) if axis.shape == (3,) else 0.0
        if not (np.isfinite(norm) and norm > 0.0):
            raise ValueError(f"turn: axis must be a finite nonzero (3,) vector, got {axis.tolist()}")
        arms = self.targets[world, idx] - pivot
        radial = arms - np.outer(arms @ axis / norm, axis / norm)
        if not np.any(np.sum(radial * radial, axis=1) > 0.0):
            raise ValueError("turn: every vertex lies on the axis, so the patch has no angle to turn to")
        self.turns[world] = False
        self.turns[world, idx] = True
        self.arms[world] = 0.0
        self.arms[world, idx] = arms
        self.wrist_axis[world] = axis / norm
        self.pivot[world] = pivot
        self.pivot_target[world] = pivot
        self.wrist_angle[world] = 0.0
        self.wrist_stiffness[world] = 0.0

    def drive_wrist(self, world: int, pivot) -> None:
        """The wrist's pivot of ``world`` reaches ``pivot`` (m, (3,)) at the end of the next step."""
        pivot = np.asarray(pivot, dtype=np.float64).reshape(-1)
        if not self.turns[world].any():
            raise ValueError("drive_wrist() needs a wrist: call turn() first")
        if pivot.shape != (3,) or not np.all(np.isfinite(pivot)):
            raise ValueError(f"drive_wrist: pivot must be 3 finite coordinates (m), got {pivot.tolist()}")
        self.pivot_target[world] = pivot

    def wrist_places(self, world: int) -> np.ndarray:
        """``(k, 3)`` m: where the wrist's vertices of ``world`` are at its current pivot
        and angle (Rodrigues' rotation of their arms)."""
        idx = np.flatnonzero(self.turns[world])
        turn = rotation(self.wrist_axis[world], float(self.wrist_angle[world]))
        return self.pivot[world] + self.arms[world, idx] @ turn.T

    def detach(self, world: int, vertices=None) -> None:
        """Release the kinematic vertices of ``world`` (all, or ``vertices``: the wrist too
        if it holds any of them); they keep their velocity."""
        if vertices is None:
            self.kinematic[world] = False
            self.hold_stiffness[world] = 0.0
            self.turns[world] = False
        else:
            idx = self.indices(vertices)
            self.kinematic[world, idx] = False
            self.hold_stiffness[world, idx] = 0.0
            if self.turns[world, idx].any():  # the rest of the patch stays held where it is
                self.targets[world, self.turns[world]] = self.wrist_places(world)
                self.turns[world] = False

    def clear(self, world: int) -> None:
        """Nothing held and no external force in ``world``."""
        self.kinematic[world] = False
        self.hold_stiffness[world] = 0.0
        self.external_forces[world] = 0.0
        self.turns[world] = False

    def exactly_held(self) -> np.ndarray:
        """``(N, n)`` bool: the kinematic vertices held exactly (no spring)."""
        return self.kinematic & (self.hold_stiffness == 0.0)

    def spring_held(self) -> np.ndarray:
        """``(N, n)`` bool: the kinematic vertices held by a spring."""
        return self.kinematic & (self.hold_stiffness > 0.0)

    def spring_stiffness(self, fixed) -> np.ndarray:
        """``(N, n)`` N/m: the hold spring of each spring-held vertex that ``fixed`` (the
        model's ``(n,)`` mask) does not pin, 0 elsewhere: what a solver steps."""
        return np.where(self.spring_held() & ~np.asarray(fixed, dtype=bool)[None, :], self.hold_stiffness, 0.0)

    def __repr__(self) -> str:
        return f"Control({self.n_worlds} worlds, {int(self.kinematic.sum())} held vertices)"
