"""The tracker's association takes each contact's distance terms once per frame: the pairs
it makes are those of ContactTracker._distance asked pair by pair (the plain form), on
random tracks and contacts (σ infinite or NaN, positions not finite, shared elements)."""

from __future__ import annotations

import math

from cellbridge.tactile import ContactEstimator, grid_layout
from cellbridge.tactile.contact_result import Contact
from cellbridge.tactile.tracker import ContactTracker, _Track
from hypothesis import given
from hypothesis import strategies as st

values = st.one_of(st.floats(-0.02, 0.02), st.sampled_from([math.inf, math.nan]))
sigmas = st.one_of(st.floats(0.0, 0.01), st.sampled_from([math.inf, math.nan, 0.0, 0.002, 0.01]))
contacts = st.builds(lambda x, y, sx, sy, els: Contact(
    x=x, y=y, force=1.0, area=1e-4, diameter=0.01, centroid_x=x, centroid_y=y, model_x=x, model_y=y,
    sigma_x=sx, sigma_y=sy, sigma_xy=0.0, cov=((0.0, 0.0), (0.0, 0.0)), sigma_force=0.1, sigma_diameter=0.001,
    elements=tuple(els), valid=True, fit_ok=True, observable=(True, True), pressure=1e4, force_sum=1.0, chi2=1.0,
    dof=3), st.floats(-0.02, 0.02), values, sigmas, sigmas, st.lists(st.integers(0, 8), min_size=1, max_size=3))


def _plain(tracker: ContactTracker, cs: list[Contact]) -> list[tuple[int, int]]:
    cand = []
    for ti, tr in enumerate(tracker._tracks):
        ref = tr.anchor if tr.anchor is not None else tr.contact
        for ci, c in enumerate(cs):
            d = tracker._distance(ref, c)
            shared = not tr.elements.isdisjoint(frozenset(c.elements))
            if d <= tracker.gate or shared:
                cand.append((not (shared and tr.id is not None), d, tr.id is None, ti, ci))
    cand.sort()
    used_t, used_c, pairs = set(), set(), []
    for _, _, _, ti, ci in cand:
        if ti in used_t or ci in used_c:
            continue
        used_t.add(ti)
        used_c.add(ci)
        pairs.append((ti, ci))
    return pairs


@given(st.lists(st.tuples(contacts, st.booleans(), st.one_of(st.none(), contacts)), max_size=6),
       st.lists(contacts, max_size=6), st.floats(0.0, 0.02))
def test_the_pairs_are_those_of_the_distance_pair_by_pair(tracks, cs, motion):
    tracker = ContactTracker(ContactEstimator(grid_layout(3, 3)), motion=motion)
    tracker._tracks = [_Track(c, 0, id=k if born else None, elements=frozenset(c.elements), anchor=a)
                       for k, (c, born, a) in enumerate(tracks)]
    assert tracker._associate(cs) == _plain(tracker, cs)
