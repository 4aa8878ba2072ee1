"""Contact estimation over the array (cellbridge.tactile.contacts)."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pytest
from cellbridge.tactile.contacts import (
    Contact,
    ContactEstimator,
    cluster_elements,
    estimate_contacts,
    force_centroid,
)
from cellbridge.tactile.element import ElementParams
from cellbridge.tactile.layout import SkinLayout, grid_layout
from cellbridge.tactile.response import skin_response
from cellbridge.tactile.transfer import counter_delta, counts_per_farad
from hypothesis import given, settings
from hypothesis import strategies as st

LAY = grid_layout(2, 2)  # the paper's 2×2 array, 40 mm pitch; seams at x = 20 mm, y = 20 mm
EST = ContactEstimator(LAY)
P = ElementParams()
MM = 1e-3


def measure(contacts: Any, lay: SkinLayout = LAY, **kw: Any) -> tuple[np.ndarray, np.ndarray]:
    return skin_response(lay, contacts, **kw)


def quantised(dc1: np.ndarray, dc2: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
    """What one 2 ms counter gate per channel reports, as ΔC against the rest value."""
    return [counter_delta(dc, rest, rng.uniform(0, 1, dc.shape)) for dc, rest in ((dc1, P.C1_rest), (dc2, P.C2_rest))]


# Rms of one counter reading: at most half a count.
COUNTER_NOISE = (float(0.5 / counts_per_farad(P.C1_rest)), float(0.5 / counts_per_farad(P.C2_rest)))


# ------------------------------------------------------------------------ clusters


def test_clusters_are_connected_components():
    lay = grid_layout(3, 4)
    active = np.zeros(12, dtype=bool)
    active[[0, 1, 5, 10, 11, 3]] = True  # {0,1,5}, {10,11}, {3}
    lab = cluster_elements(lay, active)
    assert lab[0] == lab[1] == lab[5] and lab[10] == lab[11]
    assert len({lab[0], lab[10], lab[3]}) == 3
    assert (lab[~active] == -1).all() and sorted(set(lab[active])) == [0, 1, 2]
    # Diagonal neighbours are separate contacts unless asked otherwise.
    diag = np.zeros(12, dtype=bool)
    diag[[0, 5]] = True
    assert len(set(cluster_elements(lay, diag)[[0, 5]])) == 2
    assert len(set(cluster_elements(lay, diag, "corner")[[0, 5]])) == 1
    assert (cluster_elements(lay, np.zeros(12, dtype=bool)) == -1).all()
    with pytest.raises(ValueError):
        cluster_elements(lay, np.ones(5, dtype=bool))


def test_active_elements_around_one_unknown_element_are_one_cluster():
    lay = grid_layout(4, 4)
    active = np.zeros(16, dtype=bool)
    active[[5, 10]] = True  # diagonal: apart by edges
    unknown = np.zeros(16, dtype=bool)
    assert len(set(cluster_elements(lay, active, unknown=unknown)[[5, 10]])) == 2
    unknown[6] = True  # the corner's other element: the press may cover it
    lab = cluster_elements(lay, active, unknown=unknown)
    assert lab[5] == lab[10] and lab[6] == -1
    # two apart in a row across one unknown element: one cluster; across two: apart
    row = np.zeros(16, dtype=bool)
    row[[0, 2]] = True
    assert len(set(cluster_elements(lay, row, unknown=np.eye(16, dtype=bool)[1])[[0, 2]])) == 1
    far = np.zeros(16, dtype=bool)
    far[[0, 3]] = True
    assert len(set(cluster_elements(lay, far, unknown=np.eye(16, dtype=bool)[1] | np.eye(16, dtype=bool)[2])[[0, 3]])) == 2
    with pytest.raises(ValueError):
        cluster_elements(lay, active, unknown=np.ones(5, dtype=bool))


def test_presses_with_a_known_untouched_element_between_them_stay_apart_beside_unknown_ones():
    # A gateway line drops and the row next to two presses goes unknown. Each unknown
    # element touches both presses at its corners, yet the element between the presses
    # reads untouched: one disk over both would press it. They were one contact of the
    # summed force, placed on that untouched element.
    lay = grid_layout(4, 4)
    row = np.zeros(16, dtype=bool)
    row[[0, 2]] = True
    behind = np.zeros(16, dtype=bool)
    behind[4:8] = True  # row 1 unknown; element 1 known and untouched
    lab = cluster_elements(lay, row, unknown=behind)
    assert lab[0] != lab[2]
    dc1, dc2 = measure([(0.0, 0.0, 2.0, 0.015), (0.080, 0.0, 2.0, 0.015)], lay)
    assert dc1[1] == 0 and (dc1[[0, 2]] > 0).all()
    dc1[4:8] = np.nan
    dc2[4:8] = np.nan
    cs = sorted(ContactEstimator(lay).estimate(dc1, dc2), key=lambda c: c.x)
    assert len(cs) == 2, cs
    assert [round(c.x, 3) for c in cs] == [0.0, 0.08]
    assert [round(c.force, 1) for c in cs] == [2.0, 2.0]
    # the element between them unknown too: they may be one press over it (one cluster)
    lab = cluster_elements(lay, row, unknown=behind | np.eye(16, dtype=bool)[1])
    assert lab[0] == lab[2]


def test_a_corner_press_whose_two_edge_elements_are_unknown_is_one_contact():
    # The daemon estimates a skin frame with elements it has no reading of (a late bridge,
    # a line that just came back) as NaN. A corner press read on its two diagonal elements
    # only came out as two contacts, each with a quarter of the force: a second contact
    # id for as long as the middle stayed unknown.
    lay = grid_layout(4, 4)
    corner = (0.0585, 0.0625, 3.0, 0.020)  # across the corner of elements 5, 6, 9 and 10
    dc1, dc2 = measure([corner], lay)
    assert (dc1[[5, 6, 9, 10]] > 0).all()
    dc1[[6, 9]] = np.nan
    dc2[[6, 9]] = np.nan
    cs = ContactEstimator(lay).estimate(dc1, dc2)
    assert len(cs) == 1, cs
    c = cs[0]
    # the two diagonal elements do not place it along their diagonal: the fit says so,
    # and puts it at the corner, the middle of what they allow
    assert c.observable == (False, False)
    assert math.hypot(c.x - 0.060, c.y - 0.060) < 1 * MM
    assert c.force == pytest.approx(3.0, rel=0.10)


def test_two_presses_read_on_two_diagonal_elements_stay_two_where_the_last_frame_had_two():
    # Two presses, one inside each diagonal element, the elements between them unknown:
    # their readings fit one disk over the corner as well as two (each element reads its
    # own area and force only). The frames before had two contacts there: they stay two.
    lay = grid_layout(4, 4)
    presses = [(0.045, 0.045, 2.0, 0.015), (0.085, 0.085, 2.0, 0.015)]  # in elements 5 and 10
    dc1, dc2 = measure(presses, lay)
    est = ContactEstimator(lay)
    both = est.estimate(dc1, dc2)
    assert len(both) == 2
    dc1[[6, 9]] = np.nan
    dc2[[6, 9]] = np.nan
    hints = [(c.x, c.y, c.diameter, c.force) for c in both]
    cs = est.estimate(dc1, dc2, hints=hints)
    assert len(cs) == 2, cs
    assert sorted(round(c.force, 1) for c in cs) == [2.0, 2.0]
    # light touches (no fitted disk: the hint says only where they were) stay two as well
    light = [(0.045, 0.045, 0.0, math.nan), (0.085, 0.085, 0.0, math.nan)]
    cs = est.estimate(dc1, dc2, hints=light)
    assert len(cs) == 2, cs
    # one hint (the frames before had one contact): the corner's one press
    assert len(est.estimate(dc1, dc2, hints=hints[:1])) == 1


def test_force_centroid():
    w = np.array([1.0, 3.0, 0.0, 0.0])
    assert force_centroid(LAY, w, [0, 1]) == pytest.approx((0.030, 0.0))
    assert force_centroid(LAY, np.zeros(4), [0, 1]) == pytest.approx((0.020, 0.0))


# ---------------------------------------------------------------------- positions


def test_two_separate_contacts_are_two_clusters():
    lay = grid_layout(3, 3)
    truth = [[0.0, 0.0, 3.0, 0.010], [0.080, 0.062, 5.0, 0.016]]
    cs = ContactEstimator(lay).estimate(*measure(truth, lay))
    assert len(cs) == 2
    a, b = sorted(cs, key=lambda c: c.x)
    assert a.elements == (0,) and b.elements == (5, 8)
    assert a.force == pytest.approx(3.0, rel=1e-6) and b.force == pytest.approx(5.0, rel=1e-6)
    assert b.diameter == pytest.approx(0.016, rel=1e-6)
    assert abs(b.y - 0.062) < 0.01 * MM and b.observable[1]
    assert all(c.valid and c.fit_ok for c in cs)


@settings(max_examples=25, deadline=None)
@given(
    # Offset of the disk centre from the seam. Beyond ±4.5 mm the 10 mm disk's share
    # of the other element drops under a few noise sigmas and the skin no longer sees
    # the straddle (covered by the inside-one-element case).
    st.floats(-4.5 * MM, 4.5 * MM),
    st.floats(-15 * MM, 15 * MM),
    st.floats(2.0, 8.0),
)
def test_straddling_contact_located_within_1mm_and_centroid_is_worse(off, y, f):
    d = 0.010
    x = 0.020 + off
    found = EST.estimate(*measure([x, y, f, d]))
    assert len(found) == 1
    c = found[0]
    assert c.elements == (0, 1) and c.valid and c.fit_ok
    # Across the seam the position is observed: the model-based estimate is within
    # 1 mm (in fact µm), the centroid tens of millimetres off.
    assert c.observable[0]
    assert abs(c.model_x - x) < 1 * MM
    assert c.force == pytest.approx(f, rel=1e-3) and c.diameter == pytest.approx(d, rel=1e-3)
    assert abs(c.centroid_x - x) >= abs(c.model_x - x)
    if abs(off) > 1 * MM:
        assert abs(c.centroid_x - x) > 1 * MM
    # Along the seam it is not: reported at the row's middle, with the spread of the
    # positions consistent with the readings, which include the truth.
    assert not c.observable[1]
    assert abs(c.y) < 1 * MM
    assert abs(c.y - y) <= math.sqrt(3) * c.sigma_y + 0.5 * MM


def test_corner_contact_is_located_in_both_axes():
    for x, y, f, d in [(0.018, 0.023, 5.0, 0.016), (0.025, 0.013, 8.0, 0.026), (0.020, 0.020, 3.0, 0.010)]:
        (c,) = EST.estimate(*measure([x, y, f, d]))
        assert c.observable == (True, True)
        assert math.hypot(c.x - x, c.y - y) < 0.1 * MM
        assert c.sigma_xy < 0.1 * MM
        if (x, y) != (0.020, 0.020):  # the centroid is right only at the symmetric point
            assert math.hypot(c.centroid_x - x, c.centroid_y - y) > 1 * MM


def test_disk_inside_one_element_reports_the_centre_with_the_feasible_spread():
    for x, y, d in [(0.003, -0.007, 0.010), (-0.012, 0.0, 0.010), (0.0, 0.0, 0.026)]:
        (c,) = EST.estimate(*measure([x, y, 5.0, d]))
        assert c.observable == (False, False)
        assert c.x == pytest.approx(0.0, abs=0.3 * MM) and c.y == pytest.approx(0.0, abs=0.3 * MM)
        # Uniform over the centres keeping the disk on the element: (side − D)/√12,
        # a little more for the noise margin at the ends.
        width = 0.040 - d
        assert width / math.sqrt(12) <= c.sigma_x <= (width + 3 * MM) / math.sqrt(12)
        assert abs(c.x - x) <= math.sqrt(3) * c.sigma_x
        assert c.force == pytest.approx(5.0, rel=1e-6)


def test_method_area_agrees():
    est = ContactEstimator(LAY, method="area")
    (c,) = est.estimate(*measure([0.0215, 0.004, 4.0, 0.016]))
    assert abs(c.x - 0.0215) < 0.01 * MM and c.force == pytest.approx(4.0, rel=1e-6)
    with pytest.raises(ValueError):
        ContactEstimator(LAY, method="area", spread=0.002)


def test_straddling_contacts_with_counter_quantisation():
    rng = np.random.default_rng(11)
    est = ContactEstimator(LAY, noise=COUNTER_NOISE)
    errs, cerrs, z = [], [], []
    for x in np.linspace(0.0155, 0.0245, 10):
        truth = [x, 0.0, 3.0, 0.010]
        (c,) = est.estimate(*quantised(*measure(truth), rng))
        errs.append(c.x - x)
        cerrs.append(c.centroid_x - x)
        z.append((c.x - x) / c.sigma_x)
    rms = math.sqrt(np.mean(np.square(errs)))
    assert rms < 1 * MM
    assert math.sqrt(np.mean(np.square(cerrs))) > 5 * rms
    assert np.max(np.abs(z)) < 5  # the reported uncertainty is not a false precision


def test_light_touch_is_flagged_and_bounded_by_the_shares():
    # 0.3 N on a 10 mm disk is in the inverse's ambiguous low-pressure region: no
    # force and no diameter, but across the seam the elements' ratio still bounds
    # the centre for every diameter the readings allow.
    x = 0.018
    (c,) = EST.estimate(*measure([x, 0.0, 0.3, 0.010]))
    assert not c.valid and math.isnan(c.force) and math.isnan(c.diameter)
    assert c.fit_ok and c.observable == (True, False)
    assert abs(c.x - x) <= 2 * c.sigma_x
    assert c.sigma_x < 5 * MM  # the interval, not a whole element (≈ 11.5 mm)
    assert abs(c.centroid_x - x) > 3 * c.sigma_x  # the centroid is far outside it
    assert c.sigma_y > 5 * MM  # along the seam it is unknown


def test_light_touch_interval_covers_the_truth_under_noise():
    rng = np.random.default_rng(4)
    est = ContactEstimator(LAY, noise=1e-15)
    for _ in range(20):
        d = rng.uniform(0.008, 0.016)
        x = 0.020 + rng.uniform(-0.4, 0.4) * d
        dc1, dc2 = measure([x, 0.0, rng.uniform(0.15, 0.4), d])
        dc1 = dc1 + rng.normal(0, 1e-15, 4)
        dc2 = dc2 + rng.normal(0, 1e-15, 4)
        cs = est.estimate(dc1, dc2)
        assert len(cs) == 1
        c = cs[0]
        if not c.valid and c.observable[0]:
            assert abs(c.x - x) <= 2 * c.sigma_x + 0.05 * MM


def test_spread_model_fit():
    s = 0.002
    est = ContactEstimator(LAY, spread=s)
    (c,) = est.estimate(*measure([0.018, 0.003, 3.0, 0.010], spread=s))
    assert abs(c.x - 0.018) < 0.1 * MM and c.force == pytest.approx(3.0, rel=1e-2)
    assert c.diameter == pytest.approx(0.010, rel=1e-2)
    assert abs(c.y - 0.003) <= math.sqrt(3) * c.sigma_y
    # The uniform model on the same readings is biased: tension makes the contact
    # look larger and softer than it is.
    (u,) = EST.estimate(*measure([0.018, 0.003, 3.0, 0.010], spread=s))
    assert u.diameter > 0.012


def test_active_mask_nan_and_output_format():
    dc1, dc2 = measure([[0.0, 0.0, 3.0, 0.010], [0.040, 0.040, 2.0, 0.012]])
    cs = EST.estimate(dc1, dc2, active=np.array([True, False, False, False]))
    assert len(cs) == 1 and cs[0].elements == (0,)
    dc1[3] = np.nan
    assert len(EST.estimate(dc1, dc2)) == 1
    d = cs[0].to_dict()
    json.dumps(d)
    assert set(d) == set(Contact.__dataclass_fields__)
    assert estimate_contacts(LAY, *measure([0.0, 0.0, 3.0, 0.010]))[0].force == pytest.approx(3.0)
    assert EST.estimate(np.zeros(4), np.zeros(4)) == []
    with pytest.raises(ValueError):
        EST.estimate(np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError):
        EST.estimate(np.zeros(4), np.zeros(4), active=np.ones(2, dtype=bool))
    with pytest.raises(ValueError):
        ContactEstimator(LAY, method="centroid")  # type: ignore[arg-type]  # the point: an unknown method is refused
    with pytest.raises(ValueError):
        ContactEstimator(LAY, noise=0.0)


# ------------------------------------------------------------------ touching contacts


def noisy(contacts, lay, rng, noise=1e-15):
    dc1, dc2 = measure(contacts, lay)
    return dc1 + rng.normal(0, noise, lay.n), dc2 + rng.normal(0, noise, lay.n)


LAY34 = grid_layout(3, 4)


def test_two_disks_of_different_force_in_one_cluster_come_back_as_two():
    # Each disk sits mainly on its own element (neighbours along x) and straddles a
    # corner, so both positions are observable; their footprints share elements 1
    # and 5, so clustering makes one cluster of them.
    rng = np.random.default_rng(7)
    est = ContactEstimator(LAY34, noise=1e-15)
    truth = [[0.017, 0.022, 3.0, 0.016], [0.057, 0.018, 8.0, 0.020]]
    for _ in range(5):
        cs = est.estimate(*noisy(truth, LAY34, rng))
        assert len(cs) == 2
        got = sorted(cs, key=lambda c: c.x)
        for c, (x, y, f, _d) in zip(got, truth):
            assert math.hypot(c.x - x, c.y - y) < 1 * MM
            assert c.force == pytest.approx(f, rel=0.05)
            assert c.observable == (True, True)
            assert abs(c.x - x) <= 3 * c.sigma_x and abs(c.y - y) <= 3 * c.sigma_y
        # One cluster, shared elements: both contacts name the middle ones.
        assert {1, 5} <= set(got[0].elements) & set(got[1].elements)


def test_physically_touching_disks_are_separated():
    # Two disks in contact with each other on neighbouring elements: the one over
    # the corner is located to well under 1 mm; the other lies inside its column,
    # so its x is honestly reported as unresolved with a σ that covers it.
    rng = np.random.default_rng(8)
    est = ContactEstimator(LAY34, noise=1e-15)
    a, b = [0.017, 0.022, 3.0, 0.016], [0.031, 0.022, 8.0, 0.012]
    cs = est.estimate(*noisy([a, b], LAY34, rng))
    assert len(cs) == 2
    ca = min(cs, key=lambda c: abs(c.force - 3.0))
    cb = max(cs, key=lambda c: abs(c.force - 3.0))
    assert math.hypot(ca.x - a[0], ca.y - a[1]) < 1 * MM
    assert abs(cb.y - b[1]) < 1 * MM and cb.force == pytest.approx(8.0, rel=0.05)
    assert not cb.observable[0] and abs(cb.x - b[0]) <= math.sqrt(3) * cb.sigma_x + 0.5 * MM


def test_single_disk_is_never_split():
    rng = np.random.default_rng(9)
    lay = grid_layout(3, 3)
    est = ContactEstimator(lay, noise=1e-15)
    for _ in range(60):
        d = rng.uniform(0.008, 0.035)
        x, y = rng.uniform(-0.01, 0.09, 2)
        cs = est.estimate(*noisy([x, y, rng.uniform(1.0, 15.0), d], lay, rng))
        assert len(cs) == 1, (x, y, d, [(c.x, c.y, c.force) for c in cs])


def test_split_can_be_turned_off():
    rng = np.random.default_rng(7)
    truth = [[0.017, 0.022, 3.0, 0.016], [0.057, 0.018, 8.0, 0.020]]
    cs = ContactEstimator(LAY34, noise=1e-15, split=False).estimate(*noisy(truth, LAY34, rng))
    assert len(cs) == 1 and cs[0].chi2 > 10 * cs[0].dof  # the misfit shows


def test_estimate_frames_gives_each_frame_what_estimate_gives():
    rng = np.random.default_rng(12)
    lay = grid_layout(3, 3)
    est = ContactEstimator(lay, noise=1e-15)
    scenes = [
        [[0.018, 0.004, 4.0, 0.012]],
        [],  # nothing touched
        [[0.0, 0.0, 3.0, 0.010], [0.080, 0.062, 5.0, 0.016]],
        [[0.018, 0.0, 0.3, 0.010]],  # a light touch
        [[0.017, 0.022, 3.0, 0.016], [0.057, 0.018, 8.0, 0.020]],  # one cluster, two disks
    ]
    frames = [noisy(s, lay, rng) if s else (rng.normal(0, 1e-15, lay.n), rng.normal(0, 1e-15, lay.n))
              for s in scenes]
    d1 = np.stack([f[0] for f in frames])
    d2 = np.stack([f[1] for f in frames])
    active = np.stack([(f[0] > 6e-15) | (f[1] > 6e-15) for f in frames])
    batched = est.estimate_frames(d1, d2, active)
    assert len(batched) == len(scenes)
    for t in range(len(scenes)):
        one = est.estimate(d1[t], d2[t], active[t])
        assert [c.to_dict() for c in batched[t]] == [c.to_dict() for c in one]
    assert [len(b) for b in batched] == [1, 0, 2, 1, 2]
    with pytest.raises(ValueError, match="shape"):
        est.estimate_frames(d1[0], d2[0])
    with pytest.raises(ValueError, match="active"):
        est.estimate_frames(d1, d2, active[:, :3])


# ------------------------------------------------------------------ hard presses


@pytest.mark.parametrize(
    ("x", "y", "f", "d"),
    [
        (0.060, 0.060, 50.0, 0.012),  # a finger pressed hard on a corner of four elements
        (0.020, 0.000, 120.0, 0.012),  # across a seam, saturating the foam
        (0.000, 0.000, 40.0, 0.006),  # a tool tip inside one element
    ],
)
def test_hard_press_is_fitted_with_its_force_not_taken_for_a_light_touch(x, y, f, d):
    """Each element's inverse finds such a press too noisy to report (its pressure is on
    the unique high branch, so no light touch reads like it); the cluster's fit still
    measures the force. It used to come back valid=False with a NaN force, exactly
    like a feather."""
    lay = grid_layout(4, 4)
    (c,) = ContactEstimator(lay).estimate(*measure([[x, y, f, d]], lay))
    assert c.valid and c.fit_ok
    assert c.force == pytest.approx(f, rel=1e-6)
    assert c.diameter == pytest.approx(d, rel=1e-6)
    assert math.isfinite(c.sigma_force) and c.sigma_force > 0
    assert abs(c.x - x) <= 2 * c.sigma_x + 1e-9 and abs(c.y - y) <= 2 * c.sigma_y + 1e-9


def test_hard_press_force_sigma_covers_the_truth_under_noise():
    """Where the foam saturates the cost in ln F is flat upwards: the curvature's σ
    alone left the truth up to 6 σ above the fit. σ_F must hold it at 2σ as often
    as it claims, with no wild misses."""
    lay = grid_layout(4, 4)
    est = ContactEstimator(lay)
    rng = np.random.default_rng(7)
    z = []
    for _ in range(80):
        f, d = rng.uniform(30.0, 300.0), rng.uniform(0.006, 0.016)
        x, y = rng.uniform(0.0, 0.12, 2)
        dc1, dc2 = measure([[x, y, f, d]], lay)
        dc1 = dc1 + rng.normal(0, 7e-16, dc1.shape)
        dc2 = dc2 + rng.normal(0, 7e-16, dc2.shape)
        active = np.maximum(dc1, dc2) > 50e-15  # the calibrator's touch threshold
        cs = est.estimate(dc1, dc2, active)
        assert len(cs) == 1
        assert cs[0].valid
        z.append((cs[0].force - f) / cs[0].sigma_force)
    z = np.abs(np.array(z))
    assert np.mean(z <= 2.0) >= 0.9
    assert z.max() < 4.0


def test_two_fingers_with_a_touched_neighbour_that_reads_nothing_do_not_crash_the_split():
    """The calibrator's hysteresis keeps an element touched after the finger slid off
    it (ΔC back near zero). With two fingers beside it, the split's seed that credits
    that element alone to the second disk has no area: math.log(0) raised ValueError
    out of estimate(), killing the frame loop (136 of 3 000 random frames of this kind)."""
    lay = grid_layout(3, 3)
    truth = [[0.088, 0.075, 8.0, 0.016], [0.052, 0.088, 7.0, 0.014]]  # on elements 8 and 7
    dc1, dc2 = measure(truth, lay)
    active = dc1 > 50e-15
    assert not active[4] and dc1[4] == 0.0
    active[4] = True  # still touched: it has not read below the leave threshold long enough
    # Readings the model made, trusted to the noise: each finger lies inside its own
    # element, and only their 14 % different pressures tell them from one disk.
    cs = ContactEstimator(lay, model_error=0.0).estimate(dc1, dc2, active)
    assert len(cs) == 2
    for (x, y, f, _d), c in zip(sorted(truth), sorted(cs, key=lambda c: c.x)):
        assert c.valid and c.fit_ok
        assert abs(c.x - x) <= 3 * c.sigma_x + 1e-6 and abs(c.y - y) <= 3 * c.sigma_y + 1e-6
        assert c.force == pytest.approx(f, rel=1e-3)


@pytest.mark.parametrize(
    ("element", "channel", "glitch"),
    [(0, 0, -1e-12), (0, 0, 0.0), (1, 1, -1e-13), (2, 0, -1e-12), (0, 1, 0.0)],
)
def test_failed_fit_reports_the_centroid_with_a_sigma_that_holds_it(element, channel, glitch):
    """A one-channel glitch (a dropped reading sent as 0, a negative spike) on a touched
    element or its neighbour makes the disk fit fail, and the contact falls back to the
    centroid. Its σ was the failed fit's covariance: 0.5 mm with the truth 5 mm away,
    or inf with a NaN σ_xy (an inf σ matches every track in the tracker), and the axes
    claimed observable."""
    lay = grid_layout(3, 3)
    truth = (0.020, 0.0, 5.0, 0.012)  # across the seam of elements 0 and 1
    dc = np.array(measure([truth], lay))
    active = dc.max(axis=0) > 50e-15
    dc[channel, element] = glitch
    cs = ContactEstimator(lay).estimate(dc[0], dc[1], active)
    assert len(cs) == 1 and cs[0].valid and not cs[0].fit_ok
    (c,) = cs
    for v, s, t in ((c.x, c.sigma_x, truth[0]), (c.y, c.sigma_y, truth[1])):
        assert math.isfinite(s) and 0 < s < 0.1
        assert abs(v - t) <= 2 * s
    assert math.isfinite(c.sigma_xy) and c.sigma_xy >= max(c.sigma_x, c.sigma_y) - 1e-12
    assert c.observable == (False, False)


def test_spread_refinement_builds_profile_rows_only_for_fits_it_keeps(monkeypatch):
    """Readings no disk explains (a hand, a glitch) fail the uniform fit at any size, up
    to 100 element sides; the spread refinement sized its profile rows by that failed
    fit: 0.8 m of disk on a 2×2 skin asked for ~6 000 rows, a 0.5 GB temporary and
    seconds inside one frame (MemoryError under a 4 GB limit). Only fits it keeps,
    and no disk larger than the skin, may size them."""
    from cellbridge.tactile.spread_model import DV, PROFILE_ROWS

    s = 0.002
    est = ContactEstimator(LAY, spread=s)
    lo, hi = LAY.bounds[:, :2].min(axis=0), LAY.bounds[:, 2:].max(axis=0)
    bound = int(math.ceil((0.5 * float(np.hypot(*(hi - lo))) * 1.5 / s + 2.0) / DV)) + 2
    asked = []
    real = PROFILE_ROWS.upto

    def spy(k_max):
        asked.append(k_max)
        assert k_max <= max(bound, PROFILE_ROWS.rows.shape[0]), f"{k_max} rows asked for"
        return real(k_max)

    monkeypatch.setattr(PROFILE_ROWS, "upto", spy)
    dc1 = np.array([1.57487310e-13, 6.78318954e-12, 1.72295669e-11, 2.76113861e-11])
    dc2 = np.array([8.96837013e-14, 8.01914861e-12, 1.69099721e-11, 1.31653495e-11])
    cs = est.estimate(dc1, dc2)
    assert asked and cs and all(math.isfinite(c.x) and math.isfinite(c.sigma_x) for c in cs)


def test_a_press_on_a_skin_with_a_few_percent_gain_error_is_one_contact():
    """No skin is its model. With 3 % rms gain error per channel and element, one
    press came back as two contacts on about a third of presses: a small second disk
    wholly inside one element soaks up that element's excess, far above the noise.
    The split's model tolerance (model_error, 1 % of the cluster's largest reading by
    default) takes such a misfit for what it is."""
    rng = np.random.default_rng(21)
    lay = grid_layout(4, 4)
    est = ContactEstimator(lay, noise=1e-15)
    whole = ContactEstimator(lay, noise=1e-15, split=False)  # one contact per cluster
    two = []
    for _ in range(40):
        truth = [*rng.uniform(-0.016, 0.136, 2), rng.uniform(2.0, 15.0), rng.uniform(0.008, 0.030)]
        dc1, dc2 = measure(truth, lay)
        dc1 = dc1 * (1 + rng.normal(0, 0.03, lay.n)) + rng.normal(0, 1e-15, lay.n)
        dc2 = dc2 * (1 + rng.normal(0, 0.03, lay.n)) + rng.normal(0, 1e-15, lay.n)
        if len(est.estimate(dc1, dc2)) > len(whole.estimate(dc1, dc2)):
            two.append(truth)
    assert two == []
    with pytest.raises(ValueError, match="model_error"):
        ContactEstimator(lay, model_error=-0.1)
