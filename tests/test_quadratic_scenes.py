"""The retraction scenes on 10-node tets (``physics={"field": "quadratic"}``)."""

import gymnasium as gym
import numpy as np
import pytest

import heml_gym.envs  # noqa: F401  (registers the envs)
from heml_gym import QuadraticFemForce, QuadraticTetMesh
from heml_gym.envs import scripted

from env_checks import assert_random_steps_stay_finite

TISSUE = "heml_gym/TissueRetraction-v1"
QUADRATIC = {"field": "quadratic", "integrator": "implicit", "max_dt": 0.025}


def test_the_flap_on_quadratic_tets_holds_every_node_of_its_regions():
    """Attached edge and grasp line select the edge nodes too: on 6 x 6 x 1 cells the
    attached face x = 0 has (2*6+1) x (2*1+1) nodes and the grasp line 2*6+1."""
    env = gym.make(TISSUE, cells=(6, 6, 1), physics=QUADRATIC)
    task = env.unwrapped.task
    mesh = task.scene.mesh
    assert isinstance(mesh, QuadraticTetMesh) and isinstance(task.model.field, QuadraticFemForce)
    assert mesh.n_vertices == 13 * 13 * 3
    assert len(task.scene.fixed) == 13 * 3 and np.all(mesh.vertices[task.scene.fixed, 0] == 0.0)
    assert len(task.scene.grasp_patch) == 13
    assert task.model.mass.sum() == pytest.approx(950.0 * 0.12 * 0.12 * 0.008, rel=1e-12)


def test_random_steps_on_quadratic_tets_stay_finite_and_converged():
    assert_random_steps_stay_finite(gym.make(TISSUE, cells=(6, 6, 1), physics=QUADRATIC), 30, seed=1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_scripted_fold_succeeds_on_quadratic_tets(seed):
    env = gym.make(TISSUE, cells=(6, 6, 1), physics=QUADRATIC)
    policy = scripted.scripted_policy(env.unwrapped.task.scene.spec)
    obs, _ = env.reset(seed=seed)
    policy.reset()
    for _ in range(100):
        obs, _, terminated, truncated, info = env.step(policy(obs))
        if terminated or truncated:
            break
    assert info["is_success"] and info["solver_converged"]
