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
"""

from __future__ import annotations

import pickle

from numba.core import caching

__all__ = ["tolerate_stale_indexes", "STALE_INDEX_ERRORS"]

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
