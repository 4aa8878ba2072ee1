"""Contacts on a skin whose charts close on themselves: one contact across a wrap seam.

A cylinder cannot be unrolled flat without a cut. The atlas (see
:mod:`cellbridge.tactile.skin_geometry`) cuts each band somewhere, and a press across
that cut reads, on the flat layout, as two touches at the band's two ends. So a band is
covered by a second chart too, cut on the opposite side (its far half moved one period
back): a press near the first chart's cut is in the middle of the second. Contacts come
from the first chart, except those on the elements next to its cut, which come from the
second, their positions taken back into the band. (Two overlapping charts for a
cylinder, as an atlas of a manifold has them.)

:class:`SeamEstimator` is a :class:`~cellbridge.tactile.estimator.ContactEstimator`
(the tracker and everything else take it as one); with no band it is exactly one.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
from cellbridge.tactile.arrays import FloatArray, IntArray
from cellbridge.tactile.contact_result import Contact
from cellbridge.tactile.element import ElementParams
from cellbridge.tactile.estimator import ContactEstimator, _checked_hints
from cellbridge.tactile.layout import SkinLayout
from cellbridge.tactile.skin_geometry import Band
from numpy.typing import ArrayLike, NDArray

__all__ = ["SeamEstimator"]


@dataclass
class _Twin:
    band: Band
    rows: IntArray  # layout rows of the band's elements
    at_cut: np.ndarray  # (rows,) bool: next to the first chart's cut (either end)
    cut_ids: frozenset[int]
    estimator: ContactEstimator


class SeamEstimator(ContactEstimator):
    """A contact estimator for a layout with bands (``bands``: the atlas's charts that
    close on themselves, :attr:`SkinGeometry.bands`); other keywords as
    :class:`ContactEstimator`. A band needs at least 4 element columns around (a contact
    over at most two columns is then whole in one of the two charts)."""

    def __init__(self, layout: SkinLayout, params: ElementParams | None = None, *,
                 bands: Sequence[Band] = (), **options: object) -> None:
        super().__init__(layout, params, **options)  # type: ignore[arg-type]  # ContactEstimator's own keywords, checked there
        self.bands = tuple(bands)
        self._twins: list[_Twin] = []
        self._row_of = {e: i for i, e in enumerate(layout.ids.tolist())}  # element id -> layout row
        side = layout.side
        for b in self.bands:
            rows = np.flatnonzero(b.holds(layout.centres[:, 0], layout.centres[:, 1]))
            if rows.size == 0:
                continue
            x = layout.centres[rows, 0]
            at_cut = (x < b.x0 + side) | (x > b.x0 + b.period - side)
            moved = layout.centres[rows].copy()
            far = moved[:, 0] >= b.x0 + 0.5 * b.period
            moved[far, 0] -= b.period
            twin_layout = SkinLayout(moved, side=side, ids=layout.ids[rows], neighbour_gap=layout.neighbour_gap)
            twin = ContactEstimator(twin_layout, self.params, **options)  # type: ignore[arg-type]  # as above
            self._twins.append(_Twin(b, rows, at_cut, frozenset(int(i) for i in layout.ids[rows][at_cut]), twin))

    def estimate(self, dC1: ArrayLike, dC2: ArrayLike, active: ArrayLike | None = None, *,
                 hints: ArrayLike | None = None, replaced: NDArray[np.bool_] | None = None) -> list[Contact]:
        if not self._twins:
            return super().estimate(dC1, dC2, active, hints=hints, replaced=replaced)
        given = self._replaced_mask(replaced)
        h = _checked_hints(hints)
        C1, C2, ACT = self._readings(dC1, dC2, active, 1)
        act = ACT[0]
        # Each element's inverse once for the skin: a band's second chart reads the same
        # elements, and an element's inverse is its readings' alone (the same values).
        inv = self._inverse(C1, C2, ACT)
        # The second charts first: the elements whose contacts they give (a press at a cut)
        # are replaced in the first chart's, whose clusters wholly on them are then not
        # estimated at all (they were, and dropped: a seventh of a humanoid's estimate).
        seams: list[tuple[_Twin, list[Contact], frozenset[int]]] = []
        drop = np.zeros(self.layout.n, dtype=bool) if given is None else given.copy()
        for tw in self._twins:
            if not (act[tw.rows] & tw.at_cut).any():
                continue
            b = tw.band
            hb = h[b.holds(h[:, 0], h[:, 1], self.layout.side)] if h.size else h
            if hb.size:
                hb = hb.copy()
                hb[:, 0] = np.where(hb[:, 0] >= b.x0 + 0.5 * b.period, hb[:, 0] - b.period, hb[:, 0])
            # (only a cluster on the cut can give a seam contact: the band's others are not estimated)
            (found,) = tw.estimator._estimate(C1[:, tw.rows], C2[:, tw.rows], ACT[:, tw.rows], hb, ~tw.at_cut,
                                              inv.rows(tw.rows))
            seam = [c for c in found if tw.cut_ids.intersection(c.elements)]
            if not seam:
                continue
            taken = tw.cut_ids.union(*(c.elements for c in seam))
            seams.append((tw, seam, taken))
            drop[[self._row_of[e] for e in taken]] = True
        (contacts,) = self._estimate(C1, C2, ACT, h, drop if drop.any() else None, inv)
        for tw, seam, taken in seams:
            contacts = [c for c in contacts if not taken.intersection(c.elements)]
            contacts += [_wrapped(c, tw.band) for c in seam]
        return contacts

    def estimate_frames(self, dC1: ArrayLike, dC2: ArrayLike, active: ArrayLike | None = None) -> list[list[Contact]]:
        if not self._twins:
            return super().estimate_frames(dC1, dC2, active)
        c1, c2, act = self._readings(dC1, dC2, active, None)
        return [self.estimate(c1[t], c2[t], act[t]) for t in range(c1.shape[0])]


def _wrapped(c: Contact, b: Band) -> Contact:
    """A contact of the second chart with its x coordinates taken back into the band."""
    def w(x: float) -> float:
        return b.wrap(x) if np.isfinite(x) else x
    return replace(c, x=w(c.x), centroid_x=w(c.centroid_x), model_x=w(c.model_x))


def wrapped_distance(a: FloatArray, b: FloatArray, band: Band) -> FloatArray:
    """|a − b| along a band's x, the shorter way round."""
    d = np.abs(np.asarray(a) - np.asarray(b)) % band.period
    return np.minimum(d, band.period - d)
