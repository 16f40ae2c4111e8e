"""The inlinable logarithm used by the vectorised Neo-Hookean kernel agrees with math.log."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from heml_gym.fastlog import SMALLEST_NORMAL, log_positive


@nb.njit
def _apply(xs, out):
    for i in range(xs.shape[0]):
        out[i] = log_positive(xs[i])


def test_log_positive_within_two_ulp_of_math_log():
    rng = np.random.default_rng(0)
    xs = np.concatenate([
        rng.uniform(0.05, 20.0, 200_000),  # the volume ratios a simulation sees
        1.0 + rng.uniform(-1e-8, 1e-8, 10_000),  # near rest, where ln J ~ J - 1
        np.exp(rng.uniform(-700, 700, 10_000)),  # every exponent
        [SMALLEST_NORMAL, 1.0, 2.0, 0.5, math.sqrt(2.0), np.nextafter(math.sqrt(2.0), 2.0)],
    ])
    out = np.empty_like(xs)
    _apply(xs, out)
    ref = np.log(xs)
    nonzero = ref != 0
    ulps = np.abs(out - ref)[nonzero] / np.spacing(np.abs(ref[nonzero]))
    assert ulps.max() <= 2.0
    assert out[np.flatnonzero(xs == 1.0)[0]] == 0.0


def test_the_neo_hookean_force_kernel_vectorises_on_this_cpu():
    """The blocked Neo-Hookean kernel must compile to packed double arithmetic (SIMD) on
    whatever x86-64 CPU runs the tests, AVX2-only ones included (it once compiled to
    scalar code there: 18 against 45 M tets/s), and for whatever target Numba compiles for
    (``NUMBA_CPU_NAME=x86-64 NUMBA_CPU_FEATURES=""``: SSE2's packed instructions, without
    the VEX ``v`` prefix). Compiled afresh, as cached code cannot be inspected."""
    import platform
    import re

    import numba
    import pytest

    import heml_gym as hg
    from heml_gym import materials as M
    from heml_gym.forces import kernels_heml

    if platform.machine().lower() not in ("x86_64", "amd64"):
        pytest.skip("the instruction names checked are x86's")
    mesh = hg.box_mesh((0.1, 0.1, 0.1), 2)
    field = hg.HemlForce(mesh, M.NeoHookean(E=5e3, nu=0.45))
    fresh = numba.njit(error_model="numpy", fastmath={"contract"})(kernels_heml.constant_psi1_forces_chunk.py_func)
    out = np.zeros_like(mesh.vertices)
    fresh(mesh.vertices.copy(), *field.split_kernel_args(), out, 0, mesh.n_tets)
    asm = next(iter(fresh.inspect_asm().values()))
    packed = re.findall(r"\bv?(?:mul|div|add|sub)pd\b|\bvfn?m(?:add|sub)\d+pd\b", asm)
    assert len(packed) > 20, "the kernel loop is scalar"
    assert re.search(r"\bv?divpd\b", asm)  # the volume term's division, in SIMD lanes
