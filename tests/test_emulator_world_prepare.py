"""A bridge process's world: the capacitances a new press gives are computed when the
world's contacts come (``World.prepare``), not in the readout of the frame that shows it,
and a press that touches none of the world's elements costs no skin response at all."""

from __future__ import annotations

import math
from typing import Any

import pytest
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import CLOCK_HZ
from cellbridge.emulator.world import world as world_module
from cellbridge.emulator.world.world import Contact, World

MESH = meshgen.grid(4, 4, None)
#: a 20 mm, 3 N press on the seam of four elements in the grid's lower left
SEAM = (0.04, 0.04, 3.0, 0.02)


@pytest.fixture
def responses(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Counts the skin responses the worlds compute (one entry per call)."""
    calls: list[int] = []
    real = world_module.skin_response

    def counted(*args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(world_module, "skin_response", counted)
    return calls


def _touched_and_far() -> tuple[int, int]:
    whole = World(MESH, [Contact(0.0, math.inf, *SEAM)])
    c1, _ = whole.capacitances(0.5)
    touched = [b for b, i in whole.index.items() if c1[i] != whole.rest[0]]
    far = [b for b in MESH.ids if b not in touched
           and min(abs(p - q) for p, q in zip(MESH.bridge(b).position, SEAM[:2])) > MESH.side + SEAM[3]]
    assert touched and far
    return touched[0], far[0]


def test_a_press_elsewhere_costs_a_bridges_world_no_skin_response(responses: list[int]) -> None:
    _, far = _touched_and_far()
    responses.clear()
    world = World(MESH, bridges=[far])
    world.set_contacts([Contact(1.0, 1.0, *SEAM)], 1.0)
    sense = world.sense_for(far)
    assert sense(int(1.5 * CLOCK_HZ)) == world.rest
    assert responses == []


def test_prepare_computes_the_press_before_its_first_gate_and_changes_no_value(responses: list[int]) -> None:
    touched, _ = _touched_and_far()
    press = Contact(1.0, 0.3, *SEAM)
    plain = World(MESH, bridges=[touched])
    plain.set_contacts([press], 1.001)
    expected = [plain.sense_for(touched)(int(t * CLOCK_HZ)) for t in (0.99, 1.005, 1.2, 1.31)]
    assert expected[1] != plain.rest

    world = World(MESH, bridges=[touched])
    world.set_contacts([press], 1.001)
    world.prepare(1.001)
    before = len(responses)
    assert before >= 1
    sense = world.sense_for(touched)
    # a lazy sample of the gate before the press (rest), then the press's gates, then after it
    got = [sense(int(t * CLOCK_HZ)) for t in (0.99, 1.005, 1.2, 1.31)]
    assert got == expected
    assert len(responses) == before  # nothing computed at the samples: prepare did it


def test_a_sample_of_a_gate_before_the_press_does_not_evict_the_press(responses: list[int]) -> None:
    touched, _ = _touched_and_far()
    responses.clear()
    world = World(MESH, bridges=[touched])
    world.set_contacts([Contact(1.0, 5.0, *SEAM)], 1.001)
    sense = world.sense_for(touched)
    for t in (1.01, 0.99, 1.02, 0.995, 1.03):  # relays' lazy samples interleave with the press's
        sense(int(t * CLOCK_HZ))
    assert len(responses) == 1
