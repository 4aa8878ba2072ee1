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

numba checks a cached kernel against its own file alone, yet the kernels compile in
rules of other modules (``disk_model.layer_response`` in the element inverse,
``inversion``'s per-reading rules, ``spread_model``'s constants in the fits): an edit of
one left the callers' cache as it was, and processes ran the rule from before the edit
without a word. So each kernel's cache is checked against every module of
:data:`KERNEL_SOURCES` too (tests/test_tactile_kernel_cache_sources.py keeps the list whole).
"""

from __future__ import annotations

import os
import warnings
from functools import cache
from typing import Any, Callable

from numba import njit

__all__ = ["compiled", "UNCACHED", "KERNEL_SOURCES", "missing_from_cache"]

#: The modules of this package whose code a kernel may compile in: those holding kernels and
#: every module of the package they import from, and so on (their functions and constants
#: are compiled into the callers). An edit of any of them compiles every kernel again.
KERNEL_SOURCES = ("arrays", "calibration", "calibration_kernel", "cluster_kernel", "contact_surface", "disk_model",
                  "element", "fit_kernel", "inverse_kernel", "inversion", "layout", "overlap", "response",
                  "spread_model")

#: Qualified names of the kernels compiled without a disk cache in this process.
UNCACHED: list[str] = []

#: The kernels made with a disk cache in this process, for :func:`missing_from_cache`.
_CACHED: list[Any] = []


def compiled(fn: Callable[..., Any], **options: Any) -> Any:
    """``numba.njit(cache=True, **options)``, or without the cache where numba finds no place for it.

    Used as ``@compiled`` on a kernel, or as ``compiled(f, error_model="numpy")`` on a
    plain numpy function written for arrays and floats alike, so one copy of a rule
    serves both numpy and the compiled loops (``error_model="numpy"``: x/0 gives
    inf or NaN as in numpy, instead of raising).
    """
    try:
        dispatcher = _checked_against_sources(njit(cache=True, **options)(fn))
        if hasattr(dispatcher, "py_func"):  # (not with NUMBA_DISABLE_JIT: the function itself, nothing to cache)
            _CACHED.append(dispatcher)
        return dispatcher
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


@cache
def _sources_stamp() -> tuple[tuple[str, int, int], ...]:
    """(module, modification time in ns, size) of every module of :data:`KERNEL_SOURCES`."""
    here = os.path.dirname(os.path.abspath(__file__))
    out = []
    for name in KERNEL_SOURCES:
        try:
            st = os.stat(os.path.join(here, f"{name}.py"))
        except OSError:  # (an installation without the sources: numba's own check alone)
            continue
        out.append((name, st.st_mtime_ns, st.st_size))
    return tuple(out)


def _checked_against_sources(dispatcher: Any) -> Any:
    """``dispatcher`` (cached) with its cache index stamped, and checked, with the stamps of
    :data:`KERNEL_SOURCES` beside numba's own of the kernel's file: a cache written before an
    edit of any of them is not loaded, the kernel compiles again and overwrites it. (numba's
    index holds one stamp, compared for equality; a numba without that field keeps its own.)"""
    index = getattr(getattr(dispatcher, "_cache", None), "_cache_file", None)
    if index is not None and hasattr(index, "_source_stamp"):
        index._source_stamp = (index._source_stamp, _sources_stamp())
        _read_or_none(index)
    return dispatcher


def _read_or_none(index: Any) -> None:
    """``index`` (numba's cache index of one kernel) reading a file it cannot read (cut short,
    empty: numba renames it into place without syncing it, and a power loss soon after can
    leave it so) as no cache: the kernel compiles again and its files are written anew.
    numba read it as a cache, and the kernel raised at its every call, in every process, until
    the cache was deleted. (An index: empty; a data file: as one deleted, which numba skips.)"""
    load_index, load_data = getattr(index, "_load_index", None), getattr(index, "_load_data", None)
    if load_index is None or load_data is None:
        return

    def _load_index() -> Any:
        try:
            return load_index()
        except OSError:  # (numba's: a missing index is no cache, an unreadable folder is not)
            raise
        except Exception:  # unpickling what is left: EOFError, UnpicklingError, ...
            return {}

    def _load_data(name: str) -> Any:
        try:
            return load_data(name)
        except OSError:
            raise
        except Exception as exc:
            raise OSError(f"numba cache file {name} unreadable: {exc!r}") from exc

    index._load_index, index._load_data = _load_index, _load_data


def missing_from_cache(modules: tuple[str, ...] = ()) -> list[str]:
    """Qualified names of the kernels made so far in this process (by importing their
    modules) whose disk cache holds no code for this machine, or code compiled before an
    edit of their sources: what the first call of each would compile. Only those of
    ``modules`` (full module names) where given: a process may hold kernels it never calls
    (the daemon imports its contact worker's), which say nothing of its own.

    Why a process asks: compiling grows it by about 150 MiB (LLVM's memory, which it keeps
    for its life) where loading the same kernels from the cache costs about 50, so a
    long-running process compiles in a child first (:mod:`cellbridge.daemon.shell.kernels`).
    A kernel whose cache cannot be asked (another numba's internals, an unreadable folder)
    is not named: a child could not tell either, and would be started at every start for
    nothing; the kernel compiles where it is first called, as without this check."""
    out = []
    for dispatcher in _CACHED:
        if modules and dispatcher.py_func.__module__ not in modules:
            continue
        try:
            magic = dispatcher.targetctx.codegen().magic_tuple()
            index = dispatcher._cache._cache_file._load_index()  # {} when absent or stale
            if any(key[1] == magic for key in index):
                continue
        except Exception:  # (see above: not named)
            continue
        out.append(f"{dispatcher.py_func.__module__}.{dispatcher.py_func.__qualname__}")
    return out
