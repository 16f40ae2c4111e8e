"""What a task measures on the tissue, per world: how much of a target the
tissue hides from the camera, how far a flap is folded back, how much it is strained.

Each measure is a small object built once from the scene and called with the current
positions (m) of the worlds it measures; the tasks compose them into rewards, success
and cost. Units: m, rad, and fractions.
"""

from __future__ import annotations

import numpy as np

from .geometry import fibonacci_sphere, visible_fraction, visible_fraction_batch


def finite(values: np.ndarray, nan: float) -> np.ndarray:
    """``np.nan_to_num(values, nan=nan)`` (infinities to the largest finite floats); the
    array itself, without a copy, when every value is finite already (the usual case)."""
    if np.isfinite(values).all():
        return values
    return np.nan_to_num(values, nan=nan)


class Exposure:
    """The fraction of a spherical target's camera-facing surface samples (``samples`` of
    them, on a Fibonacci sphere of the scene's ``target_radius``) that the deformed tissue
    surface does not hide from the scene's camera, by ray casting."""

    def __init__(self, scene, samples: int):
        self.scene = scene
        self.sphere = fibonacci_sphere(samples)

    def __call__(self, x: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """``x``: ``(k, n, 3)`` positions of ``k`` worlds; ``targets``: ``(k, 3)`` centres."""
        s, r = self.scene, self.scene.target_radius
        points = targets[:, None, :] + r * self.sphere[None, :, :]
        # only samples facing the camera count; the rest are hidden by the target itself
        if len(x) == 1:  # no thread launch for one world
            return np.array([visible_fraction(points[0], s.camera, x[0], s.surface_faces,
                                              sphere_center=targets[0], sphere_radius=r)])
        return visible_fraction_batch(points, s.camera, x, s.surface_faces, sphere_center=targets, sphere_radius=r)


class FoldLift:
    """How far a flap's free edge is folded back about its hinge line: the mean over the
    edge vertices of their fold angle from rest over the scene's ``fold_angle``, each
    clipped to [0, 1]."""

    def __init__(self, scene):
        self.scene = scene
        self.edge = np.asarray(scene.edge_vertices, dtype=np.int64)
        self.rest_angle = self.angles(scene.mesh.vertices[None, self.edge])[0]

    def angles(self, x_edge: np.ndarray) -> np.ndarray:
        """Angle (rad) of each edge vertex about the hinge, 0 along the free direction,
        increasing as the edge lifts; in (-pi/2, 3 pi/2] so that folding back past
        vertical does not wrap."""
        s = self.scene
        dx = s.fold_direction * (x_edge[..., 0] - s.hinge[0])
        dz = x_edge[..., 2] - s.hinge[1]
        angle = np.arctan2(dz, dx)
        return np.where(angle <= -np.pi / 2, angle + 2 * np.pi, angle)

    def __call__(self, x_edge: np.ndarray) -> np.ndarray:
        """``x_edge``: ``(k, len(edge), 3)`` positions of the edge vertices of ``k`` worlds."""
        progress = (self.angles(x_edge) - self.rest_angle) / self.scene.fold_angle
        return finite(np.clip(progress, 0.0, 1.0), nan=0.0).mean(axis=1)
