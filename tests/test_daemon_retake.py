"""The retake of a frame whose late onset came after it was taken (daemon/moment.py), attacked.

The skin frames are taken as the service's contact loop takes them (a look when data came
or when ``Moments.due`` says, no pacer: it only spaces the looks), and each frame taken is
estimated and tracked by the daemon's own contact stage, as the worker does.
"""

from __future__ import annotations

import math

import numpy as np

from cellbridge.daemon.contacts import ContactSnapshot, ContactStage
from cellbridge.daemon.elements import default_params
from cellbridge.daemon.moment import Moments
from cellbridge.tactile import grid_layout, skin_response

from pipeline_helpers import published
from test_daemon_moment import PERIOD, _idle_frames_taken, _onset

TIMEOUT, MAX_LAG, HELD_WAIT = 2.0, 0.5, 0.5
ENTER, LEAVE = 1e-13, 0.5e-13
NOISE = 2e-15


class Skin:
    """A 4x4 event-based skin on mesh time: each element sends a held reading when its
    reading changes (no heartbeat within the few hundred ms simulated), each ``delay`` s
    after its frame unless told otherwise; the contact loop looks at every millisecond
    the data or ``due`` ask for, and the daemon's contact stage tracks each frame taken."""

    def __init__(self, max_missed: int = 2, birth_frames: int = 1) -> None:
        self.layout = grid_layout(4, 4)
        n = self.layout.n
        self.m = Moments(n, 64, self.layout.corner_edges)
        self.stage = ContactStage(self.layout, default_params(self.layout), NOISE, "capacitance",
                                  birth_frames=birth_frames, max_missed=max_missed)
        self.pending: list[tuple[float, int, float, np.ndarray]] = []  # (arrival, row, t, dc)
        self.frames: list[tuple[float, float, list[dict]]] = []  # (now, t of the frame, contacts)
        self.touched = np.zeros(n, dtype=bool)

    def dc(self, row: int, force: float) -> np.ndarray:
        if force <= 0:
            return np.zeros(2)
        x, y = self.layout.centres[row]
        d1, d2 = skin_response(self.layout, [(x, y, force, 0.012)])
        return np.array([d1[row], d2[row]])

    def send(self, row: int, k: int, force: float, delay: float = 0.003) -> None:
        t = round(k * PERIOD, 9)
        self.pending.append((t + delay, row, t, self.dc(row, force)))

    def _deliver(self, now: float) -> bool:
        came = [p for p in self.pending if p[0] <= now + 1e-12]
        self.pending = [p for p in self.pending if p[0] > now + 1e-12]
        for arrival, row, t, dc in sorted(came, key=lambda p: p[0]):
            n = self.layout.n
            self.m.record(np.array([row]), np.array([t]), np.array([0], dtype=np.uint64), dc[None, :], True,
                          arrival, np.full((n, 2), ENTER), np.full((n, 2), LEAVE), np.array([True]),
                          np.array([True]), np.array([PERIOD]))
            self.touched[row] = bool((dc > ENTER).any())
            self.m.settle(np.array([row]), self.touched)
        return bool(came)

    def run(self, start: float, end: float) -> None:
        now = start
        while now < end:
            now = round(now + 0.001, 9)
            came = self._deliver(now)
            if came or self.m.due(now, TIMEOUT, MAX_LAG, HELD_WAIT) <= now:
                got = self.m.take(now, TIMEOUT, MAX_LAG, held_wait=HELD_WAIT)
                if got is not None:
                    # as LayoutStages.snapshot makes it (what the moment says beyond ``unknown``, too)
                    snap = ContactSnapshot(got.dc, got.touched, now, got.t_sample, got.cycle, self.layout.ids,
                                           got.t, got.unknown, *got[6:])
                    self.frames.append((now, got.t, self.stage.run(snap)))


def _warm(skin: Skin) -> float:
    """Every element reported 50 frames untouched (delays learnt); the host time after."""
    for k in range(50):
        for row in range(skin.layout.n):
            skin.send(row, k, 0.0)
    skin.run(-0.001, 50 * PERIOD)
    return 50 * PERIOD


def _ids_on(skin: Skin, element: int) -> set[int]:
    return {c["id"] for _, _, cs in skin.frames for c in cs if element in c["elements"]}


def test_a_retake_does_not_count_a_frame_twice_against_a_contact_elsewhere() -> None:
    """A light press on element 0 dips under the touch threshold for two frames (70, 71):
    with ``max_missed = 2`` it keeps its id. A press on element 15, far away, has its onset
    of frame 70 retried: it reaches the host after frame 70 was taken, and frame 70 is taken
    again. The tracker counts that retake as one more frame the light press was missed in:
    it ends after frame 71 and comes back under a new id at frame 72."""
    def run(late: bool) -> Skin:
        skin = Skin(max_missed=2)
        now = _warm(skin)
        for k in range(60, 90):  # the light press, under the threshold at frames 70 and 71
            if k in (60, 70, 72):
                skin.send(0, k, 0.0 if k == 70 else 1.0)
        skin.send(15, 70, 3.0, delay=0.012 if late else 0.003)
        skin.run(now, 90 * PERIOD)
        return skin

    on_time = run(late=False)
    assert on_time.m.retaken == 0 and len(_ids_on(on_time, 0)) == 1  # (the dip alone keeps the id)
    late = run(late=True)
    assert late.m.retaken == 1  # (frame 70 was taken again for element 15's late onset)
    assert len(_ids_on(late, 0)) == 1, sorted(_ids_on(late, 0))


def test_a_retake_does_not_count_a_frame_twice_for_a_contact_to_be_born() -> None:
    """``birth_frames = 3``: a reading over the threshold on element 5 for two frames (69,
    70: a knock, a spike) is no contact. Element 15's press has its onset of frame 70
    retried, and frame 70 is taken again: the tracker counts the spike's third frame in it,
    and a contact is born that two frames of readings never made."""
    def run(late: bool) -> Skin:
        skin = Skin(birth_frames=3)
        now = _warm(skin)
        skin.send(5, 69, 1.0)
        skin.send(5, 71, 0.0)
        skin.send(15, 70, 3.0, delay=0.012 if late else 0.003)
        skin.run(now, 80 * PERIOD)
        return skin

    assert not _ids_on(run(late=False), 5)  # (two frames: no contact)
    late = run(late=True)
    assert late.m.retaken == 1
    assert not _ids_on(late, 5), sorted(_ids_on(late, 5))


def test_a_late_onset_already_released_in_the_frame_taken_takes_nothing_again() -> None:
    """A tap shorter than its bridge's retry: the onset of frame f and the release of
    frame f+1 reach the host in one read, after frame f+1 was taken. The element is
    untouched in the frame taken, as it was: taking it again estimates (and publishes) the
    very same frame twice, and counts a retake in health that changed nothing."""
    m, now = _idle_frames_taken(3)
    frame = m.t_moment
    zero = np.zeros((2, 2))
    now += 0.004
    m.record(np.array([0, 0]), np.array([frame - PERIOD, frame]), np.zeros(2, dtype=np.uint64),
             np.array([[2.0, 2.0], [0.0, 0.0]]), False, now, zero + 1.0, zero + 0.5, np.array([True, True]),
             np.array([True, True]), np.array([PERIOD, PERIOD]))
    m.settle(np.array([0]), np.zeros(2, dtype=bool))
    got = m.take(now, timeout=2.0, max_lag=0.5, held_wait=0.5)
    assert got is None, (got.t == frame, got.touched)
    assert m.retaken == 0


def test_a_late_onset_seen_by_the_calibrator_as_drift_takes_nothing_again() -> None:
    """An element reading above ``enter`` that no contact gives is drift to the calibrator:
    not touched (``settle`` says so on the very read). Its late held reading "began a
    touch" only by the moments' own guess from the thresholds: the frame taken again is
    the frame taken, unchanged."""
    m, now = _idle_frames_taken(3)
    frame = m.t_moment
    zero = np.zeros((2, 2))
    now += 0.004
    m.record(np.array([1]), np.array([frame]), np.zeros(1, dtype=np.uint64), np.full((1, 2), 2.0), True, now,
             zero + 1.0, zero + 0.5, np.array([True]), np.array([True]), np.array([PERIOD]))
    m.settle(np.array([1]), np.zeros(2, dtype=bool))  # the calibrator: drift, not a touch
    got = m.take(now, timeout=2.0, max_lag=0.5, held_wait=0.5)
    assert got is None, (got.t == frame, got.touched)


def test_a_late_onset_pending_when_the_layout_grows_is_still_taken_again() -> None:
    """The late onset came, then (before the contact loop looked) a bridge's HELLO extended
    the layout: the moments are rebuilt and adopt the old ones' readings. The retake asked
    for is lost, and the onset's contact comes a frame later, as before the change."""
    m, now = _idle_frames_taken(3)
    frame = m.t_moment
    now += 0.004
    _onset(m, 0, frame, now)
    grown = Moments(3, m.depth)
    grown.adopt(m, np.array([0, 1]), np.array([0, 1]))
    assert grown.unseen()
    assert grown.due(now, timeout=2.0, max_lag=0.5, held_wait=0.5) <= now
    got = grown.take(now, timeout=2.0, max_lag=0.5, held_wait=0.5)
    assert got is not None and got.t == frame and got.touched[0]


# -- what held up (these pass before and after the fixes) ------------------------------------


def test_held_a_retake_is_looked_at_once_then_due_is_a_frame_on() -> None:
    """No busy loop: once the look after a late onset took (or declined) the frame again,
    ``due`` names the next frame, not ``now``, and an idle skin has nothing unseen."""
    m, now = _idle_frames_taken(3)
    frame = m.t_moment
    now += 0.004
    _onset(m, 0, frame, now)
    m.take(now, timeout=2.0, max_lag=0.5, held_wait=0.5)
    assert m.due(now, timeout=2.0, max_lag=0.5, held_wait=0.5) > now
    assert m.take(now, timeout=2.0, max_lag=0.5, held_wait=0.5) is None


def test_held_an_element_subscriber_joining_mid_press_gets_force_and_area() -> None:
    from daemon_traffic import Skin as Traffic
    from test_daemon_pipeline import STRADDLE, make, press, settle, topic

    sk, p = Traffic(), make()
    p.want({"contact"})
    settle(p, sk)
    assert not [t for t, _ in published(press(p, sk, STRADDLE, 60, 5)) if t == "element"]
    p.want({"contact", "element"})
    el = topic(press(p, sk, STRADDLE, 65, 1), "element")
    forces = [f for f, v in zip(el["force"], el["valid"]) if v]
    assert el["touched"] == [True, True, False, False] and sum(forces) > 2.5, el
    p.want({"raw"})  # nobody on contact: no look is due, whatever a late onset asked for
    assert p.contact_due(1e10) == math.inf and p.contact_job(1e10) is None
