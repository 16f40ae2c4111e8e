"""The typed bundles of arrays that the solvers' Numba kernels take.

A kernel reads a few named bundles instead of dozens of positional arrays: what the
model owns (:class:`HemlBody`, shared by every world; :class:`HemlLaws`, every world's
law, kept current by :meth:`heml_gym.Model.set_material`), the supports
(:class:`SupportArrays`), and what a solver owns (its initial Hessians, L-BFGS memory,
BDF2 history: see :mod:`heml_gym.solvers.kernels_quasi_newton`). Each bundle is a
``NamedTuple`` of arrays and scalars, which Numba passes by reference and types once per
combination of field types: build them with the dtypes documented here, or a kernel
compiles again.

Units: m, s, kg, N, Pa.
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np


class HemlBody(NamedTuple):
    """A HEML model's arrays that every world shares (read only by the kernels)."""

    tets: np.ndarray  #: (m, 4) int64 vertex indices of each tet
    coef_t: np.ndarray  #: HEML's rest coefficients, constant-major (see :class:`~heml_gym.forces.HemlRestData`)
    inv_det: np.ndarray  #: (m,) 1 / det of each tet's rest edge matrix (1/m^3)
    edge_weights: np.ndarray  #: (6, m) ``2 V0 a_k`` per tet edge, edge-major (see HemlRestData)
    mass: np.ndarray  #: (n,) lumped vertex masses (kg)
    fixed: np.ndarray  #: (n,) bool: vertices that never move
    gravity: np.ndarray  #: (3,) m/s^2
    alpha: float  #: mass-proportional damping (1/s)
    vt_ptr: np.ndarray  #: (n + 1,) int64: the tets around vertex i are ``vt_tets[vt_ptr[i]:vt_ptr[i + 1]]``
    vt_tets: np.ndarray  #: (4 m,) int64


class HemlLaws(NamedTuple):
    """Every world's law, stacked over the N worlds (leading axis), with the batch's flags."""

    law: np.ndarray  #: (N,) int64 law ids (:mod:`heml_gym.laws`)
    params: np.ndarray  #: (N, k) float64 law constants, zero-padded
    weights: np.ndarray  #: (N, 6, m) spring weights (N/m) when ``split``, else (N, 6, 1) zeros
    psi1: np.ndarray  #: (N,) the constant dPsi/dI1 (Pa) when ``split``, else 0
    split: bool  #: every world's law has a constant dPsi/dI1 (Neo-Hookean): the fused kernels
    use_q: bool  #: some world's law reads I2: the kernels read ``q_t``
    q_t: np.ndarray  #: HEML's I2 coefficients (``use_q``), else a placeholder


class WorldLaw(NamedTuple):
    """One world's row of :class:`HemlLaws` (see :func:`world_law`)."""

    law: np.int64
    params: np.ndarray
    weights: np.ndarray
    psi1: float
    split: bool
    use_q: bool
    q_t: np.ndarray


class SupportArrays(NamedTuple):
    """The rigid supports and tools as the contact kernels read them
    (:mod:`heml_gym.kernels_contact`): the static supports, then the tools
    (:mod:`heml_gym.tools`) with the pose of each in each world (a world's kernel gets its
    own, ``tool_pose`` of one row: :func:`world_supports`)."""

    planes: np.ndarray
    grids: np.ndarray
    grid_values: np.ndarray
    tool_kind: np.ndarray = np.zeros(0, dtype=np.int64)  #: (T,) int64
    tool_size: np.ndarray = np.zeros((0, 3))  #: (T, 3) m
    tool_pose: np.ndarray = np.zeros((1, 0, 12))  #: (W, T, 12): centre (m), rotation row by row
    tool_k: np.ndarray = np.zeros((1, 0))  #: (W, n) N/m: the tools' contact penalty stiffness at each vertex


@nb.njit(cache=True, inline="always")
def world_supports(supports, s):
    """World ``s``'s view of ``supports`` (:class:`SupportArrays`): its tools' poses only."""
    return SupportArrays(supports.planes, supports.grids, supports.grid_values, supports.tool_kind,
                         supports.tool_size, supports.tool_pose[s:s + 1], supports.tool_k[s:s + 1])


@nb.njit(cache=True, inline="always")
def world_law(laws, s):
    """World ``s``'s :class:`WorldLaw` of ``laws`` (:class:`HemlLaws`), in a kernel or from
    Python."""
    return WorldLaw(laws.law[s], laws.params[s], laws.weights[s], laws.psi1[s], laws.split, laws.use_q, laws.q_t)
