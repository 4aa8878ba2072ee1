"""Which touched elements belong to one contact, and the paper's centroid of a contact.

Clustering is by the layout's geometry (elements sharing a border), so a convex
contact is one cluster wherever it lies; two contacts whose footprints press
neighbouring elements form one cluster too, which the estimator then splits when two
disks explain the readings significantly better than one.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from cellbridge.tactile.arrays import IntArray
from cellbridge.tactile.layout import SkinLayout
from numpy.typing import ArrayLike, NDArray

__all__ = ["centroid_of", "cluster_elements", "force_centroid"]


def cluster_elements(
    layout: SkinLayout,
    active: ArrayLike,
    connectivity: Literal["edge", "corner"] = "edge",
    unknown: ArrayLike | None = None,
) -> IntArray:
    """Connected components of the active elements: a label per element, -1 if inactive.

    Labels are 0..K-1, numbered by the lowest element index in each component.
    Neighbourhood comes from the layout's geometry (edge-sharing by default).

    ``unknown`` (optional, per element): elements whose reading is not known (a silent
    bridge, a frame it has not reported yet). The active elements around one unknown
    element (edges and corners) are one component: the press may well cover it, and
    the two sides of a press read apart only because its middle is missing would
    otherwise be fitted as two contacts (a corner press whose two edge elements are
    late comes out as two diagonal elements). Only one unknown element bridges: touches
    farther apart stay apart, however much of the skin is unknown; so do two with a
    known untouched element on the line between them.
    """
    a = np.asarray(active, dtype=bool)
    if a.shape != (layout.n,):
        raise ValueError(f"active must have shape ({layout.n},), got {a.shape}")
    e = layout.edges if connectivity == "edge" else layout.corner_edges
    e = e[a[e[:, 0]] & a[e[:, 1]]]
    if unknown is not None:
        u = np.asarray(unknown, dtype=bool)
        if u.shape != (layout.n,):
            raise ValueError(f"unknown must have shape ({layout.n},), got {u.shape}")
        e = np.concatenate([e, _across_unknown(layout, a, u)])
    # (one compiled pass; contiguous, writable int64 pairs and bool flags: the one signature the
    # warm-up loads (a read-only array is another type to numba, compiled at its first call).
    # Imported here: this module is the layout's, which imports where numba cannot run.)
    from cellbridge.tactile.cluster_kernel import components

    return components(layout.n, np.require(e, np.int64, ("C", "W")), np.require(a, np.bool_, ("C", "W")))


def _across_unknown(layout: SkinLayout, a: np.ndarray, u: np.ndarray) -> IntArray:
    """Pairs of active elements that one unknown element may join (both among its edge and
    corner neighbours), less those with a known untouched element on the line between their
    centres: one disk over both would press that element too. (Two presses two elements
    apart along a row whose neighbour row is unknown, a line down, read their untouched
    element between them: they are two, not one contact on that element.)"""
    ce = np.concatenate([layout.corner_edges, layout.corner_edges[:, ::-1]])
    ce = ce[u[ce[:, 0]] & ~u[ce[:, 1]] & a[ce[:, 1]]]  # (unknown, active neighbour)
    if not ce.size:
        return np.zeros((0, 2), dtype=np.int64)
    ce = ce[np.lexsort((ce[:, 1], ce[:, 0]))]
    groups = np.split(ce[:, 1], np.flatnonzero(np.diff(ce[:, 0])) + 1)
    pairs = np.array([(m[i], m[j]) for m in groups for i in range(len(m)) for j in range(i + 1, len(m))],
                     dtype=np.int64).reshape(-1, 2)
    if not pairs.size:
        return pairs
    c = layout.centres
    t = np.array([1 / 3, 2 / 3])[None, :, None]  # not the middle: a shared corner for a diagonal pair
    under = layout.element_at(c[pairs[:, :1]] + t * (c[pairs[:, 1:]] - c[pairs[:, :1]]))  # (pairs, 2)
    blocked = ((under >= 0) & ~u[under] & ~a[under]).any(axis=1)
    return pairs[~blocked]


def force_centroid(layout: SkinLayout, weights: ArrayLike, members: ArrayLike,
                   centres: NDArray[np.float64] | None = None) -> tuple[float, float]:
    """The paper's spatial centroid Σw_i·c_i/Σw_i over ``members`` (indices into
    ``weights``; of the layout's elements, unless ``centres`` gives the members' own centres)."""
    idx = np.asarray(members, dtype=np.int64)
    w = np.asarray(weights, dtype=np.float64)[idx]
    return centroid_of(w, layout.centres[idx] if centres is None else centres)


def centroid_of(w: NDArray[np.float64], c: NDArray[np.float64]) -> tuple[float, float]:
    """:func:`force_centroid` of weights ``w`` at centres ``c`` (K, 2), one row each: weights
    not finite or not positive count 0; none left, the centres' mean."""
    w = np.where(np.isfinite(w) & (w > 0), w, 0.0)
    tot = w.sum()
    if not tot > 0:
        return float(c[:, 0].mean()), float(c[:, 1].mean())
    return float(w @ c[:, 0] / tot), float(w @ c[:, 1] / tot)
