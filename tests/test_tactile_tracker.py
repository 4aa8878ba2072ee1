"""Contacts across frames (cellbridge.tactile.tracker)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from cellbridge.tactile.contacts import ContactEstimator
from cellbridge.tactile.layout import grid_layout
from cellbridge.tactile.tracker import ContactTracker

from support.tracker_frames import CORNER_PRESS, LAY, MM, NOISE, _reads, frame, tracker


def test_contact_is_born_after_it_persists_and_keeps_its_id():
    rng = np.random.default_rng(1)
    tr = tracker(birth_frames=3)
    press = [0.018, 0.004, 4.0, 0.012]
    seen = [tr.update(*frame(press, rng), t=0.004 * k) for k in range(6)]
    assert [len(s) for s in seen] == [0, 0, 1, 1, 1, 1]
    ids = {s[0].id for s in seen[2:]}
    assert ids == {0}
    last = seen[-1][0]
    assert last.age == 6 and last.missed == 0 and last.t == pytest.approx(0.020)
    assert abs(last.contact.x - 0.018) < 0.1 * MM
    json.dumps(last.to_dict())
    assert tr.births == 1 and tr.rejected == 0


def test_one_frame_spike_on_an_untouched_element_never_becomes_a_contact():
    rng = np.random.default_rng(2)
    tr = tracker(birth_frames=2)
    press = [0.0, 0.0, 4.0, 0.012]  # a steady contact on element 0
    for k in range(12):
        dc1, dc2 = frame(press, rng)
        if k == 5:  # a spike on element 8, far from the press, on one frame only
            dc1[8] += 0.4e-12
            dc2[8] += 0.2e-12
        out = tr.update(dc1, dc2)
        assert [tc.id for tc in out] == ([] if k == 0 else [0])
        assert all(8 not in tc.contact.elements for tc in out)
    assert tr.births == 1 and tr.rejected == 1 and tr.candidates == 0
    # The same spike held for two frames is a contact: the rejection was the gap.
    tr2 = tracker(birth_frames=2)
    for _k in range(3):
        dc1, dc2 = frame([], rng)
        dc1[8] += 0.4e-12
        dc2[8] += 0.2e-12
        out = tr2.update(dc1, dc2)
    assert len(out) == 1


def test_id_persists_while_a_disk_slides_across_a_seam():
    rng = np.random.default_rng(3)
    tr = tracker(birth_frames=2)
    ids, xs = set(), []
    for x in np.arange(0.004, 0.036, 0.0005):  # element 0 → seam at 20 mm → element 1
        out = tr.update(*frame([x, 0.002, 5.0, 0.014], rng))
        if out:
            assert len(out) == 1
            ids.add(out[0].id)
            c = out[0].contact
            if c.observable[0]:
                xs.append(c.x - x)
    assert ids == {0}
    assert tr.births == 1 and tr.deaths == 0
    assert xs and max(abs(e) for e in xs) < 0.1 * MM  # across the seam it was located


def test_two_fingers_keep_their_ids_and_a_lifted_one_dies():
    rng = np.random.default_rng(4)
    tr = tracker(birth_frames=2, max_missed=1)
    a = [0.018, 0.0, 3.0, 0.012]
    b = [0.078, 0.060, 6.0, 0.016]
    for _ in range(4):
        out = tr.update(*frame([a, b], rng))
    by_x = {round(tc.contact.x, 2): tc.id for tc in out}
    assert len(by_x) == 2
    for _ in range(3):
        out = tr.update(*frame([b], rng))  # finger a lifted
    assert len(out) == 1 and out[0].id == by_x[round(0.078, 2)]
    assert tr.deaths == 1


def test_warm_start_gives_the_same_answer_as_a_cold_fit():
    rng = np.random.default_rng(5)
    est = ContactEstimator(LAY, noise=NOISE)
    tr = ContactTracker(est, birth_frames=1)
    for x in (0.0170, 0.0175, 0.0180):
        dc1, dc2 = frame([x, 0.021, 4.0, 0.014], rng)
        (warm,) = tr.update(dc1, dc2)
        (cold,) = est.estimate(dc1, dc2)
        assert math.hypot(warm.contact.x - cold.x, warm.contact.y - cold.y) < 1e-3 * MM
        assert warm.contact.force == pytest.approx(cold.force, rel=1e-6)


def test_bad_settings_are_named():
    est = ContactEstimator(LAY)
    with pytest.raises(ValueError, match="hints"):
        est.estimate(np.zeros(LAY.n), np.zeros(LAY.n), hints=np.zeros((2, 3)))
    for kw in ({"birth_frames": 0}, {"max_missed": -1}, {"gate": 0.0}, {"motion": -1.0}, {"split_frames": 0}):
        with pytest.raises(ValueError, match=next(iter(kw))):
            ContactTracker(est, **kw)


def _born(tr, contacts, n=3):
    for _ in range(n):
        out = tr.step(contacts)
    return {tc.contact.elements: tc.id for tc in out}


def test_a_contact_with_an_unbounded_sigma_only_continues_the_track_it_touches():
    """A contact whose position carries no information (σ = inf or a NaN position) was
    at distance 0 from every track: it took the id of whichever track came first and
    the finger it belonged to lost its id."""
    from dataclasses import replace

    est = ContactEstimator(LAY, noise=NOISE)
    rng = np.random.default_rng(6)
    (a,) = est.estimate(*frame([0.0, 0.0, 3.0, 0.012], rng))  # on element 0
    (b,) = est.estimate(*frame([0.080, 0.080, 3.0, 0.012], rng))  # on element 8
    for blind in (replace(b, sigma_x=math.inf, sigma_y=math.inf), replace(b, x=math.nan, y=math.nan)):
        tr = ContactTracker(est, birth_frames=2)
        ids = _born(tr, [a, b])
        out = tr.step([blind, a])
        assert {tc.contact.elements: tc.id for tc in out} == ids
        assert all(tc.missed == 0 for tc in out)
        # Far from every track and sharing no element, it is a new candidate, not a match.
        tr2 = ContactTracker(est, birth_frames=2)
        ids_a = _born(tr2, [a])
        out = tr2.step([replace(blind, elements=(4,)), a])
        assert {tc.contact.elements: tc.id for tc in out} == ids_a and tr2.candidates == 1


def test_a_split_of_a_confirmed_contact_waits_for_split_frames_a_press_elsewhere_does_not():
    """With ``birth_frames`` 1, a contact fitted beside a confirmed one on its elements (a
    press sliding across a seam, or releasing element by element, fitted as two disks
    for a frame) was born at once: an extra id on the press for one frame. A split must
    persist ``split_frames``; a press on other elements is still born at once."""
    from dataclasses import replace

    lay = grid_layout(4, 4)  # (on 3x3 every element is next to the middle one)
    est = ContactEstimator(lay, noise=NOISE)
    rng = np.random.default_rng(7)
    (a,) = est.estimate(*frame([0.020, 0.020, 3.0, 0.020], rng, lay))  # across elements 0, 1, 4, 5
    assert len(a.elements) == 4
    part = replace(a, x=a.x + 0.035, y=a.y, elements=a.elements[1:2])  # one of its elements, beyond the gate
    (far,) = est.estimate(*frame([0.120, 0.120, 3.0, 0.012], rng, lay))  # on element 15, not next to them
    tr = ContactTracker(est, birth_frames=1)
    (first,) = tr.step([a])
    assert first.id == 0  # born at once (birth_frames 1)
    out = tr.step([a, part, far])
    assert sorted(tc.id for tc in out) == [0, 1]  # the press elsewhere at once, the split not
    assert {tc.id: tc.contact.elements for tc in out}[1] == far.elements
    out = tr.step([a, part, far])
    assert sorted(tc.id for tc in out) == [0, 1] and tr.candidates == 1
    out = tr.step([a, part, far])  # persisted split_frames (3): a contact
    assert sorted(tc.id for tc in out) == [0, 1, 2]
    # a one-frame split is never a contact
    tr = ContactTracker(est, birth_frames=1)
    for frame_contacts in ([a], [a, part], [a], [a]):
        out = tr.step(frame_contacts)
        assert [tc.id for tc in out] == [0]
    assert tr.rejected == 1


def test_time_going_back_or_not_finite_is_refused_and_changes_nothing():
    """The calibrator refuses time going backwards; the tracker stamped such frames
    on its tracks (a consumer's velocity flips sign) and took NaN."""
    est = ContactEstimator(LAY, noise=NOISE)
    (a,) = est.estimate(*frame([0.0, 0.0, 3.0, 0.012], np.random.default_rng(7)))
    tr = ContactTracker(est, birth_frames=1)
    tr.step([a], t=1.0)
    tr.step([a], t=1.0)  # a repeated time is fine
    tr.step([a])  # so is no time
    for bad in (0.5, math.nan, math.inf):
        with pytest.raises(ValueError, match="t"):
            tr.step([a], t=bad)
    assert tr.frame == 3
    (out,) = tr.step([a], t=1.004)
    assert out.t == 1.004 and out.age == 4


def test_a_tracker_built_afresh_continues_the_contacts_carried_over_with_their_ids():
    """A new tracker (new layout, settings or worker process) given the contacts the old one
    published (through msgpack) matches a held press to its id at once, with its age going
    on; a press elsewhere is new and numbered above every carried id; a tracker that has
    already seen frames takes nothing."""
    import msgpack

    rng = np.random.default_rng(3)
    old = tracker(birth_frames=3)
    press = [0.018, 0.004, 4.0, 0.012]
    for k in range(5):
        last = old.update(*frame(press, rng), t=0.01 * k)
    wire = msgpack.unpackb(msgpack.packb([tc.to_dict() for tc in last]))
    new = tracker(birth_frames=3)
    new.ids_from(7)
    assert new.carry(wire) == 1
    out = new.update(*frame([press, [0.042, 0.042, 3.0, 0.012]], rng), t=0.05)
    assert [tc.id for tc in out] == [last[0].id] and out[0].age == last[0].age + 1
    for k in range(2):
        out = new.update(*frame([press, [0.042, 0.042, 3.0, 0.012]], rng), t=0.06 + 0.01 * k)
    assert [tc.id for tc in out] == [last[0].id, 7]
    assert new.carry(wire) == 0




def _one_late(press, late, rng):
    """A frame of ``press`` in which element ``late``'s reading is its old, untouched one."""
    dc1, dc2 = frame(press, rng)
    dc1[late] = rng.normal(0, NOISE)
    dc2[late] = rng.normal(0, NOISE)
    return dc1, dc2


@pytest.mark.parametrize("late", [0, 1, 3, 4])
def test_a_corner_press_read_in_two_for_a_frame_keeps_one_id(late):
    """``birth_frames`` 1: a frame with one of the four elements' readings late fits no one
    disk (two contacts); the split-off must not be born as a second id."""
    rng = np.random.default_rng(late)
    tr = tracker(birth_frames=1)
    ids = set()
    for k in range(8):
        out = tr.update(*(_one_late(CORNER_PRESS, late, rng) if k == 3 else frame(CORNER_PRESS, rng)))
        assert len(out) == 1, (k, out)
        ids |= {tc.id for tc in out}
    assert ids == {0}


@pytest.mark.parametrize("late", [0, 1, 3, 4])
def test_a_corner_press_read_in_two_at_its_first_frame_is_born_once(late):
    rng = np.random.default_rng(10 + late)
    tr = tracker(birth_frames=1)
    seen = [tr.update(*(_one_late(CORNER_PRESS, late, rng) if k == 0 else frame(CORNER_PRESS, rng)))
            for k in range(8)]
    assert all(len(s) <= 1 for s in seen) and {tc.id for s in seen for tc in s} == {0}
    assert [len(s) for s in seen[2:]] == [1] * 6  # born by the third frame at the latest


def test_a_lone_press_and_two_far_apart_are_born_at_their_first_frame():
    rng = np.random.default_rng(5)
    tr = tracker(birth_frames=1)
    assert len(tr.update(*frame(CORNER_PRESS, rng))) == 1
    tr2 = tracker(birth_frames=1)
    far = [[0.0, 0.0, 3.0, 0.012], [0.08, 0.08, 3.0, 0.012]]  # elements 0 and 8: not neighbours
    assert len(tr2.update(*frame(far, rng))) == 2


def test_a_press_read_in_two_while_an_element_between_is_late_keeps_one_id():
    """Both cores busy: one element of a corner press got its onset reading to the host
    hundreds of ms after the others (its held reading from before the press said
    "untouched" all that while). The press was first seen on one element (born at once),
    then fitted as two contacts for 12 frames, then whole: the split-off was born after
    ``split_frames`` as a second id. The frame's reading times tell: the element between
    the two was last read before the press began, so nothing says the press missed it."""
    rng = np.random.default_rng(21)
    onset_only_0 = frame(CORNER_PRESS, rng)
    for e in (1, 3, 4):
        onset_only_0[0][e] = rng.normal(0, NOISE)
        onset_only_0[1][e] = rng.normal(0, NOISE)
    frames = [(onset_only_0, {0})] + [(_one_late(CORNER_PRESS, 4, rng), {0, 1, 3})] * 12
    frames += [(frame(CORNER_PRESS, rng), {0, 1, 3, 4})] * 4

    def run(with_times):
        tr = tracker(birth_frames=1)
        seen, split = [], 0
        for k, ((dc1, dc2), fresh) in enumerate(frames):
            at = 0.01 * k
            kw = {"at": at, "read_at": _reads(0.0, fresh)} if with_times else {}
            split += len(tr.estimator.estimate(dc1, dc2, hints=tr.hints())) == 2
            seen.append(tr.update(dc1, dc2, t=at, **kw))
        return seen, split

    seen, split = run(True)
    assert split >= 10  # the frames with element 4 late are fitted as two contacts
    assert len(seen[0]) == 1  # the press is born at its first frame
    assert {tc.id for s in seen for tc in s} == {0}
    (last,) = seen[-1]
    assert abs(last.contact.x - CORNER_PRESS[0]) < 0.1 * MM and abs(last.contact.y - CORNER_PRESS[1]) < 0.1 * MM
    # without the reading times only split_frames holds the split-off back: a second id
    seen, _ = run(False)
    assert {tc.id for s in seen for tc in s} == {0, 1}


def _finger(x, y, rng):
    (c,) = ContactEstimator(LAY, noise=NOISE).estimate(*frame([x, y, 3.0, 0.012], rng))
    return c


def test_a_second_finger_next_to_a_held_one_is_born_after_split_frames():
    """The elements between the two were read (heartbeats) after the first finger came: the
    second is told from a split at once, and born after ``split_frames`` as before."""
    rng = np.random.default_rng(22)
    a, b = _finger(0.0, 0.0, rng), _finger(0.04, 0.0, rng)  # on elements 0 and 1: neighbours
    assert a.elements == (0,) and b.elements == (1,)
    tr = tracker(birth_frames=1)
    for k in range(100):  # a held 1 s from t = 0
        (out,) = tr.step([a], t=0.01 * k, at=0.01 * k, read_at=_reads(0.01 * k, {0}, stale_at=0.7))
    seen = [tr.step([a, b], t=1.0 + 0.01 * k, at=1.0 + 0.01 * k, read_at=_reads(1.0 + 0.01 * k, {0, 1}, stale_at=0.7))
            for k in range(4)]
    assert [len(s) for s in seen] == [1, 1, 2, 2]
    assert {tc.id for s in seen for tc in s} == {0, 1}


def test_two_fingers_landing_next_to_each_other_wait_for_a_reading_between_them():
    """Landing together on neighbouring elements, the second is born once the elements
    between them were read after the first came (their next heartbeat), not before."""
    rng = np.random.default_rng(23)
    a, b = _finger(0.0, 0.0, rng), _finger(0.04, 0.0, rng)
    tr = tracker(birth_frames=1)
    assert [tc.id for tc in tr.step([a], t=0.0, at=0.0, read_at=_reads(0.0, {0}))] == [0]
    seen = [tr.step([a, b], t=0.01 * k, at=0.01 * k, read_at=_reads(0.01, {0, 1})) for k in range(1, 30)]
    assert all(len(s) == 1 for s in seen) and tr.candidates == 1
    heartbeat = {**_reads(0.01, {0, 1}), 3: 0.25, 4: 0.29}  # elements 3 and 4 (next to both) reported
    out = tr.step([a, b], t=0.30, at=0.30, read_at=heartbeat)
    assert [tc.id for tc in out] == [0, 1] and out[1].contact.elements == (1,)


def test_a_first_finger_is_born_on_time_when_a_second_lands_diagonally_next_to_it():
    """Event-based reporting: the elements between two diagonal presses were last read a
    heartbeat before. The first finger, alone for a frame, was held back with the second
    (both candidates, neither born) until those elements' next heartbeat: no contact at
    all for up to a second, where the first was born at its third frame before. Only the
    later of the two waits for a reading between them."""
    rng = np.random.default_rng(28)
    a, b = _finger(0.0, 0.0, rng), _finger(0.04, 0.04, rng)  # elements 0 and 4: diagonal
    assert a.elements == (0,) and b.elements == (4,)
    tr = tracker(birth_frames=3)
    seen = [tr.step([a] if k == 0 else [a, b], t=0.01 * k, at=0.01 * k,
                    read_at=_reads(0.01 * k, {0, 4} if k else {0})) for k in range(10)]
    assert [[tc.id for tc in s] for s in seen] == [[], [], [0]] + [[0]] * 7  # the first: its third frame
    heartbeat = {**_reads(0.10, {0, 4}), 1: 0.095, 3: 0.098}  # elements 1 and 3 (next to both) reported
    out = tr.step([a, b], t=0.10, at=0.10, read_at=heartbeat)
    assert [tc.id for tc in out] == [0, 1] and out[1].contact.elements == (4,)


def test_reading_times_leave_a_lone_press_born_at_its_first_frame():
    """Stale readings around a lone press (nothing next to it) hold nothing back."""
    rng = np.random.default_rng(24)
    tr = tracker(birth_frames=1)
    out = tr.update(*frame(CORNER_PRESS, rng), t=0.0, at=0.0, read_at=_reads(0.0, {0, 1, 3, 4}))
    assert [tc.id for tc in out] == [0]


def test_a_press_whole_again_continues_the_confirmed_id_not_a_split_off_closer_to_it():
    """A press fitted as two (the confirmed part on two elements, the split-off on a third)
    and then whole: its whole disk lies closer, in gate units, to the split-off (both
    element-wide σ) than to the confirmed part, and closest-first gave it the candidate's
    track; the confirmed id missed and ended, and the candidate was born as a second id."""
    from dataclasses import replace

    rng = np.random.default_rng(25)
    est = ContactEstimator(LAY, noise=NOISE)
    (whole,) = est.estimate(*frame(CORNER_PRESS, rng))
    assert set(whole.elements) == {0, 1, 3, 4}
    part = _finger(0.02, 0.0, rng)  # across the seam of elements 0 and 1
    off = replace(_finger(0.0, 0.04, rng), elements=(3,))
    tr = tracker(birth_frames=1)
    tr.step([part])
    assert tr._distance(off, whole) < tr._distance(part, whole)  # closest first would give it the split-off
    seen = [tr.step([part, off]) for _ in range(2)] + [tr.step([whole]) for _ in range(4)]
    assert {tc.id for s in seen for tc in s} == {0}
    assert seen[-1][0].contact is whole


def test_a_released_press_with_one_release_reading_late_keeps_one_id():
    """A corner press released: two diagonal elements' release readings are late, so their
    held touched readings stand alone for a few frames, two one-element contacts. The
    confirmed press continued as one of them and the other was new: born after
    ``split_frames`` as a second id (in virtual time, a corner bridge's frames held back
    300 ms at the release). It is made only of a reading the press had used: what is left
    of the press, no new contact."""
    rng = np.random.default_rng(26)
    whole = frame(CORNER_PRESS, rng)
    late = (whole[0].copy(), whole[1].copy())
    for e in (0, 4):  # released; 1 and 3 (diagonal) still hold their touched readings
        late[0][e] = rng.normal(0, NOISE)
        late[1][e] = rng.normal(0, NOISE)
    one = (late[0].copy(), late[1].copy())
    one[0][3] = rng.normal(0, NOISE)
    one[1][3] = rng.normal(0, NOISE)
    held = {e: 0.0 for e in (0, 1, 3, 4)}  # the press's onset readings, held since
    frames = [(whole, held)] * 5 + [(late, {**held, 0: 0.05, 4: 0.05})] * 6 + [(one, {**held, 0: 0.05, 4: 0.05, 3: 0.11})] * 3

    def run(with_times):
        tr = tracker(birth_frames=1)
        seen, two = [], 0
        for k, ((dc1, dc2), reads) in enumerate(frames):
            kw = {"at": 0.01 * k, "read_at": {**_reads(0.01 * k, set()), **reads}} if with_times else {}
            two += len(tr.estimator.estimate(dc1, dc2, hints=tr.hints())) == 2
            seen.append(tr.update(dc1, dc2, t=0.01 * k, **kw))
        return tr, seen, two

    tr, seen, two = run(True)
    assert two == 6  # the frames with the two late elements are two contacts
    assert {tc.id for s in seen for tc in s} == {0} and all(len(s) == 1 for s in seen)
    assert tr.remnants == 6
    tr, seen, _ = run(False)  # without the reading times: a second id
    assert {tc.id for s in seen for tc in s} == {0, 1}


def test_only_readings_a_track_used_are_its_remnant_a_new_reading_is_a_candidate():
    """Split off a confirmed contact on two elements: with the reading it used, the split-off
    is its remnant (dropped, counted); with a newer reading there it may be a new contact."""
    from dataclasses import replace

    rng = np.random.default_rng(27)
    a = _finger(0.02, 0.0, rng)  # across the seam of elements 0 and 1
    assert a.elements == (0, 1)
    left, right = replace(a, elements=(0,)), replace(a, x=0.045, elements=(1,))
    for new_read, remnants, candidates in ((0.0, 1, 0), (0.05, 0, 1)):
        tr = tracker(birth_frames=1)
        tr.step([a], t=0.0, at=0.0, read_at=_reads(0.0, {0, 1}))
        out = tr.step([left, right], t=0.1, at=0.1, read_at={**_reads(0.0, {0, 1}), 1: new_read})
        assert [tc.id for tc in out] == [0] and out[0].contact.elements == (0,)
        assert (tr.remnants, tr.candidates) == (remnants, candidates)


def _event_reads(at, fresh, held=None, stale_at=-0.5):
    """``read_at`` of a 3x3 frame on an event-based skin: the elements in ``fresh`` read at
    ``at``, those in ``held`` (element -> time) at that time (a steady press is not sent
    again), the others at ``stale_at`` (idle: a heartbeat before)."""
    return {**_reads(at, fresh, stale_at), **(held or {})}


def test_two_fingers_sharing_an_element_are_born_without_waiting_for_the_ring():
    """Two fingers 56 mm apart along a diagonal of the middle element, each over the corner
    of four elements, the second a frame after the first: both footprints on element 4. A
    new contact next to another waited until every element next to both had been read
    since the first came; sharing element 4, those were its corners 0 and 8, idle (read a
    heartbeat before, up to a second): the second finger was no contact at all. Left out,
    their readings still leave no one disk that explains the two: born after split_frames."""
    rng = np.random.default_rng(31)
    a, b = [0.0198, 0.0561, 3.0, 0.020], [0.0606, 0.0178, 3.0, 0.020]  # elements 3, 4, 6, 7 and 1, 2, 4, 5
    tr = tracker(birth_frames=1)
    seen = []
    for k in range(8):
        reads = _event_reads(0.01 if k else 0.0, {1, 2, 4, 5} if k else {3, 4, 6, 7}, {3: 0.0, 6: 0.0, 7: 0.0} if k else None)
        seen.append(tr.update(*frame([a] if k == 0 else [a, b], rng), t=0.01 * k, at=0.01 * k, read_at=reads))
    assert [[tc.id for tc in s] for s in seen] == [[0]] * 3 + [[0, 1]] * 5  # the second: its third frame
    for tc in seen[-1]:
        x, y, force, _ = a if tc.id == 0 else b
        assert math.hypot(tc.contact.x - x, tc.contact.y - y) < 0.1 * MM and tc.contact.force == pytest.approx(force, rel=0.02)


def test_two_fingers_fitted_as_one_failed_disk_for_a_frame_keep_apart_ids():
    """The same on a column (elements 7, 4 and 1; 2 N and 4 N): the second finger's first
    frame had its ring unknown, three elements' readings, too few for two disks, and one
    disk failed (the centroid between them). The first finger's track took it and then,
    closest first from that centroid, continued as the second finger; the first finger was
    new and never born (its ring read a heartbeat before). Nor may the failed fit's
    readings count as the track's: the second finger's, not sent again while it is steady,
    then read as what was left of the track (a remnant) and were dropped."""
    rng = np.random.default_rng(32)
    a, b = [0.04, 0.0668, 2.0, 0.020], [0.04, 0.0129, 4.0, 0.020]  # elements 4, 7 and 1, 4
    tr = tracker(birth_frames=1)
    seen = []
    for k in range(8):
        dc1, dc2 = frame([a] if k == 0 else [a, b], rng)
        reads = _event_reads(0.01 * k, {4, 7} if k == 0 else {1, 4} if k == 1 else set(),
                             {7: 0.0} if k == 1 else {1: 0.01, 4: 0.01, 7: 0.0} if k else None)
        if k == 1:  # the ring has no reading of this frame yet
            for e in (0, 2, 3, 5, 6, 8):
                dc1[e] = dc2[e] = reads[e] = math.nan
        seen.append(tr.update(dc1, dc2, t=0.01 * k, at=0.01 * k, read_at=reads))
    assert not seen[1][0].contact.fit_ok and set(seen[1][0].contact.elements) == {1, 4, 7}
    assert [[tc.id for tc in s] for s in seen] == [[0]] * 4 + [[0, 1]] * 4  # split_frames after its frame 2
    for s in seen[2:]:
        for tc in s:
            _, y, force, _ = a if tc.id == 0 else b
            assert abs(tc.contact.y - y) < 0.1 * MM and tc.contact.force == pytest.approx(force, rel=0.02)
    assert tr.remnants == 0
