"""A press held past ``max_touch``, and an element drifting by itself, on an emulated skin.

The virtual mesh's gateway bytes go through the daemon's pipeline in virtual time (pipeline_helpers.drive: the daemon offline, as in
test_daemon_skin_frames). ``max_touch`` is shortened to 20 s and the skin samples at
10 Hz so that a minute of virtual time keeps the test short; the logic is the one the
default 600 s runs (``bench/bench_held_press.py`` holds a press for an hour).
"""

from __future__ import annotations

import numpy as np
import pytest
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, VirtualMesh
from cellbridge.emulator.world.world import Contact, Drift, World
from cellbridge.tactile import ElementParams, grid_layout, skin_response

from support.pipeline_helpers import T0, drive

MAX_TOUCH = 20.0
PRESSED = 5  # the centre element of a 3x3 grid
CENTRE = (0.04, 0.04)
FORCE, DIAMETER = 3.0, 0.020
DRIFTING = 9  # a corner element nothing touches
PRESS_AT = 5.0  # s: baselines (20 readings at 10 Hz) are taken by then
SECTIONS = {"calibration": {"max_touch": MAX_TOUCH, "n_baseline": 20}}


def reads(seconds: float, presses: list[Contact], drifts: list[Drift]) -> list[tuple[float, bytes]]:
    mesh = meshgen.grid(3, 3, gateways=(1,))
    world = World(mesh, presses, drifts=drifts)
    vm = VirtualMesh(mesh, seed=3, world=world, settings=Settings(rate_hz=10), random_epochs=True)
    vm.run(seconds)
    return [(T0 + t / CLOCK_HZ, data) for t, data in vm.serial_chunks[1]]


def test_a_press_held_past_max_touch_keeps_its_contact_and_a_drifting_element_is_never_touched() -> None:
    """On main the press vanished from ``contact`` at max_touch (re-baselined: its id ended
    and the element read nothing), and the corner whose C2 parasitic drifts at 5 fF/s (5× the
    drift the tracker follows) was reported as a contact with a NaN force from ~15 s on."""
    seconds = PRESS_AT + 3.0 * MAX_TOUCH + 5.0
    press = Contact(PRESS_AT, 1e6, *CENTRE, FORCE, DIAMETER)
    drift = Drift(DRIFTING, 3.0, 0.0, 5e-15)
    ids: set[int] = set()
    forces, first, last, gaps = [], None, None, 0
    health = None
    for t, topic, m in drive(reads(seconds, [press], [drift]), seconds, sections=SECTIONS):
        if topic == "element":
            for b, touched in zip(m["bridge"], m["touched"]):
                assert not (b == DRIFTING and touched), f"drifting element touched at {t - T0:.1f} s"
        elif topic == "health":
            health = m
        elif topic == "contact":
            assert m.get("rebaselined", []) == [], m["rebaselined"]
            for c in m["contacts"]:
                assert DRIFTING not in c["elements"], f"drift reported as a contact at {t - T0:.1f} s: {c}"
            ids |= {c["id"] for c in m["contacts"]}
            if m["contacts"]:
                first = t if first is None else first
                last = t
                forces += [c["force"] for c in m["contacts"] if c["missed"] == 0 and t - T0 > PRESS_AT + 1.0]
            elif first is not None:
                gaps += 1
    assert len(ids) == 1 and gaps == 0, (ids, gaps)
    assert first is not None and first - T0 < PRESS_AT + 1.0 and last is not None and last - T0 > seconds - 1.0
    f = np.asarray(forces)
    assert f.size > 300 and np.all(np.abs(f / FORCE - 1.0) < 0.05), (f.min(), f.max())
    cal = health["layout"]["calibration"]  # type: ignore[index]
    assert cal["rebaselines_total"] == 0 and cal["holds_total"] >= 3, cal


def test_a_rebaseline_under_a_contact_is_said_on_the_contact_topic() -> None:
    """Under the press, C1 alone then drifts up until no contact gives the reading (ratio
    ΔC1/ΔC2 past its peak): at max_touch the element is re-baselined, and the next
    ``contact`` message names it in ``rebaselined`` (main said so only in health)."""
    p = ElementParams(side=0.04)
    d1, d2 = skin_response(grid_layout(3, 3), [(*CENTRE, FORCE, DIAMETER)], p)
    dc1, dc2 = float(d1.max()), float(d2.max())
    # by max_touch C1 reads three times the ratio of the peak above C2
    rate = (3.0 * 2.32 * dc2 - dc1) / (MAX_TOUCH - 2.0)
    seconds = PRESS_AT + MAX_TOUCH + 4.0
    press = Contact(PRESS_AT, 1e6, *CENTRE, FORCE, DIAMETER)
    said, ended = [], None
    for t, topic, m in drive(reads(seconds, [press], [Drift(PRESSED, PRESS_AT + 1.0, rate, 0.0)]), seconds,
                             sections=SECTIONS):
        if topic == "contact":
            if m["rebaselined"]:
                said.append((round(t - T0, 1), m["rebaselined"]))
            if not m["contacts"] and ended is None and t - T0 > PRESS_AT + 1.0:
                ended = t - T0
    assert len(said) == 1 and said[0][1] == [PRESSED], said
    assert PRESS_AT + MAX_TOUCH <= said[0][0] <= PRESS_AT + MAX_TOUCH + 1.0, said
    assert ended is not None and ended >= said[0][0] - 0.05, (ended, said)


def test_a_press_held_beside_a_drifting_element_keeps_its_reading_and_force() -> None:
    """The hour of ``bench/bench_held_press.py``, shortened: the corner's C2 drifts by itself
    at 2 fF/s (twice ``max_drift``: its tracker lags it by up to ``enter``) beside the held
    press. On main the skin's common offset ratcheted up through that lag (0.04 fF/s), and
    the pressed element's frozen baseline carried it: its ΔC2 read 4–7 fF low after 3 min
    and 140 fF (10 %) low after an hour, the force 7.6 % off; and in a step where the
    lagging corner was one of two elements reporting, the whole skin moved by half its lag
    (ΔC2 −30 fF, the force −1.7 % for that step). From one minute on (the corner's own
    drift is past ``enter`` by then), the pressed element's ΔC now stays within 5 fF of
    what the press makes, the offset near zero (the world has no common drift) and the
    force within 0.5 %."""
    seconds = 180.0
    p = ElementParams(side=0.04)
    d1, d2 = skin_response(grid_layout(3, 3), [(*CENTRE, FORCE, DIAMETER)], p)
    truth = np.array([d1.max(), d2.max()])
    press = Contact(PRESS_AT, 1e6, *CENTRE, FORCE, DIAMETER)
    err, forces, health = [], [], None
    for t, topic, m in drive(reads(seconds, [press], [Drift(DRIFTING, 0.0, 0.0, 2e-15)]), seconds,
                             sections=SECTIONS):
        if topic == "element":
            err += [np.array([a, c]) - truth for b, a, c in zip(m["bridge"], m["dc1"], m["dc2"])
                    if b == PRESSED and t - T0 > 60.0]
            assert not any(b == DRIFTING and x for b, x in zip(m["bridge"], m["touched"]))
        elif topic == "health":
            health = m["layout"]["calibration"]
        elif topic == "contact":
            forces += [c["force"] for c in m["contacts"] if c["missed"] == 0 and t - T0 > 60.0]
    e = np.abs(np.asarray(err))
    assert len(err) > 1000 and e.max() < 5e-15, (len(err), e.max(axis=0))
    assert health is not None
    assert np.all(np.abs(health["common_offset"]) < 3e-15), health["common_offset"]
    f = np.asarray(forces)
    assert f.size > 1000 and np.all(np.abs(f / FORCE - 1.0) < 0.005), (f.min(), f.max())


@pytest.mark.parametrize("rates", [(0.0, 5e-15), (5e-15, 0.0)])
def test_one_layer_drifting_alone_is_followed_not_touched(rates) -> None:
    """No press at all: an element whose one layer drifts at 5 fF/s for a minute (290 fF,
    six times ``enter``) is never touched, and its baseline follows the drift: what it
    reads stays within about ``enter`` (plus the drift over ``negative_after``), not
    growing with the drift."""
    seconds = 60.0
    touched_ever = False
    late = []
    for t, topic, m in drive(reads(seconds, [], [Drift(DRIFTING, 2.0, *rates)]), seconds,
                             sections=SECTIONS):
        if topic == "element":
            for b, touched, a, c in zip(m["bridge"], m["touched"], m["dc1"], m["dc2"]):
                if b == DRIFTING:
                    touched_ever |= touched
                    if t - T0 > seconds - 30.0:
                        late.append(max(abs(a), abs(c)))
        elif topic == "contact":
            assert not m["contacts"], m
    assert not touched_ever
    assert len(late) > 200 and max(late) < 70e-15, max(late)
