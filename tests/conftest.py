"""Shared fixtures: small regular and irregular meshes."""

from __future__ import annotations

import pytest

import heml_gym as hg
from deformations import perturbed_box


@pytest.fixture(scope="session")
def small_box() -> hg.TetMesh:
    return hg.box_mesh((0.1, 0.08, 0.06), (2, 2, 2))


@pytest.fixture(scope="session")
def irregular_box() -> hg.TetMesh:
    return perturbed_box(seed=3)
