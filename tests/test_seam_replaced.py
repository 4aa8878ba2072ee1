"""A seam press's contacts replace the first chart's without estimating the clusters they replace.

:class:`SeamEstimator` takes the contacts of a press at a band's cut from the band's second
chart and drops the first chart's contacts on those elements. It asks the first chart not
to estimate the clusters wholly on them (``replaced``): the contacts must be exactly those
of estimating every cluster and dropping them afterwards, whatever the frame (presses at
the cut and away from it, several at once, elements without a reading, hints of a frame
before)."""

from __future__ import annotations

import numpy as np
from cellbridge.daemon.core.elements import default_params
from cellbridge.emulator.world.robot_world import ARM_SKIN
from cellbridge.tactile.contact_result import Contact
from cellbridge.tactile.estimator import ContactEstimator
from cellbridge.tactile.inversion import DEFAULT_NOISE
from cellbridge.tactile.response import skin_response
from cellbridge.tactile.seam_estimator import SeamEstimator, _wrapped
from cellbridge.tactile.skin_geometry import parse_skin
from hypothesis import given, settings
from hypothesis import strategies as st

SKIN = parse_skin(ARM_SKIN, "arm skin")
LAY = SKIN.layout()
PARAMS = default_params(LAY)
ENTER = 50e-15  # the daemon's touch threshold (F)
EST = SeamEstimator(LAY, PARAMS, bands=SKIN.bands, noise=DEFAULT_NOISE)


def every_cluster_then_dropped(dc1: np.ndarray, dc2: np.ndarray, act: np.ndarray, hints: np.ndarray) -> list[Contact]:
    """What the seam estimator gave when the first chart estimated every cluster: its
    contacts, those on a seam press's elements then dropped for the second chart's."""
    contacts = ContactEstimator.estimate(EST, dc1, dc2, act, hints=hints)
    for tw in EST._twins:
        if not (act[tw.rows] & tw.at_cut).any():
            continue
        b = tw.band
        hb = hints[b.holds(hints[:, 0], hints[:, 1], LAY.side)] if hints.size else hints
        if hb.size:
            hb = hb.copy()
            hb[:, 0] = np.where(hb[:, 0] >= b.x0 + 0.5 * b.period, hb[:, 0] - b.period, hb[:, 0])
        found = tw.estimator.estimate(dc1[tw.rows], dc2[tw.rows], act[tw.rows], hints=hb)
        seam = [c for c in found if tw.cut_ids.intersection(c.elements)]
        if not seam:
            continue
        taken = tw.cut_ids.union(*(c.elements for c in seam))
        contacts = [c for c in contacts if not taken.intersection(c.elements)]
        contacts += [_wrapped(c, b) for c in seam]
    return contacts


def frame(presses: list[tuple[int, float, float, float, float]], seed: int, unknown: list[int]
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ΔC1, ΔC2 and touched flags of ``presses`` (element row, offset x and y in sides,
    force, diameter), each with its copy one band over across a wrap seam; ``unknown``
    rows without a reading (NaN)."""
    disks = []
    for row, dx, dy, force, diameter in presses:
        x, y = LAY.centres[row, :2]
        disk = [(float(x + dx * LAY.side), float(y + dy * LAY.side), force, diameter)]
        for b in SKIN.bands:
            disk += b.ghosts(disk[:1], LAY.side)
        disks += disk
    d1, d2 = skin_response(LAY, disks, PARAMS)
    rng = np.random.default_rng(seed)
    d1 = d1 + rng.normal(0.0, DEFAULT_NOISE, LAY.n)
    d2 = d2 + rng.normal(0.0, DEFAULT_NOISE, LAY.n)
    d1[unknown] = np.nan
    d2[unknown] = np.nan
    with np.errstate(invalid="ignore"):
        return d1, d2, (d1 > ENTER) | (d2 > ENTER)


# elements at a band's cut (either end) are drawn often: the case the seam estimator is about
AT_CUT = sorted({int(r) for tw in EST._twins for r in tw.rows[tw.at_cut]})
ROWS = st.one_of(st.sampled_from(AT_CUT), st.integers(0, LAY.n - 1))
PRESS = st.tuples(ROWS, st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(0.3, 6.0), st.floats(0.006, 0.03))


@settings(max_examples=60, deadline=None)
@given(st.lists(PRESS, min_size=1, max_size=4), st.integers(0, 2**31), st.lists(st.integers(0, LAY.n - 1), max_size=3),
       st.booleans())
def test_the_seam_estimate_is_every_cluster_estimated_then_dropped(presses, seed, unknown, hinted) -> None:
    dc1, dc2, act = frame(presses, seed, unknown)
    hints = np.zeros((0, 4))
    if hinted:  # the contacts of a frame before (a slightly different press): the tracker's hints
        before = EST.estimate(*frame([(r, dx + 0.1, dy, f * 1.1, d) for r, dx, dy, f, d in presses], seed + 1, [])[:3])
        hints = np.array([(c.x, c.y, c.diameter, c.force) for c in before], dtype=np.float64).reshape(-1, 4)
    want = every_cluster_then_dropped(dc1, dc2, act, hints)
    got = EST.estimate(dc1, dc2, act, hints=hints)
    assert repr(got) == repr(want)  # (repr: NaN fields compare equal, every field and the order)


@settings(max_examples=40, deadline=None)
@given(st.lists(PRESS, min_size=1, max_size=4), st.integers(0, 2**31), st.lists(st.integers(0, LAY.n - 1), max_size=8))
def test_replaced_elements_drop_only_the_clusters_wholly_on_them(presses, seed, replaced_rows) -> None:
    """``replaced``: a contact of a cluster wholly on those elements is gone, every other
    contact is as without it, in the same order."""
    dc1, dc2, act = frame(presses, seed, [])
    plain = ContactEstimator(LAY, PARAMS, noise=DEFAULT_NOISE)
    every = plain.estimate(dc1, dc2, act)
    replaced = np.zeros(LAY.n, dtype=bool)
    replaced[replaced_rows] = True
    got = plain.estimate(dc1, dc2, act, replaced=replaced)
    ids = set(LAY.ids[replaced].tolist())
    left = [c for c in every if c not in got]
    assert repr([c for c in every if c in got]) == repr(got)  # the others, unchanged and in order
    assert all(c.elements and set(c.elements) <= ids for c in left)
    if not replaced.any():
        assert repr(got) == repr(every)


def test_replaced_must_be_one_flag_per_element() -> None:
    """``replaced`` is a mask over the layout's elements: element rows or ids, or a mask of
    another layout, would silently drop the wrong clusters' contacts (or keep them), so
    anything but (N,) flags is refused."""
    import pytest

    dc1, dc2, act = frame([(AT_CUT[0], 0.0, 0.0, 2.0, 0.02), (0, 0.0, 0.0, 2.0, 0.02)], 1, [])
    plain = ContactEstimator(LAY, PARAMS, noise=DEFAULT_NOISE)
    rows = np.flatnonzero(act)
    for est in (plain, EST):
        for bad in (rows, np.ones(LAY.n + 3, dtype=bool), np.ones(LAY.n - 1, dtype=bool),
                    np.arange(LAY.n), np.ones((1, LAY.n), dtype=bool)):
            with pytest.raises(ValueError, match="replaced"):
                est.estimate(dc1, dc2, act, replaced=bad)  # type: ignore[arg-type]  # the wrong types are the point
    none = np.zeros(LAY.n, dtype=bool)
    assert repr(EST.estimate(dc1, dc2, act, replaced=none)) == repr(EST.estimate(dc1, dc2, act))
