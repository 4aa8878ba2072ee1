"""The compile decorator of the fit kernels: numba, cached on disk where it can be.

Compiling the kernels costs about 20 s, so they are cached (``cache=True``) next to
the modules or, where that folder is read-only, in the user's cache folder. A
service whose installation is read-only and that has no writable home (the daemon's
unit: ``ProtectSystem=strict``, ``ProtectHome=yes``, ``DynamicUser=yes``) has
neither, and numba then refuses the decorator itself, at import time: importing
anything from :mod:`cellbridge.tactile` (even the layout parser the daemon's
configuration uses) would fail. Here such a function is compiled without a disk
cache instead (on first use, every start), named in :data:`UNCACHED`, and one
warning says how to give it a cache (``NUMBA_CACHE_DIR``).
"""

from __future__ import annotations

import warnings
from typing import Any, Callable

from numba import njit

__all__ = ["compiled", "UNCACHED"]

#: Qualified names of the kernels compiled without a disk cache in this process.
UNCACHED: list[str] = []


def compiled(fn: Callable[..., Any], **options: Any) -> Any:
    """``numba.njit(cache=True, **options)``, or without the cache where numba finds no place for it.

    Used as ``@compiled`` on a kernel, or as ``compiled(f, error_model="numpy")`` on a
    plain numpy function written for arrays and floats alike, so one copy of a rule
    serves both numpy and the compiled loops (``error_model="numpy"``: x/0 gives
    inf or NaN as in numpy, instead of raising).
    """
    try:
        return njit(cache=True, **options)(fn)
    except RuntimeError as exc:
        if "cannot cache" not in str(exc):
            raise
    if not UNCACHED:
        warnings.warn(
            "cellbridge.tactile: no writable numba cache folder (the installation is read-only and so "
            "is the user's cache folder); the contact kernels compile on first use in every process "
            "(about 20 s). Set NUMBA_CACHE_DIR to a writable folder to compile them once.",
            RuntimeWarning,
            stacklevel=2,
        )
    UNCACHED.append(f"{fn.__module__}.{fn.__qualname__}")
    return njit(**options)(fn)
