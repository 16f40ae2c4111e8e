"""Compiled-kernel caches that outlive a heml-gym upgrade.

The kernels are compiled with ``cache=True``: Numba keeps each function's machine code
in ``__pycache__`` beside its source, with an index of the argument types it was
compiled for. Numba reads that index by unpickling it *before* it checks whether the
source changed, so an index written by an older heml-gym that names a type since
renamed or removed (a kernel bundle's ``NamedTuple``) raises ``AttributeError`` inside
the first step instead of counting as stale (numba/numba#6018). pip leaves
``__pycache__`` behind on upgrades, and so does ``git pull`` in a checkout.

:func:`tolerate_stale_indexes` (called when :mod:`heml_gym` is imported) makes an index
that cannot be unpickled count as stale, as Numba already treats one written by another
Numba version: the kernel is compiled again and the index rewritten.

Numba also judges a cached kernel fresh by the stamp of its own source file only, so a
kernel whose callee in another module changed (the L-BFGS kernel calls the force chunks
of ``forces/kernels_heml.py`` and the wrist's of ``solvers/kernels_wrist.py``) would load
its old machine code, silently: after an upgrade that touched only the callee, or in a
checkout after a pull. :func:`stamp_with_package_sources` (called for :mod:`heml_gym`'s own
folder when it is imported) adds to the stamp of every kernel in a folder a digest of all
of that folder's kernel sources (its ``.py`` files that use ``njit``), so a change to any
of them recompiles them all.
"""

from __future__ import annotations

import hashlib
import os
import pickle
from pathlib import Path

from numba.core import caching

__all__ = ["tolerate_stale_indexes", "stamp_with_package_sources", "sources_digest", "STALE_INDEX_ERRORS"]

#: What unpickling an index from older code raises: a renamed or removed class or module,
#: a truncated or garbled file.
STALE_INDEX_ERRORS = (AttributeError, ImportError, EOFError, pickle.UnpicklingError, TypeError, ValueError)


def tolerate_stale_indexes() -> None:
    """Make Numba treat a cache index it cannot unpickle as stale (idempotent)."""
    index_file = caching.IndexDataCacheFile
    load = index_file._load_index
    if getattr(load, "tolerates_stale_indexes", False):
        return

    def _load_index(self):
        try:
            return load(self)
        except STALE_INDEX_ERRORS:
            return {}

    _load_index.tolerates_stale_indexes = True
    index_file._load_index = _load_index


def sources_digest(root) -> str:
    """A digest (hex) of the ``.py`` files under ``root`` that use ``njit`` (their paths
    relative to it and their contents)."""
    root = Path(root)
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        text = path.read_bytes()
        if b"njit" in text:
            digest.update(str(path.relative_to(root)).encode() + b"\0" + text + b"\0")
    return digest.hexdigest()


def stamp_with_package_sources(root) -> None:
    """Make the cache stamp of every kernel whose source lies under ``root`` (a folder)
    include :func:`sources_digest` of ``root`` (idempotent per folder): a change to any
    kernel source there recompiles every kernel there, callers in other files included."""
    root = Path(root).resolve()
    mixin = caching._SourceFileBackedLocatorMixin
    stamp = mixin.get_source_stamp
    roots = getattr(stamp, "package_digests", None)
    if roots is None:
        roots = {}

        def get_source_stamp(self):
            own = stamp(self)
            path = os.path.realpath(getattr(self, "_py_file", "") or "")
            for folder, digest in roots.items():
                if path.startswith(folder + os.sep):
                    return own, digest
            return own

        get_source_stamp.package_digests = roots
        mixin.get_source_stamp = get_source_stamp
    roots[str(root)] = sources_digest(root)
