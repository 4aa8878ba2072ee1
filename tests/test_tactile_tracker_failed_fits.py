"""The tracker's anchor: a contact that stays a failed fit, and late onsets at a corner."""

from __future__ import annotations

from cellbridge.tactile.contact_result import Contact
from cellbridge.tactile.contacts import ContactEstimator
from cellbridge.tactile.layout import grid_layout
from cellbridge.tactile.tracker import ContactTracker

MM = 1e-3
LAY = grid_layout(1, 8)


def _contact(x: float, elements: tuple[int, ...], fit_ok: bool) -> Contact:
    s = 2 * MM
    return Contact(x=x, y=0.0, force=2.0, area=1e-4, diameter=0.012, centroid_x=x, centroid_y=0.0,
                   model_x=x, model_y=0.0, sigma_x=s, sigma_y=s, sigma_xy=s, cov=((s * s, 0.0), (0.0, s * s)),
                   sigma_force=0.1, sigma_diameter=0.001, elements=elements, valid=True, fit_ok=fit_ok,
                   observable=(True, True), pressure=1e4, force_sum=2.0, chi2=50.0 if not fit_ok else 1.0,
                   dof=1)


def test_a_contact_that_stays_a_failed_fit_while_it_slides_keeps_its_id() -> None:
    # One fitted frame, then a cluster no disk explains (an edge, a palm, two fingers the
    # readings cannot separate) sliding 15 mm a frame, well within the gate (3 x 10 mm
    # motion) of where it was the frame before. The anchor stays at the one fitted frame
    # for ever, so once the cluster has left that fit's elements, it is measured from
    # there: 45 mm away, out of the gate; the track dies and the same contact gets a new id.
    tr = ContactTracker(ContactEstimator(LAY, noise=1e-15), birth_frames=1)
    ids = []
    for k in range(6):
        c = _contact(0.015 * k, (k,), fit_ok=(k == 0))
        out = tr.step([c], t=0.01 * k)
        ids.append([tc.id for tc in out])
    assert ids == [[0]] * 6, ids


def test_a_corner_press_with_two_diagonal_onsets_late_keeps_one_id() -> None:
    # Held up: a corner press (elements 0, 1, 3, 4 of a 3x3) whose diagonal onsets 1 and 3
    # reach the host 120 ms after 0 and 4 (two contacts meanwhile): _one_press, estimating 0
    # and 4 without 1 and 3, finds one press, and the split-off waits.
    import numpy as np

    from support import tracker_frames as t

    rng = np.random.default_rng(41)
    press = t.CORNER_PRESS
    frames = []
    for k in range(16):
        dc1, dc2 = t.frame(press, rng)
        fresh = {0, 1, 3, 4} if k >= 12 else {0, 4}
        if k < 12:
            for e in (1, 3):
                dc1[e] = rng.normal(0, t.NOISE)
                dc2[e] = rng.normal(0, t.NOISE)
        frames.append((dc1, dc2, fresh))
    tr = t.tracker(birth_frames=1)
    seen, split = [], 0
    for k, (dc1, dc2, fresh) in enumerate(frames):
        split += len(tr.estimator.estimate(dc1, dc2, hints=tr.hints())) == 2
        seen.append(tr.update(dc1, dc2, t=0.01 * k, at=0.01 * k, read_at=t._reads(0.0, fresh)))
    assert split >= 10  # read as two while 1 and 3 are late
    assert {tc.id for s in seen for tc in s} == {0}, [[tc.id for tc in s] for s in seen]
