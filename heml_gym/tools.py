"""Rigid tools that touch the tissue: kinematic shapes posed by the user each step.

A tool is a rigid body the tissue cannot enter, like a support, but it moves: each world
poses it anew before a step (:meth:`heml_gym.Control.pose_tool`), and the solver sees it
where it is posed at the step's end. Contact is frictionless: a penalty on the free
vertices inside it in the potential the implicit solvers minimise (with its Hessian blocks
in Newton's matrix and the L-BFGS preconditioner's contact set) and the static solver's,
its stiffness a multiple of the tissue's own at each vertex; unlike a support's, there is
no projection onto its surface afterwards. Explicit sub-steps instead put a vertex inside
a tool back on its surface and take its velocity into it, as they do for a support. Every
solver reports the force each tool exerts on the tissue
(:attr:`heml_gym.solvers.StepStats.tool_force`). Units: m, N.

Limits: contact is on the tissue's vertices, so a tool thinner than the mesh's cells can
slip between them; and a vertex carried more than half a tool's thickness into it within
one sub-step comes out on the far side (tunnelling): keep a tool's speed below its half
thickness per sub-step (a 4 mm paddle in the tasks' 0.05 s sub-steps: 40 mm/s).

    Capsule(radius=0.005, half_length=0.1)       # a shaft or a probe, along its local z
    Box(half_extents=(0.03, 0.02, 0.002))        # a paddle retractor, thin along z

    model = Model(mesh, material, supports=[PlaneSupport()], tools=[Box((0.03, 0.02, 0.002))])
    control.pose_tool(world, 0, position=(0.05, 0.04, 0.012))   # identity rotation
"""

from __future__ import annotations

import math

import numpy as np

from .kernels_contact import BOX, CAPSULE, tool_each

__all__ = ["Tool", "Capsule", "Box", "Tools", "PARKED"]

#: where a tool waits before it is first posed (m): far from any tissue
PARKED = np.array([0.0, 0.0, 1e6])


def _positive(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive number of metres, got {value!r}")
    return float(value)


class Tool:
    """A rigid shape (:class:`Capsule`, :class:`Box`) in its own frame, centred on its origin."""

    kind: int
    size: tuple


class Capsule(Tool):
    """The points within ``radius`` (m) of the segment from ``-half_length`` to
    ``+half_length`` (m) along the tool's local z: a shaft, a probe."""

    kind = CAPSULE

    def __init__(self, radius: float, half_length: float):
        self.radius, self.half_length = _positive("radius", radius), _positive("half_length", half_length)
        self.size = (self.radius, self.half_length, 0.0)

    def __repr__(self) -> str:
        return f"Capsule(radius={self.radius:g}, half_length={self.half_length:g})"


class Box(Tool):
    """The box ``|x| <= hx, |y| <= hy, |z| <= hz`` (m) in the tool's frame: a paddle."""

    kind = BOX

    def __init__(self, half_extents):
        h = tuple(half_extents) if isinstance(half_extents, (list, tuple, np.ndarray)) else None
        if h is None or len(h) != 3:
            raise ValueError(f"half_extents must be three positive lengths in metres, got {half_extents!r}")
        self.size = tuple(_positive("half_extents", float(v) if isinstance(v, np.floating) else v) for v in h)

    def __repr__(self) -> str:
        return f"Box(half_extents={list(self.size)})"


class Tools:
    """A model's tools packed for the kernels: ``kind (T,)`` int64, ``size (T, 3)`` (m)."""

    def __init__(self, tools=()):
        items = tuple(tools)
        for t in items:
            if not isinstance(t, Tool):
                raise TypeError(f"tools must be Capsule or Box objects, got {type(t).__name__}")
        self.items = items
        self.kind = np.array([t.kind for t in items], dtype=np.int64)
        self.size = np.array([t.size for t in items], dtype=np.float64).reshape(-1, 3)

    @classmethod
    def from_arrays(cls, kind, size) -> "Tools":
        """The tools of packed ``kind (T,)`` and ``size (T, 3)`` (as the kernels read them)."""
        return cls([Capsule(sz[0], sz[1]) if k == CAPSULE else Box(sz) for k, sz in zip(kind, size)])

    def __len__(self) -> int:
        return len(self.items)

    def signed_distance(self, points, pose) -> tuple[np.ndarray, np.ndarray]:
        """Smallest signed distance (m) of ``points (k, 3)`` to the tools posed at ``pose
        (T, 12)`` (``inf`` without tools) and that tool's outward normal, ``((k,), (k, 3))``."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        if not len(self):
            return np.full(len(p), math.inf), np.zeros((len(p), 3))
        each, normals = self.each_distance(p, pose)
        nearest = np.argmin(each, axis=0)
        k = np.arange(len(p))
        return each[nearest, k], normals[nearest, k]

    def each_distance(self, points, pose) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (m) of ``points (k, 3)`` to each tool posed at ``pose (T, 12)``
        and its outward normals: ``((T, k), (T, k, 3))``."""
        p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        d, n = np.empty((len(self), len(p))), np.empty((len(self), len(p), 3))
        tool_each(p, self.kind, self.size, np.ascontiguousarray(pose, dtype=np.float64), d, n)
        return d, n

    def penalty(self, points, pose, stiffness, free) -> "ToolPenalty":
        """The tools' contact penalty on ``points (k, 3)`` posed at ``pose (T, 12)``:
        ``sum_t sum_i k_i / 2 min(d_it, 0)^2`` over the ``free (k,)`` points, ``k_i`` =
        ``stiffness (k,)`` N/m (each tool on its own: a point squeezed between two feels
        both)."""
        d, n = self.each_distance(points, pose)
        pen = np.where(free[None, :], np.minimum(d, 0.0), 0.0)  # (T, k)
        k = np.asarray(stiffness, dtype=np.float64)
        energy = 0.5 * float((k[None, :] * pen * pen).sum())
        push = (k[None, :] * pen)[:, :, None] * n  # (T, k, 3): the gradient's parts
        touching = np.flatnonzero((pen < 0.0).any(axis=0))
        blocks = np.einsum("tk,tka,tkb->kab", (k[None, :] * (pen < 0.0))[:, touching], n[:, touching],
                           n[:, touching])
        return ToolPenalty(energy, push.sum(axis=0), -push.sum(axis=1), touching, blocks, k)


class ToolPenalty:
    """:meth:`Tools.penalty`'s parts: ``energy`` (J), ``gradient (k, 3)`` (N), ``force (T,
    3)`` (N: each tool's on the points), ``touching`` (indices of the points inside a
    tool), ``blocks (len(touching), 3, 3)`` (its Hessian's, N/m) and ``stiffness (k,)``
    (N/m, the penalty's at each point)."""

    def __init__(self, energy, gradient, force, touching, blocks, stiffness):
        self.energy, self.gradient, self.force, self.touching, self.blocks = energy, gradient, force, touching, blocks
        self.stiffness = stiffness
