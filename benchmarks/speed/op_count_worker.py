"""Exact floating-point operation counts of a force evaluation, by running the kernel.

The force kernels are plain scalar Python under ``NUMBA_DISABLE_JIT=1``. This module runs
them on a whole mesh with every float input replaced by :class:`Counted`, a float that
counts each ``+ - * /`` it takes part in, and each call of ``log exp sqrt pow``. So the
count is of the very code that runs compiled, on the very mesh, not an estimate.

Import this module before anything imports numba (it sets ``NUMBA_DISABLE_JIT``); the
op-count benchmark runs it in a subprocess for that reason.
"""

from __future__ import annotations

import math
import os
import types
from dataclasses import dataclass

os.environ["NUMBA_DISABLE_JIT"] = "1"

import numpy as np


@dataclass
class OpTally:
    add: int = 0  # additions and subtractions
    mul: int = 0  # multiplications
    div: int = 0  # divisions
    func: int = 0  # log, exp, sqrt, pow

    @property
    def add_mul(self) -> int:
        """Additions plus multiplications (the seed's "+ x" count); divisions counted as x."""
        return self.add + self.mul + self.div

    def reset(self):
        self.add = self.mul = self.div = self.func = 0


TALLY = OpTally()


class Counted(float):
    """A float that tallies the arithmetic it takes part in."""

    __slots__ = ()

    def __add__(self, o):
        TALLY.add += 1
        return Counted(float(self) + float(o))

    __radd__ = __add__

    def __sub__(self, o):
        TALLY.add += 1
        return Counted(float(self) - float(o))

    def __rsub__(self, o):
        TALLY.add += 1
        return Counted(float(o) - float(self))

    def __mul__(self, o):
        TALLY.mul += 1
        return Counted(float(self) * float(o))

    __rmul__ = __mul__

    def __truediv__(self, o):
        TALLY.div += 1
        return Counted(float(self) / float(o))

    def __rtruediv__(self, o):
        TALLY.div += 1
        return Counted(float(o) / float(self))

    def __neg__(self):  # a sign flip, not an arithmetic operation
        return Counted(-float(self))

    def __pow__(self, o):
        TALLY.func += 1
        return Counted(float(self) ** float(o))


def _counting_function(fn):
    def wrapped(*args):
        TALLY.func += 1
        return Counted(fn(*(float(a) for a in args)))

    return wrapped


counting_math = types.SimpleNamespace(
    log=_counting_function(math.log),
    exp=_counting_function(math.exp),
    sqrt=_counting_function(math.sqrt),
    inf=math.inf,
    nan=math.nan,
)


def counted_array(a) -> np.ndarray:
    """An object array of :class:`Counted` with the values of ``a``."""
    a = np.asarray(a, dtype=np.float64)
    out = np.empty(a.shape, dtype=object)
    flat = out.reshape(-1)
    for i, v in enumerate(a.reshape(-1)):
        flat[i] = Counted(v)
    return out


def _patch_math():
    import heml_gym.fastlog as fastlog
    import heml_gym.forces.kernels_mass_spring as ms
    import heml_gym.laws as laws

    laws.math = counting_math
    ms.math = counting_math
    fastlog.math = counting_math


def count_forces(field, x: np.ndarray) -> tuple[OpTally, np.ndarray]:
    """Run ``field``'s serial force kernel once at ``x`` with counting scalars.

    Every float64 array the field holds (precomputed constants, work arrays) is replaced
    by a counted copy on a shallow clone of the field, so the very kernel that runs
    compiled runs here. Returns the tally and the forces it computed (N).
    """
    if os.environ.get("NUMBA_DISABLE_JIT") != "1":  # pragma: no cover
        raise RuntimeError("op counting needs NUMBA_DISABLE_JIT=1 set before numba is imported")
    import copy

    _patch_math()
    clone = copy.copy(field)
    for name, value in vars(field).items():
        if isinstance(value, np.ndarray) and value.dtype == np.float64:
            setattr(clone, name, counted_array(value))
    f = np.empty((field.mesh.n_vertices, 3), dtype=object)
    f.fill(0.0)
    xc = counted_array(x)
    TALLY.reset()
    clone.add_forces(xc, f)
    result = OpTally(TALLY.add, TALLY.mul, TALLY.div, TALLY.func)
    return result, np.array(f, dtype=np.float64)


def _main():
    """``python -m heml_gym.benchmarks.speed.op_count_worker MESH.npz``: print the counts of one force evaluation as JSON."""
    import json
    import sys

    import heml_gym as hg
    from heml_gym import materials as M

    data = np.load(sys.argv[1])
    mesh = hg.TetMesh(data["vertices"], data["tets"])
    rng = np.random.default_rng(0)
    x = mesh.vertices * 1.05 + 1e-3 * mesh.min_edge_length * rng.standard_normal(mesh.vertices.shape)
    fields = {
        "heml_stvk": hg.HemlForce(mesh, M.StVenantKirchhoff(E=5e3, nu=0.45)),
        "heml_neo_hookean": hg.HemlForce(mesh, M.NeoHookean(E=5e3, nu=0.45)),
        "mass_tensor": hg.MassTensorForce(mesh, M.StVenantKirchhoff(E=5e3, nu=0.45)),
        "mass_spring": hg.MassSpringForce(mesh, M.NeoHookean(E=5e3, nu=0.45)),
    }
    out = {}
    for name, field in fields.items():
        tally, counted = count_forces(field, x)
        out[name] = {
            "add": tally.add, "mul": tally.mul, "div": tally.div, "func": tally.func,
            "add_mul": tally.add_mul,
            "max_abs_force": float(np.abs(counted).max()),
        }
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    _main()
