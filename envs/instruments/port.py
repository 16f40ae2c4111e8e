"""An instrument on a port: its shaft passes through a fixed point of the body wall.

A laparoscopic instrument enters through a trocar: its shaft always passes through the
port (a remote centre of motion), so its tip moves by tilting the shaft about the port
and sliding it in or out. A :class:`Port` maps the tip (m) to port coordinates and back:

* ``pitch`` and ``yaw`` (rad): the shaft's tilt from the port's axis (the line from the
  port to the middle of the instrument's start box), about the axis's two normals ``e1``
  and ``e2``; the shaft's direction is ``normalise(axis + tan(pitch) e1 + tan(yaw) e2)``,
  so pitch alone turns the shaft by exactly ``pitch`` in the plane of ``axis`` and
  ``e1``, and no tilt within ``max_tilt`` is singular;
* ``insertion`` (m): the distance from the port to the tip along the shaft.

The action of a grasper on a port is then ``(pitch_rate, yaw_rate, insertion_rate,
grasp)``: tilt rates in units of ``angular_speed`` (rad/s) and the insertion rate in units
of the task's ``max_speed`` (m/s). ``e1`` is horizontal (``axis x z``, or ``x`` when the
axis is vertical), ``e2 = axis x e1``. Units: m, rad, s.
"""

from __future__ import annotations

import numpy as np

#: the shortest insertion (m): the tip stays this far inside the port
MIN_INSERTION = 1e-3
#: the jaws' length (m) beyond the end of a shaft that touches tissue
SHAFT_GAP = 0.015
#: a touching shaft's half-length (m): it reaches from its end back through the port and far beyond
SHAFT_HALF_LENGTH = 0.3


class Port:
    """Port coordinates of an instrument whose shaft passes through ``port`` (m, (3,)),
    its axis towards ``towards`` (m, (3,), e.g. the middle of the start box);
    ``angular_speed`` (rad/s) of a tilt command of 1; tilts clipped to ``max_tilt`` (rad)."""

    def __init__(self, port, towards, angular_speed: float, max_tilt: float):
        self.port = np.asarray(port, dtype=np.float64)
        axis = np.asarray(towards, dtype=np.float64) - self.port
        self.axis = axis / np.linalg.norm(axis)
        e1 = np.cross(self.axis, (0.0, 0.0, 1.0))
        if np.linalg.norm(e1) < 1e-9:  # a vertical axis: tilt about x first
            e1 = np.array([1.0, 0.0, 0.0]) - self.axis[0] * self.axis
        self.e1 = e1 / np.linalg.norm(e1)
        self.e2 = np.cross(self.axis, self.e1)
        self.angular_speed, self.max_tilt = float(angular_speed), float(max_tilt)

    @classmethod
    def of(cls, gripper) -> "Port | None":
        """The port of a ``GripperSpec`` (its axis towards the middle of its start box), or
        None when it has none."""
        if gripper.port is None:
            return None
        towards = 0.5 * (np.asarray(gripper.start_low, dtype=np.float64) + np.asarray(gripper.start_high))
        return cls(gripper.port, towards, gripper.angular_speed, gripper.max_tilt)

    def coordinates(self, tips: np.ndarray) -> np.ndarray:
        """``(N, 3)`` pitch (rad), yaw (rad), insertion (m) of tips ``(N, 3)`` (m); a tip
        at or behind the port's plane gets the tilt limit's direction."""
        d = np.atleast_2d(tips) - self.port
        insertion = np.linalg.norm(d, axis=1)
        along = np.maximum(d @ self.axis, 1e-12)
        pitch = np.arctan2(d @ self.e1, along)
        yaw = np.arctan2(d @ self.e2, along)
        return np.column_stack([np.clip(pitch, -self.max_tilt, self.max_tilt),
                                np.clip(yaw, -self.max_tilt, self.max_tilt), insertion])

    def tips(self, coordinates: np.ndarray) -> np.ndarray:
        """Tips ``(N, 3)`` (m) at port coordinates ``(N, 3)`` (pitch, yaw in rad; insertion, m)."""
        c = np.atleast_2d(coordinates)
        u = self.axis + np.tan(c[:, :1]) * self.e1 + np.tan(c[:, 1:2]) * self.e2
        return self.port + c[:, 2:3] * u / np.linalg.norm(u, axis=1, keepdims=True)

    def advance(self, tips: np.ndarray, commands: np.ndarray, max_speed: float, dt: float) -> np.ndarray:
        """Tips ``(N, 3)`` (m) after ``dt`` (s) of ``commands (N, 3)`` in [-1, 1] (pitch and
        yaw rates in units of ``angular_speed``, insertion rate in units of ``max_speed``,
        m/s); tilts stay within ``max_tilt``, the insertion at least :data:`MIN_INSERTION`."""
        c = self.coordinates(tips)
        c[:, :2] = np.clip(c[:, :2] + commands[:, :2] * self.angular_speed * dt, -self.max_tilt, self.max_tilt)
        c[:, 2] = np.maximum(c[:, 2] + commands[:, 2] * max_speed * dt, MIN_INSERTION)
        return self.tips(c)

    def shaft_poses(self, tips: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where a shaft capsule of half-length :data:`SHAFT_HALF_LENGTH` is for tips ``(N,
        3)`` (m): its end :data:`SHAFT_GAP` behind each tip on the line from the port, the
        rest back through the port and beyond. Returns centres ``(N, 3)`` (m) and rotations
        ``(N, 3, 3)`` whose third column is the shaft's direction (the capsule's axis)."""
        d = np.atleast_2d(tips) - self.port
        u = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        centres = self.shaft_ends(tips) - SHAFT_HALF_LENGTH * u
        helper = np.where(np.abs(u[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
        a = np.cross(helper, u)
        a /= np.linalg.norm(a, axis=1, keepdims=True)
        b = np.cross(u, a)
        return centres, np.stack([a, b, u], axis=2)

    def shaft_ends(self, tips: np.ndarray) -> np.ndarray:
        """The end of the shaft ``(N, 3)`` (m) for tips ``(N, 3)`` (m): :data:`SHAFT_GAP`
        behind each tip on the line from the port (the shaft runs from there to the port)."""
        d = np.atleast_2d(tips) - self.port
        return np.atleast_2d(tips) - SHAFT_GAP * d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)

    def commands_for(self, tips: np.ndarray, velocity: np.ndarray, max_speed: float) -> np.ndarray:
        """The port commands ``(N, 3)`` in [-1, 1] that move tips ``(N, 3)`` (m) at
        ``velocity (N, 3)`` (m/s) to first order (the shaft's Jacobian inverted), for a
        controller that thinks in Cartesian velocities; clipped to [-1, 1]."""
        d = np.atleast_2d(tips) - self.port
        v = np.atleast_2d(velocity)
        insertion = np.linalg.norm(d, axis=1, keepdims=True)
        u = d / insertion
        u_dot = (v - (v * u).sum(axis=1, keepdims=True) * u) / insertion  # the shaft's turn rate (1/s)
        a, ua_dot = np.maximum(u @ self.axis, 1e-12), u_dot @ self.axis
        rates = []
        for e in (self.e1, self.e2):  # d/dt arctan(u.e / u.a)
            ue, ue_dot = u @ e, u_dot @ e
            rates.append((ue_dot * a - ue * ua_dot) / (a * a + ue * ue))
        out = np.column_stack([rates[0] / self.angular_speed, rates[1] / self.angular_speed,
                               (v * u).sum(axis=1) / max_speed])
        return np.clip(out, -1.0, 1.0)
