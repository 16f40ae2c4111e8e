"""Shared fixtures (small regular and irregular meshes) and the test run's grouping."""

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


def pytest_collection_modifyitems(config, items):
    """Tests that start Ray clusters run one after another on one worker when the suite
    runs in parallel (``pytest -n 2 --dist loadgroup``, as scripts/test.sh runs it): two
    clusters at once on a 2-core machine only slow each other down."""
    for item in items:
        if item.get_closest_marker("ray"):
            item.add_marker(pytest.mark.xdist_group("ray"))
