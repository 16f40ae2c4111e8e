"""Per-tet deformation measures of a deformed mesh (numpy; for reports and observations)."""

from __future__ import annotations

import numpy as np

from .mesh import TetMesh


def deformation_gradients(mesh: TetMesh, x: np.ndarray) -> np.ndarray:
    """``F = Ds Dm^-1`` of every tet, shape ``(m, 3, 3)`` (dimensionless)."""
    cur = np.asarray(x)[mesh.tets]
    ds = (cur[:, 1:] - cur[:, :1]).transpose(0, 2, 1)
    return ds @ mesh.rest_edge_inverses


def principal_stretches(mesh: TetMesh, x: np.ndarray) -> np.ndarray:
    """Principal stretches (singular values of F) per tet, ``(m, 3)``, largest first."""
    return np.linalg.svd(deformation_gradients(mesh, x), compute_uv=False)


def max_principal_strain(mesh: TetMesh, x: np.ndarray) -> float:
    """Largest engineering strain ``|stretch - 1|`` over all tets and directions."""
    s = principal_stretches(mesh, x)
    return float(np.max(np.abs(s - 1.0)))


def volume_ratios(mesh: TetMesh, x: np.ndarray) -> np.ndarray:
    """Signed ``J = V / V0`` per tet (<= 0 for an inverted tet)."""
    from .mesh import signed_volumes

    return signed_volumes(np.asarray(x), mesh.tets) / mesh.volumes
