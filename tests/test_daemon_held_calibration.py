"""Event-based skins and the calibrator's common mode: a held reading takes part in every step.

An event-based bridge sends only when its element changes (and a heartbeat): the readings
of one calibration step are then mostly those of the elements under a press. Taken alone,
they rose alike, which is what a common step of the whole skin looks like; the press was
absorbed as drift and every other element went negative (a corner press came out on two
elements of four, and a ghost contact sat on the gateway's element). A held reading
stands for the frames after it, so it takes part until a new one comes.
"""

from __future__ import annotations

import numpy as np
import pytest
from cellbridge.daemon.core.config import DEFAULT_NOISE, parse_config
from cellbridge.daemon.core.elements import ElementStage
from cellbridge.daemon.core.layout import LayoutStages
from cellbridge.tactile import CalibrationConfig, ElementParams
from cellbridge.tactile.layout import grid_layout

pF = 1e-12
REST = np.array([19.44 * pF, 15.67 * pF])
PRESS = np.array([0.46 * pF, 0.282 * pF])  # one element's share of a corner press (C1, C2)
UNDER = np.array([5, 6, 9, 10])  # rows under a press at the corner of four elements


RATE = 100.0  # Hz: sample k is taken at k / RATE s


def test_a_corner_press_reported_element_by_element_is_one_press_on_four_elements() -> None:
    # A 4x4 event-based skin in virtual time: every element sends a heartbeat a second
    # (the baselines), then a press at the corner of four elements; their samples of the
    # press's first frame reach the host two by two, as relays deliver them. The first
    # read's two elements alone rose alike, and were taken for a common step of the skin:
    # the press was absorbed as drift (in the emulated skin a corner press came out on two
    # elements of four, the idle elements went negative by its ΔC, and a ghost contact
    # sat on the gateway's element for seconds).
    layout = grid_layout(4, 4)
    skin = LayoutStages(parse_config({"link": [{"name": "gw", "url": "/dev/null"}],
                                      "calibration": {"n_baseline": 3}}), layout)
    n = layout.n

    def read(rows: np.ndarray, index: int, now: float, dc: np.ndarray) -> None:
        k = rows.shape[0]
        caps = np.tile(REST + dc, (k, 1))
        skin.step(rows, np.tile([19_593, 15_786], (k, 1)), np.zeros((k, 2), dtype=bool), caps,
                  np.full(k, index / RATE), np.full(k, index * 500_000, dtype=np.uint64), now,
                  np.ones(k, dtype=bool), np.ones(k, dtype=bool), np.full(k, 1.0 / RATE))

    everyone = np.arange(n)
    for beat in range(4):  # heartbeats: the baselines (3 readings each), then one more
        read(everyone, 100 * beat, beat + 0.005, np.zeros(2))
    assert skin.snapshot(3.02, 5.0, scheduled=False) is not None
    press = 4 * 100  # the first frame of the press, 4 s
    read(UNDER[[1, 3]], press, 4.006, PRESS)  # two of the four first, the others 6 ms later
    read(UNDER[[0, 2]], press, 4.012, PRESS)
    snap = skin.snapshot(4.05, 5.0, scheduled=False)
    assert snap is not None and snap.t_frame >= press / RATE
    assert set(np.flatnonzero(snap.touched).tolist()) == set(UNDER.tolist())
    np.testing.assert_allclose(snap.dc[UNDER], np.tile(PRESS, (4, 1)), atol=5e-15)
    idle = np.setdiff1d(everyone, UNDER)
    assert skin.elements is not None
    # no offset on the rest of the skin (their held readings are a second old: unknown in the
    # frame, by the DATA fallback's one-period rule, but their baselines stayed)
    assert np.abs(REST - skin.elements.calibrator.baseline[idle]).max() < 5e-15
    assert snap.unknown is not None and snap.unknown[idle].all()
    assert skin.elements.calibrator.health()["common_jumps"] == 0


def groups(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    last = {r: i for i, r in enumerate(rows.tolist())}
    return np.fromiter(last, np.int64, len(last)), np.fromiter(last.values(), np.int64, len(last))


def ready_stage(held: bool) -> tuple[ElementStage, float]:
    """A 4x4 skin whose every element sent a few quiet readings (held or periodic)."""
    layout = grid_layout(4, 4)
    stage = ElementStage(layout, ElementParams(side=layout.side), CalibrationConfig(n_baseline=3), DEFAULT_NOISE)
    rows = np.arange(layout.n)
    rng = np.random.default_rng(1)
    t = 0.0
    for _ in range(5):
        t += 0.1
        caps = REST + rng.normal(0, 1e-16, (layout.n, 2))
        stage.step(rows, caps, groups(rows), t, np.full(layout.n, held))
    assert stage.calibrator.ready.all()
    return stage, t


def send(stage: ElementStage, t: float, rows: np.ndarray, held: bool = True) -> dict[str, np.ndarray]:
    caps = np.tile(REST + PRESS, (rows.shape[0], 1))
    return stage.step(rows, caps, groups(rows), t, np.full(rows.shape[0], held)).columns


@pytest.mark.parametrize("first", [UNDER[:2], UNDER[1:3], UNDER[2:], UNDER[:3]])
def test_the_first_elements_of_a_press_to_report_are_no_common_step(first) -> None:
    # The elements under a press report one by one, whichever a read brings first; the
    # skin's other elements are held at rest meanwhile.
    stage, t = ready_stage(held=True)
    res = send(stage, t + 0.1, first)
    np.testing.assert_allclose(res["dc1"], PRESS[0], atol=5e-15)
    assert stage.touched[first].all()
    assert np.abs(stage.calibrator.common_drift).max() < 5e-15
    rest = np.setdiff1d(UNDER, first)
    res = send(stage, t + 0.2, rest)
    np.testing.assert_allclose(res["dc1"], PRESS[0], atol=5e-15)
    assert stage.touched[UNDER].all() and stage.touched.sum() == UNDER.shape[0]


def test_a_held_reading_stops_standing_after_tau() -> None:
    # A bridge silent for longer than the drift tracker's time constant is silent, not
    # held: its old reading no longer takes part (the common offset then comes from the
    # elements that report, as for any silent element).
    stage, t = ready_stage(held=True)
    later = t + stage.calibrator.config.tau + 1.0
    others = np.arange(2, 16)
    caps = np.tile(REST + 0.3 * pF, (others.shape[0], 1))  # a common step, seen by those that report
    stage.step(others, caps, groups(others), later, np.full(others.shape[0], True))
    assert stage.calibrator.common_drift[0] == pytest.approx(0.3 * pF, abs=5e-15)
    assert not stage.touched.any()


def test_periodic_readings_are_not_held_over() -> None:
    # A periodic element without a reading in a step has no reading there (lost or late):
    # nothing is filled in for it.
    stage, t = ready_stage(held=False)
    stage.step(UNDER[:2], np.tile(REST + PRESS, (2, 1)), groups(UNDER[:2]), t + 0.1, np.zeros(2, dtype=bool))
    assert np.isnan(stage._standing(np.full((16, 2), np.nan))).all()


@pytest.mark.parametrize("heartbeat, settings", [
    (20.0, {"health": {"bridge_timeout": 30.0}}),  # a long heartbeat (SET_REPORTING allows 600 s)
    (1.0, {"calibration": {"n_baseline": 3, "tau": 0.5}}),  # a short drift time constant
])
def test_a_held_reading_stands_while_its_bridge_is_live_even_past_tau(heartbeat, settings) -> None:
    # A held reading stood for tau (10 s) only. A bridge whose heartbeat is longer than
    # that (and a bridge_timeout that keeps it live), or a tau shorter than the heartbeat,
    # let the idle elements' readings lapse between heartbeats: the first elements of a
    # press then stepped alone, rose alike, and were absorbed as a common step of the skin
    # (ΔC 0, nothing touched, the offset at the press's ΔC) — the fault the held fill was
    # made for. A held reading stands while its bridge is live (bridge_timeout), tau at least.
    layout = grid_layout(4, 4)
    cfg = {"link": [{"name": "gw", "url": "/dev/null"}], "calibration": {"n_baseline": 3}}
    cfg.update(settings)
    skin = LayoutStages(parse_config(cfg), layout)
    everyone = np.arange(layout.n)

    def read(rows: np.ndarray, t: float, dc: np.ndarray) -> None:
        k = rows.shape[0]
        index = round(t * RATE)
        skin.step(rows, np.tile([19_593, 15_786], (k, 1)), np.zeros((k, 2), dtype=bool), np.tile(REST + dc, (k, 1)),
                  np.full(k, index / RATE), np.full(k, index * 500_000, dtype=np.uint64), t + 0.005,
                  np.ones(k, dtype=bool), np.ones(k, dtype=bool), np.full(k, 1.0 / RATE))

    for beat in range(4):  # heartbeats: the baselines (3 readings each), then one more
        read(everyone, beat * heartbeat, np.zeros(2))
    press = 3 * heartbeat + 0.75 * heartbeat  # between two heartbeats
    read(UNDER[[1, 3]], press, PRESS)
    read(UNDER[[0, 2]], press + 0.01, PRESS)
    assert skin.elements is not None
    cal = skin.elements.calibrator
    assert cal.touched[UNDER].all() and cal.touched.sum() == UNDER.shape[0]
    np.testing.assert_allclose(cal.baseline[UNDER], np.tile(REST, (4, 1)), atol=5e-15)
    assert np.abs(cal.common_drift).max() < 5e-15 and cal.health()["common_jumps"] == 0


def test_held_readings_stand_across_a_bridge_joining_the_layout() -> None:
    # A late bridge's HELLO extends the layout (normal while a large skin boots bridge by
    # bridge); the elements that kept their place keep their baselines and touch state, and
    # their held readings went with the old stage: until each sent again (a heartbeat, a
    # second) a press's first elements stepped alone and were absorbed as a common step.
    layout = grid_layout(4, 4)
    skin = LayoutStages(parse_config({"link": [{"name": "gw", "url": "/dev/null"}],
                                      "calibration": {"n_baseline": 3}}), None)
    geometry = {int(b) + 1: (float(x), float(y), layout.side) for b, (x, y) in zip(layout.ids, layout.centres)}
    late = 16
    assert skin.hello({b: g for b, g in geometry.items() if b != late})
    bridges = np.array(sorted(b for b in geometry if b != late))

    def read(ids: np.ndarray, index: int, now: float, dc: np.ndarray) -> None:
        k = ids.shape[0]
        rows = skin.rows_of(ids, np.zeros(k, dtype=np.int64))
        skin.step(rows, np.tile([19_593, 15_786], (k, 1)), np.zeros((k, 2), dtype=bool), np.tile(REST + dc, (k, 1)),
                  np.full(k, index / RATE), np.full(k, index * 500_000, dtype=np.uint64), now,
                  np.ones(k, dtype=bool), np.ones(k, dtype=bool), np.full(k, 1.0 / RATE))

    for beat in range(4):  # heartbeats: the baselines (3 readings each), then one more
        read(bridges, 100 * beat, beat + 0.005, np.zeros(2))
    assert skin.hello({late: geometry[late]})  # the late bridge joins at 3.5 s
    under = UNDER + 1  # bridge ids of the rows under a corner press
    read(under[[1, 3]], 400, 4.006, np.asarray(PRESS))
    read(under[[0, 2]], 400, 4.012, np.asarray(PRESS))
    assert skin.elements is not None
    cal = skin.elements.calibrator
    rows = skin.rows_of(under, np.zeros(4, dtype=np.int64))
    assert cal.touched[rows].all() and cal.touched.sum() == 4
    np.testing.assert_allclose(cal.baseline[rows], np.tile(REST, (4, 1)), atol=5e-15)
    assert np.abs(cal.common_drift).max() < 5e-15 and cal.health()["common_jumps"] == 0
