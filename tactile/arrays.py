"""The numpy array types the package's signatures use, defined once, and array helpers they share."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

__all__ = ["BoolArray", "FloatArray", "IntArray", "median0", "rows_all", "rows_any"]


def median0(a: FloatArray) -> Any:
    """``np.median(a, axis=0)`` of a float64 array (1-D: a scalar; 2-D: a row), bit for bit:
    the same partition and the same arithmetic, without np.median's generic machinery (a
    skin frame takes a few medians of a thousand readings; the wrapper cost as much as the
    partition). NaN anywhere in a column: NaN, as np.median gives it."""
    n = a.shape[0]
    if n == 0 or a.dtype != np.float64 or a.ndim > 2:
        return np.median(a, axis=0)
    h = n // 2
    p = np.partition(a, [h - 1, h, -1] if n % 2 == 0 else [h, -1], axis=0)
    m = (0.0 + p[h - 1] + p[h]) / 2 if n % 2 == 0 else (0.0 + p[h]) / 1  # (np.mean's sum starts at 0.0: -0.0 is 0.0)
    last = p[n - 1]
    nan = np.isnan(last)
    if a.ndim == 1:
        return last if nan else m
    return np.where(nan, last, m) if nan.any() else m


def rows_any(m: BoolArray) -> BoolArray:
    """``m.any(axis=1)`` of an (N, C) boolean array, column by column: a reduction along a
    short last axis costs several times the C element-wise ``|`` it amounts to (the
    calibrator asks a dozen of them of every skin frame)."""
    out = m[:, 0].copy()
    for j in range(1, m.shape[1]):
        out |= m[:, j]
    return out


def rows_all(m: BoolArray) -> BoolArray:
    """``m.all(axis=1)`` of an (N, C) boolean array, column by column (see :func:`rows_any`)."""
    out = m[:, 0].copy()
    for j in range(1, m.shape[1]):
        out &= m[:, j]
    return out
